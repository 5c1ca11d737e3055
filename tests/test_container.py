"""The image's build context carries every folder the server reads at run time.

No Docker engine runs here, so the Dockerfile's COPY lines are played into a folder and the
server's app is built from that folder alone: a folder the image would miss (as frontend/
once was) fails here, not at `docker compose up`."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _copies() -> list[str]:
    sources: list[str] = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"]:
            sources.extend(words[1:-1])
    return sources


def test_the_image_builds_the_app_from_its_copies_alone(tmp_path: Path) -> None:
    context = tmp_path / "app"
    context.mkdir()
    for source in _copies():
        src = ROOT / source
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, context / source)
    probe = (
        "import backend, pathlib; assert pathlib.Path(backend.__file__).is_relative_to("
        f"{str(context)!r}), backend.__file__\n"
        "from backend.api.app import create_app\n"
        "from backend.settings import Settings\n"
        f"create_app(Settings(data_dir={str(tmp_path / 'data')!r}))\n"
        "from backend.db.session import migrate\n"
        f"migrate('sqlite:///{tmp_path / 'data' / 'm.sqlite'}')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=context,
        env={"PYTHONPATH": str(context), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]


def test_the_image_runs_as_its_own_user_and_reports_its_health() -> None:
    text = (ROOT / "Dockerfile").read_text()
    users = [line.split()[1] for line in text.splitlines() if line.startswith("USER ")]
    assert users and users[-1] not in ("root", "0")
    assert "HEALTHCHECK" in text and "/api/instrument" in text
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert not set(_copies()) & set(ignored)
    assert "build: ." in (ROOT / "docker-compose.yml").read_text()
