"""Request hygiene in front of the app: the token is checked, and the body size limited, before a body is read.

:class:`RequestGuard` is a plain ASGI middleware. For every ``/api`` request that carries a body (any
``POST``, ``PUT``, ``PATCH`` or ``DELETE``, or a declared ``Content-Length``/``Transfer-Encoding``):

1. the bearer token is checked first (an admin token under ``/api/admin``, an annotator token elsewhere):
   401 without reading a byte of the body;
2. a declared ``Content-Length`` above ``max_body_bytes`` gives 413, again without reading the body; a
   malformed one gives 400;
3. a body without a declared length (chunked) is counted as it arrives and cut off with 413 at the limit.

Outside ``/api`` everything is read-only (the pages and their static files): a request there that declares a
body gets 405 (``POST``, ``PUT``, ``PATCH``, ``DELETE``) or 400 (a ``GET`` with a body) at once, with
``Connection: close``, so the body is never read.

The server never holds more than one limit's worth of a body, whatever the client sends: every refusal closes
the connection, and uvicorn stops reading a connection whose response has been sent (flow control).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Awaitable, Callable, MutableMapping
from contextvars import ContextVar
from typing import Any

from starlette.exceptions import HTTPException

from trafficrlhf_sdk.feedback.errors import AuthenticationError
from trafficrlhf_sdk.feedback.store import FeedbackStore

__all__ = ["DEFAULT_MAX_BODY_BYTES", "DroppedResponseFilter", "RequestGuard", "bearer_token", "install_log_filter"]

DEFAULT_MAX_BODY_BYTES = 64 * 1024  # the largest legitimate body (a settings update with guidelines) is ~50 kB
BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}
log = logging.getLogger(__name__)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value, or None."""
    if authorization and authorization[:7].lower() == "bearer ":
        return authorization[7:].strip() or None
    return None


class RequestGuard:
    """ASGI middleware: auth, then size, before the body (see the module docstring).

    Args:
        app: the wrapped ASGI app.
        store: the feedback store that knows the tokens.
        max_body_bytes: the largest request body accepted (bytes).
    """

    def __init__(self, app: Any, store: FeedbackStore, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
        if max_body_bytes < 1:
            raise ValueError(f"`max_body_bytes` must be positive; got {max_body_bytes!r}.")
        self.app, self.store, self.max_body_bytes = app, store, max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Screen one request, then pass it on (or answer 400/401/405/413 without reading the body)."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        try:
            await self._screen(scope, receive, _guarded(send))
        except _ConnectionGone as gone:  # the server already answered a malformed request and closed the stream
            _dropped.set(True)
            log.debug("response to %s %s dropped: %s", scope.get("method"), scope.get("path"), gone)

    async def _screen(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        length_header = headers.get("content-length")
        has_body = (scope["method"] in BODY_METHODS or length_header not in (None, "0")
                    or "transfer-encoding" in headers)
        if not has_body:
            await self.app(scope, receive, send)
            return
        if not scope["path"].startswith("/api/"):
            path = scope["path"][:80]
            if scope["method"] in ("GET", "HEAD"):
                await _reply(send, 400, f"{scope['method']} {path} carries a body; pages take none (the API is "
                                        "under /api/).")
            else:
                await _reply(send, 405, f"{scope['method'][:10]} is not allowed on {path}: pages and files outside "
                                        "/api/ are read-only (GET); the API is under /api/.", {"allow": "GET, HEAD"})
            return
        token = bearer_token(headers.get("authorization"))
        try:
            if scope["path"].startswith("/api/admin/"):
                self.store.authenticate_admin(token)
            else:
                self.store.authenticate(token)
        except AuthenticationError as exc:
            await _reply(send, 401, str(exc), {"www-authenticate": "Bearer"})
            return
        if length_header is not None:
            try:
                length = int(length_header)
                if length < 0:
                    raise ValueError(length_header)
            except ValueError:
                await _reply(send, 400, f"malformed Content-Length header {length_header[:40]!r}; send a byte count.")
                return
            if length > self.max_body_bytes:
                await _reply(send, 413, f"request body of {length} bytes is over the limit of {self.max_body_bytes} "
                                        "bytes; send a smaller body.")
                return
        limit = self.max_body_bytes
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise HTTPException(413, f"request body is over the limit of {limit} bytes; send a smaller body.")
            return message

        await self.app(scope, counted, send)


# set in the task of a request whose response :func:`_guarded` dropped; read by :class:`DroppedResponseFilter`
_dropped: ContextVar[bool] = ContextVar("trafficrlhf_response_dropped", default=False)
INCOMPLETE_RESPONSE = "ASGI callable returned without completing response."


class DroppedResponseFilter(logging.Filter):
    """Keeps uvicorn's "returned without completing response" error out of the log for a request whose response
    was dropped on purpose (uvicorn had already answered the malformed request with its own 400)."""

    def filter(self, record: logging.LogRecord) -> bool:  # noqa: D102
        return not (record.msg == INCOMPLETE_RESPONSE and _dropped.get())


def install_log_filter() -> None:
    """Add :class:`DroppedResponseFilter` to uvicorn's error logger (once)."""
    logger = logging.getLogger("uvicorn.error")
    if not any(isinstance(f, DroppedResponseFilter) for f in logger.filters):
        logger.addFilter(DroppedResponseFilter())


class _ConnectionGone(Exception):
    """The HTTP connection can no longer take a response (see :func:`_guarded`)."""


def _protocol_errors() -> tuple[type[BaseException], ...]:
    try:
        from h11 import LocalProtocolError
    except ImportError:  # another server implementation: nothing of h11's to translate
        return ()
    return (LocalProtocolError,)


def _guarded(send: Send) -> Send:
    """``send`` that turns "this connection takes no more responses" into :class:`_ConnectionGone`.

    When a client sends a malformed request (a bad chunk, a broken header) while the app is still working on it,
    uvicorn answers 400 itself and marks the connection for closing; the app's own response then fails inside
    h11. That is the client's doing, not a server error, so it is dropped quietly instead of logged as a
    traceback."""
    errors = _protocol_errors()

    async def guarded(message: Message) -> None:
        try:
            await send(message)
        except errors as exc:
            raise _ConnectionGone(str(exc)) from None

    return guarded


async def _reply(send: Send, status: int, error: str, extra: dict[str, str] | None = None) -> None:
    body = json.dumps({"error": error}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
               (b"connection", b"close")]
    headers += [(k.encode(), v.encode()) for k, v in (extra or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
