# The acquisition server's image (docker-compose.yml builds it). It carries every folder the
# server reads at run time (tests/test_container.py checks this list against the code), runs
# as a user of its own, and reports its health from the status route.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml constraints.txt README.md alembic.ini ./
COPY backend backend
COPY hardware hardware
COPY merge merge
COPY alembic alembic
COPY frontend frontend
RUN pip install --no-cache-dir -c constraints.txt -e . \
    && useradd --system --create-home --home-dir /home/mosaic mosaic \
    && mkdir -p /data && chown mosaic:mosaic /data
USER mosaic
ENV MOSAIC_DATA_DIR=/data
EXPOSE 8000 8080
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/api/instrument', timeout=4)"
CMD ["mosaic-afm", "serve", "--host", "0.0.0.0", "--port", "8000"]
