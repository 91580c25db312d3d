"""Hostile HTTP requests to the annotation server: a real server (``trafficrlhf feedback serve`` semantics, in a
subprocess on a loopback port) over a 4-item campaign, sent raw bytes over a socket, generated with hypothesis:
JSON label bodies of every shape (wrong types, out-of-range choices, huge numbers, unknown keys, deep nesting),
methods and paths (traversal, encoded NUL, unicode, huge ids, unknown routes), tokens (missing, malformed, very
long, an annotator's token on the admin API), and protocol abuse (garbage request lines, huge and many headers,
conflicting or negative lengths, broken chunked encoding, bodies larger than the limit, a body where none belongs).

A request passes when the server answers it with a 4xx and a short error body, or with a 2xx that is right for
it (a valid label, a page, an item), without a 5xx, without a traceback in the server's log, and with the
server's peak resident memory under the bound. A 2xx to a request that should have been refused, or a static
file from outside the app's folder, is a silent wrong result.
"""

from __future__ import annotations

import json
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest
from hostile_harness import case_param, PEAK_LIMIT_MB, Outcome, assert_handled, draw, record
from hypothesis import strategies as st

CATEGORY = "HTTP requests"
NUM_CANDIDATES = 5


@dataclass
class Live:
    """The running server, its tokens and the read end of its log."""

    server: object
    tokens: dict[str, str]
    log: bytearray

    @property
    def pid(self) -> int:
        return self.server.proc.pid  # type: ignore[attr-defined]

    @property
    def port(self) -> int:
        return self.server.port  # type: ignore[attr-defined]

    def drain_log(self) -> str:
        """Log text written since the last call."""
        fd = self.server.proc.stderr.fileno()  # type: ignore[attr-defined]
        chunks = []
        while True:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                break
            if not chunk:
                break
            chunks.append(chunk)
        text = b"".join(chunks)
        self.log += text
        return text.decode(errors="replace")

    def peak_mb(self) -> float:
        with open(f"/proc/{self.pid}/status") as f:
            match = re.search(r"VmHWM:\s+(\d+) kB", f.read())
        return int(match.group(1)) / 1024 if match else 0.0


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    """A server over campaign ``tiny`` (4 items, N = 5, no playback wait) with annotator alice and an admin."""
    pytest.importorskip("trafficrlhf_annotation_web")
    from trafficrlhf_annotation_web.testing import Server

    from trafficrlhf_sdk.feedback import FeedbackStore
    from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

    path = str(tmp_path_factory.mktemp("http") / "feedback.db")
    store = FeedbackStore(path)
    make_tiny_campaign(store, num_contexts=4, num_candidates=NUM_CANDIDATES)
    store.update_settings("tiny", playback_required=False)
    tokens = {"alice": store.add_annotator("alice")[1], "admin": store.add_admin("owner")}
    store.close()
    server = Server(path).start()
    os.set_blocking(server.proc.stderr.fileno(), False)  # type: ignore[union-attr]
    try:
        yield Live(server, tokens, bytearray())
    finally:
        server.stop()


def exchange(port: int, raw: bytes, timeout: float = 10.0, half_close: bool = False) -> bytes:
    """Send ``raw`` (then close the sending side when ``half_close``: a client that stops mid-request) and read
    the answer until the server closes (or ``timeout``)."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        try:
            sock.sendall(raw)
            if half_close:
                sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass  # the server may refuse and close before the whole request is sent
        chunks, deadline = [], time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                break
            except OSError:
                break
            if not chunk:
                break
            chunks.append(chunk)
        return b"".join(chunks)


def request(method: str, path: str, token: str | None = None, body: bytes | None = None,
            headers: tuple[tuple[str, str], ...] = ()) -> bytes:
    lines = [f"{method} {path} HTTP/1.1", "Host: 127.0.0.1", "Connection: close"]
    if token is not None:
        lines.append(f"Authorization: Bearer {token}")
    if body is not None:
        lines += ["Content-Type: application/json", f"Content-Length: {len(body)}"]
    lines += [f"{k}: {v}" for k, v in headers]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("utf-8", "surrogateescape") + (body or b"")


Judge = Callable[[int, bytes], "str | None"]  # (status, body) of a 2xx -> None when right


def refused(status: int, body: bytes) -> str | None:
    return f"HTTP {status} to a request that should have been refused"


HALF_CLOSED = ("length larger than body", "empty", "http/0.9", "lf only")  # requests the client leaves unfinished


def judge(live: Live, name: str, raw: bytes, ok: Judge, half_close: bool = False) -> Outcome:
    """Send one request; classify the answer and the log lines it caused (see the module docstring). A request
    the client leaves unfinished (``half_close``) may also be closed without an answer."""
    start = time.monotonic()
    answer = exchange(live.port, raw, timeout=5.0 if half_close else 10.0, half_close=half_close)
    time.sleep(0.02)
    log = live.drain_log()
    head, _, body = answer.partition(b"\r\n\r\n")
    match = re.match(rb"HTTP/1\.[01] (\d{3})", head)
    status = int(match.group(1)) if match else 0
    outcome = Outcome(CATEGORY, name, raw[:160].decode("latin-1"), status, body[:500].decode(errors="replace"),
                      log[-1500:], live.peak_mb(), time.monotonic() - start, input_bytes=len(raw))
    if "Traceback" in log or re.search(r"\bERROR\b|Exception in ASGI", log):
        outcome.kind, outcome.why = "internal error", "the server logged an error or a traceback"
    elif status >= 500:
        outcome.kind, outcome.why = "internal error", f"HTTP {status}"
    elif status == 0 and half_close:
        outcome.kind, outcome.why = "correct", "the unfinished request was closed without an answer"
    elif status == 0:
        outcome.kind, outcome.why = "unclear error", "no HTTP answer (connection closed or timed out)"
    elif 400 <= status < 500:
        short = 0 < len(body) <= 4096 or b"Invalid HTTP request" in answer or raw.startswith(b"HEAD ")
        outcome.kind, outcome.why = ("clear error", f"HTTP {status}: {body[:200]!r}") if short else \
            ("unclear error", f"HTTP {status} with an empty or oversized body")
    else:
        problem = ok(status, body)
        outcome.kind, outcome.why = ("correct", f"HTTP {status}, checked") if problem is None else \
            ("silent wrong", problem)
    record(outcome)
    return outcome


# --------------------------------------------------------------------------------------------- generated cases
JSON = st.recursive(st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False)
                    | st.text(max_size=20), lambda inner: st.lists(inner, max_size=4)
                    | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=12)
CHOICES = st.one_of(st.integers(-3, NUM_CANDIDATES + 2), st.sampled_from([True, False, None, "tie", "1", 1.0, 2**63,
                                                                          -(2**63), [], {}, "\u0661"]))
LABEL_BODIES = st.one_of(
    st.fixed_dictionaries({"choice": CHOICES}),
    st.fixed_dictionaries({"choice": CHOICES, "time_ms": st.sampled_from([0, -1, 2**63, 1.5, "x", None, 10**30])}),
    st.fixed_dictionaries({"choice": CHOICES, "extra": JSON}),
    JSON,
)
PATHS = ["/", "/healthz", "/api/me", "/api/campaigns/tiny/next", "/api/campaigns/tiny/items/1",
         "/api/campaigns/tiny/items/-1", "/api/campaigns/tiny/items/99999999999999999999999",
         "/api/campaigns/tiny/items/1e3", "/api/campaigns/%00/next", "/api/campaigns/" + "a" * 5000 + "/next",
         "/api/campaigns/..%2F..%2Fetc/next", "/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/etc/passwd",
         "/static/..%2f..%2f..%2fetc%2fpasswd", "/api/admin/overview", "/api/admin/annotators",
         "/api/campaigns/tiny/history", "/api/campaigns/tiny/agreement", "/api/campaigns/t%C3%AFny/next",
         "/api/campaigns/\u202etiny/next", "//api//me", "/api/me?x=" + "%" * 100, "/admin", "/nope", "*"]
METHODS = ["GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "HEAD", "TRACE", "CONNECT", "FOO", "get"]
TOKENS = ["alice", "admin", None, "", "Bearer", "x" * 100_000, "\u00e9\u00e9", "Basic YWxpY2U6cHc=",
          "alice-token-with-suffix"]
RAW = ["garbage", "http/0.9", "no host", "huge header", "many headers", "crlf injection", "two lengths",
       "negative length", "length overflow", "length larger than body", "bad chunk size", "chunk size overflow",
       "chunked and length", "oversized body", "oversized chunked body", "body outside api", "expect continue",
       "header with nul", "request line 100k", "utf8 in method", "pipelined", "empty", "lf only"]

PAGES = {"/", "/healthz", "/admin"}  # read-only pages anyone may GET
ANNOTATOR_GETS = {"/api/me", "/api/campaigns/tiny/next", "/api/campaigns/tiny/items/1",
                  "/api/campaigns/tiny/history", "/api/campaigns/tiny/agreement"}


def _token(live: Live, name: str | None) -> str | None:
    if name in ("alice", "admin"):
        return live.tokens[name]
    if name == "alice-token-with-suffix":
        return live.tokens["alice"] + "x"
    return name


def _route_judge(method: str, path: str, token: str | None) -> Judge:
    """A 2xx is right only for a page, or for an annotator's read of the annotator API, or an admin's read."""
    def ok(status: int, body: bytes) -> str | None:
        if b"root:x:0:0" in body:
            return "served a file from outside the app"
        if method in ("GET", "HEAD") and path in PAGES:
            return None
        if method == "GET" and path in ANNOTATOR_GETS and token == "alice":
            return None if body.strip().startswith(b"{") else "not a JSON answer"
        if method == "GET" and path.startswith("/api/admin/") and token == "admin":
            return None if body.strip().startswith((b"{", b"[")) else "not a JSON answer"
        if method == "OPTIONS":
            return None  # an empty allow-list answer
        return refused(status, body)
    return ok


def _label_judge(body: object) -> Judge:
    choice = body.get("choice") if isinstance(body, dict) else None
    valid = (isinstance(body, dict) and set(body) <= {"choice", "time_ms"} and
             (isinstance(choice, int) and not isinstance(choice, bool) and 0 <= choice <= NUM_CANDIDATES) and
             (body.get("time_ms") is None or (type(body.get("time_ms")) is int and 0 <= body["time_ms"] < 2**63)))

    def ok(status: int, answer: bytes) -> str | None:
        return None if valid else f"HTTP {status}: label {body!r} accepted"
    return ok


def raw_request(live: Live, kind: str) -> tuple[bytes, Judge]:
    token = live.tokens["alice"]
    label = "/api/campaigns/tiny/items/1/label"
    if kind == "garbage":
        return b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + os.urandom(64), refused
    if kind == "http/0.9":
        return b"GET /\r\n", refused
    if kind == "no host":
        return b"GET /healthz HTTP/1.1\r\nConnection: close\r\n\r\n", _route_judge("GET", "/healthz", None)
    if kind == "huge header":
        return request("GET", "/healthz", headers=(("X-Big", "a" * 200_000),)), refused
    if kind == "many headers":
        return request("GET", "/healthz", headers=tuple((f"X-{i}", "v") for i in range(20_000))), refused
    if kind == "crlf injection":
        return request("GET", "/healthz", headers=(("X-A", "b\r\nX-Injected: 1"),)), \
            _route_judge("GET", "/healthz", None)
    if kind == "two lengths":
        return (f"POST {label} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nContent-Length: 12\r\n"
                "Content-Length: 3\r\nContent-Type: application/json\r\n\r\n{\"choice\":1}").encode(), refused
    if kind == "negative length":
        return request("POST", label, token, headers=(("Content-Length", "-1"),)), refused
    if kind == "length overflow":
        return request("POST", label, token, headers=(("Content-Length", "9" * 40),)), refused
    if kind == "length larger than body":
        return (f"POST {label} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nContent-Length: 5000\r\n"
                "Content-Type: application/json\r\n\r\n{\"choice\": 1}").encode(), refused
    if kind in ("bad chunk size", "chunk size overflow", "chunked and length"):
        size = {"bad chunk size": "zz", "chunk size overflow": "f" * 40, "chunked and length": "c"}[kind]
        extra = "Content-Length: 12\r\n" if kind == "chunked and length" else ""
        return (f"POST {label} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nTransfer-Encoding: chunked\r\n"
                f"{extra}Content-Type: application/json\r\n\r\n{size}\r\n{{\"choice\":1}}\r\n0\r\n\r\n").encode(), \
            refused if kind != "chunked and length" else _label_judge({"choice": 1})
    if kind == "oversized body":
        return request("POST", label, token, body=b'{"choice": 1, "pad": "' + b"a" * 2_000_000 + b'"}'), refused
    if kind == "oversized chunked body":
        chunk = b"a" * 65536
        body = b"".join(b"%x\r\n" % len(chunk) + chunk + b"\r\n" for _ in range(40)) + b"0\r\n\r\n"
        return (f"POST {label} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nTransfer-Encoding: chunked\r\n"
                "Content-Type: application/json\r\n\r\n").encode() + body, refused
    if kind == "body outside api":
        return request("POST", "/", body=b"x" * 5_000_000), refused
    if kind == "expect continue":
        return request("POST", label, token, headers=(("Expect", "100-continue"), ("Content-Length", "100000000"))), \
            refused
    if kind == "header with nul":
        return b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-A: a\x00b\r\nConnection: close\r\n\r\n", \
            _route_judge("GET", "/healthz", None)
    if kind == "request line 100k":
        return b"GET /" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: x\r\n\r\n", refused
    if kind == "utf8 in method":
        return "G\u00c9T /healthz HTTP/1.1\r\nHost: x\r\n\r\n".encode(), refused
    if kind == "pipelined":
        return request("GET", "/healthz").replace(b"Connection: close\r\n", b"") + request("GET", "/healthz"), \
            _route_judge("GET", "/healthz", None)
    if kind == "empty":
        return b"", refused
    return b"GET /healthz HTTP/1.1\nHost: x\nConnection: close\n\n", _route_judge("GET", "/healthz", None)


LABELS = draw(LABEL_BODIES, 45, 73)
ROUTES = draw(st.tuples(st.sampled_from(METHODS), st.sampled_from(PATHS), st.sampled_from(TOKENS)), 45, 73)

KNOWN: dict[str, str] = {}


def _params(large: bool) -> list:
    cases = [("label", i, body) for i, body in enumerate(LABELS)] + \
            [("route", i, route) for i, route in enumerate(ROUTES)] + [("raw", i, kind) for i, kind in enumerate(RAW)]
    params = []
    for kind, index, value in cases:
        small = (kind == "label" and index < 2) or (kind == "route" and index < 2) or \
            (kind == "raw" and value in ("garbage", "two lengths", "oversized body", "body outside api"))
        if not (large or small):
            continue
        case_id = f"http-{kind}-{index}"
        params.append(case_param(kind, value, case_id=case_id, large=large, known=KNOWN))
    return params


@pytest.mark.parametrize(("kind", "value"), _params(False) + _params(True))
def test_hostile_http_request(kind: str, value: object, live: Live) -> None:
    if kind == "label":
        body = json.dumps(value).encode()
        raw, ok = request("POST", "/api/campaigns/tiny/items/1/label", live.tokens["alice"], body), \
            _label_judge(value)
        if isinstance(value, dict) and "choice" in value:  # the item must be open for a valid label to land
            exchange(live.port, request("GET", "/api/campaigns/tiny/items/1", live.tokens["alice"]))
            live.drain_log()
        name = f"label body {value!r}"
    elif kind == "route":
        method, path, token = value  # type: ignore[misc]
        raw, ok = request(method, path, _token(live, token)), _route_judge(method, path, token)
        name = f"{method} {path[:80]} token={str(token)[:20]!r}"
    else:
        raw, ok = raw_request(live, str(value))
        name = f"raw: {value}"
    outcome = judge(live, name[:200], raw, ok, half_close=value in HALF_CLOSED)
    assert_handled(outcome)


def test_large_bodies_leave_the_server_memory_flat_and_its_log_clean(live: Live) -> None:
    """Five 20 MB bodies, to a page and to the API, raise the server's peak resident memory by less than 50 MB;
    after every request of the suite, its log holds no traceback."""
    before = live.peak_mb()
    for path, token in (("/", None), ("/api/campaigns/tiny/items/1/label", live.tokens["alice"]),
                        ("/healthz", None), ("/api/me", live.tokens["alice"]), ("/nope", None)):
        exchange(live.port, request("POST", path, token, body=b"x" * 20_000_000))
    time.sleep(0.2)
    live.drain_log()
    assert live.peak_mb() - before < 50, f"peak {before:.0f} -> {live.peak_mb():.0f} MB"
    assert live.peak_mb() < PEAK_LIMIT_MB
    assert "Traceback" not in live.log.decode(errors="replace"), live.log.decode(errors="replace")[-3000:]
