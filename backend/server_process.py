"""The server as a child process (``mosaic-afm serve``): for integration tests that kill and
restart it, and for benchmarks that measure it from outside."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

#: The token the child server is given (it serves the simulated instrument by default).
TOKEN = "server-process-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}", "X-Operator": "server_process"}


#: Ports tried by :meth:`ServerProcess.start` when the one chosen is taken before the bind.
BIND_TRIES = 3


class PortTaken(RuntimeError):
    """The port chosen was taken by another process before the server could bind it."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class ServerProcess:
    """``python -m backend.cli serve`` on a free port with its own data dir."""

    def __init__(self, data_dir: Path, *, port: int | None = None, **env: str) -> None:
        self.data_dir = data_dir
        #: a port of our own choosing may be taken between the choice and the server's bind (by
        #: any process's outgoing connection): then another is chosen (:meth:`start`)
        self._chosen = port is None
        self.port = port or free_port()
        self.env = {
            **os.environ,
            "MOSAIC_DATA_DIR": str(data_dir),
            "MOSAIC_API_TOKEN": TOKEN,
            "MOSAIC_INSTRUMENT": "sim://",
            "MOSAIC_SIM_SPEED": "max",
            **env,
        }
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def log(self) -> Path:
        """The server's output, one file per port tried."""
        return self.data_dir / f"server-{self.port}.log"

    def start(self, timeout: float = 60.0) -> ServerProcess:
        for _ in range(BIND_TRIES - 1):
            try:
                return self._start(timeout)
            except PortTaken:
                self.port = free_port()
        return self._start(timeout)

    def _start(self, timeout: float) -> ServerProcess:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "backend.cli", "serve", "--port", str(self.port)],
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                said = self.log.read_text()[-2000:]
                if self._chosen and "address already in use" in said:
                    raise PortTaken(said)
                raise RuntimeError(f"the server exited: {said}")
            try:
                if httpx.get(self.url + "/api/auth/whoami", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"the server did not come up: {self.log.read_text()[-2000:]}")

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs, as in a power cut of the server."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=60)


def wait_for(
    client: httpx.Client, url: str, done: Any, *, timeout: float = 300.0, poll: float = 0.05
) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        body: dict[str, Any] = client.get(url).json()
        if done(body):
            return body
        if time.monotonic() > deadline:
            raise AssertionError(f"{url} never got there: {body}")
        time.sleep(poll)
