"""Hostile HTTP against a real server: bodies sent outside /api are refused (405) without being read, malformed
requests and dropped connections leave no traceback or error in the log; and the 422 of a bad choice lists
exactly the choices the campaign accepts."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from trafficrlhf_annotation_web.testing import free_port

BODY_BYTES = 100 * 1024 * 1024


@pytest.fixture()
def logged_server(campaign_db, tmp_path: Path) -> Iterator[tuple[str, int, Path]]:  # type: ignore[no-untyped-def]
    """A real server at uvicorn's default log level for `feedback serve` (warning); yields (url, pid, log file)."""
    port, log_path = free_port(), tmp_path / "server.log"
    code = f"from trafficrlhf_annotation_web import serve; serve({campaign_db[0]!r}, '127.0.0.1', {port})"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=log,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()
            try:
                if httpx.get(url + "/healthz", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        yield url, proc.pid, log_path
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as handle:
        return next(int(line.split()[1]) for line in handle if line.startswith("VmRSS")) / 1024


def post_big(port: int, path: str, out: list[tuple[str, int, bytes]]) -> None:
    """POST a declared 100 MB body to ``path``, 1 MB at a time, until the server stops taking it."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sent = 0
    try:
        sock.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     f"Content-Length: {BODY_BYTES}\r\n\r\n".encode())
        chunk = b"x" * (1 << 20)
        while sent < BODY_BYTES:
            sock.sendall(chunk)
            sent += len(chunk)
    except OSError:
        pass
    try:
        sock.settimeout(10)
        status = sock.recv(100).split(b"\r\n")[0]
    except OSError as exc:
        status = repr(exc).encode()
    finally:
        sock.close()
    out.append((path, sent, status))


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads the server's memory from /proc")
def test_bodies_outside_api_get_405_without_being_read(logged_server) -> None:  # type: ignore[no-untyped-def]
    url, pid, log_path = logged_server
    port = int(url.rsplit(":", 1)[1])
    before = peak = rss_mb(pid)
    stop = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not stop.is_set():
            peak = max(peak, rss_mb(pid))
            time.sleep(0.02)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    results: list[tuple[str, int, bytes]] = []
    posts = [threading.Thread(target=post_big, args=(port, path, results))
             for path in ("/", "/admin", "/nothing/here", "/static/admin.js", "/healthz")]
    for thread in posts:
        thread.start()
    for thread in posts:
        thread.join(120)
    stop.set()
    sampler.join(5)
    assert len(results) == 5
    for path, sent, status in results:
        assert status.startswith(b"HTTP/1.1 405"), (path, status)
        assert sent < BODY_BYTES // 4, (path, sent)  # refused long before the body was through
    assert peak - before < 50, (before, peak)
    assert httpx.get(url + "/healthz").status_code == 200
    assert "Traceback" not in log_path.read_text()


def test_a_405_outside_api_says_what_is_allowed(client) -> None:  # type: ignore[no-untyped-def]
    response = client.post("/admin", content=b"{}")
    assert response.status_code == 405 and response.headers["allow"] == "GET, HEAD"
    assert "read-only" in response.json()["error"] and "/api/" in response.json()["error"]
    assert client.get("/admin").status_code == 200


MALFORMED = [
    b"GARBAGE\r\n\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: abc\r\n\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nX-Bad\x00: y\r\n\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nX-Long: " + b"a" * 200_000 + b"\r\n\r\n",
    b"POST /api/campaigns/tiny/items/1/label HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\nab",
    b"POST /api/campaigns/tiny/items/1/label HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nZZZ\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n",
    b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 1000000\r\n\r\n" + b"x" * 1000,
    b"GET /static/admin.js HTTP/1.1\r\nHost: x\r\n\r\n" * 20,
    b"\x16\x03\x01\x00\xa5\x01\x00\x00\xa1\x03\x03",
    b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n",
]


@pytest.mark.parametrize("read_first", [False, True])
def test_malformed_requests_and_dropped_connections_leave_no_traceback(logged_server,  # type: ignore[no-untyped-def]
                                                                       read_first: bool) -> None:
    url, _, log_path = logged_server
    port = int(url.rsplit(":", 1)[1])
    for raw in MALFORMED:
        sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        try:
            sock.sendall(raw)
            if read_first:
                sock.recv(10)
            else:
                time.sleep(0.05)
        except OSError:
            pass
        finally:
            sock.close()
    time.sleep(0.5)
    assert httpx.get(url + "/healthz").status_code == 200
    log = log_path.read_text()
    assert "Traceback" not in log and "ERROR" not in log, log[-3000:]


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.mark.parametrize("allow_tie", [False, True])
def test_a_bad_choice_lists_exactly_what_is_accepted(campaign_db, allow_tie: bool) -> None:  # type: ignore[no-untyped-def]
    from fastapi.testclient import TestClient

    from trafficrlhf_sdk.feedback import FeedbackStore

    from trafficrlhf_annotation_web.app import create_app

    path, tokens = campaign_db
    store = FeedbackStore(path)
    store.update_settings("tiny", allow_tie=allow_tie)
    store.close()
    with TestClient(create_app(path)) as client:
        token = tokens["alice"]
        item = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()["item"]
        url = f"/api/campaigns/tiny/items/{item}/label"
        for bad in (-1, 6, -5) + (() if allow_tie else ("tie",)):
            response = client.post(url, json={"choice": bad}, headers=auth(token))
            message = response.json()["error"]
            assert response.status_code == 422, message
            assert "from 0 (none realistic) to 5" in message and f"got {bad!r}" in message
            assert "-1" not in message.replace(f"got {bad!r}", "")  # never offered over HTTP
            assert ('"tie"' in message) == allow_tie
        # what the message offers is accepted
        accepted = client.post(url, json={"choice": "tie" if allow_tie else 0}, headers=auth(token))
        assert accepted.status_code == 201, accepted.text
