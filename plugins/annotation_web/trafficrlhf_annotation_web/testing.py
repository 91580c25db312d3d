"""Helpers to test the app against a real server: a free loopback port and a server subprocess."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time

import httpx

__all__ = ["Server", "free_port"]


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Server:
    """``trafficrlhf feedback serve`` semantics in a subprocess: start, wait until healthy, kill."""

    def __init__(self, db_path: str, port: int | None = None, synchronous: str = "FULL") -> None:
        self.db_path, self.port, self.synchronous = db_path, port or free_port(), synchronous
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """``http://127.0.0.1:PORT``."""
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 30.0) -> Server:
        """Start the subprocess and wait (bounded) until ``/healthz`` answers."""
        code = ("from trafficrlhf_annotation_web import serve; "
                f"serve({self.db_path!r}, '127.0.0.1', {self.port}, log_level='error', "
                f"synchronous={self.synchronous!r})")
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                error = self.proc.stderr.read().decode()[-2000:]  # type: ignore[union-attr]
                self._close_pipe()
                raise RuntimeError(f"server exited: {error}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return self
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"server on {self.url} not healthy after {timeout_s} s")

    def kill9(self) -> None:
        """SIGKILL: no shutdown handler runs, like a crash."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self._close_pipe()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after 10 s."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill9()
        self._close_pipe()

    def _close_pipe(self) -> None:
        """Close the stderr pipe of a finished server (left open, it leaks a file handle per server)."""
        if self.proc is not None and self.proc.poll() is not None and self.proc.stderr is not None:
            self.proc.stderr.close()
