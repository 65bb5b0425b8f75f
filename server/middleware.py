"""Two ASGI guards that act before a request body is read: the upload cap and evaluation admission.

Starlette spools uploaded files to disk but puts no cap on their total size (its ``max_part_size`` covers
plain form fields only), and FastAPI parses the whole form before a route runs. So the cap is enforced on
the byte stream itself: a declared ``Content-Length`` over the cap is refused before anything is read,
and a body that grows past it (chunked, or a lying header) is cut off while it streams.
"""

from __future__ import annotations

import json
from collections.abc import Callable

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .errors import error_body

__all__ = ["BodyLimitMiddleware", "AdmissionMiddleware", "BodyTooLarge"]


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` when the body passes the cap; an HTTPException so FastAPI passes it on."""

    def __init__(self, limit: int) -> None:
        super().__init__(status_code=413, detail=_too_large_message(limit))


def _too_large_message(limit: int) -> str:
    return f"the request body is larger than the upload limit of {limit / (1 << 20):g} MB (KITTI_EVAL_MAX_UPLOAD_MB)"


async def _send_json(send: Send, status: int, body: dict[str, object], headers: dict[str, str]) -> None:
    raw = json.dumps(body).encode()
    head = [(b"content-type", b"application/json"), (b"content-length", str(len(raw)).encode())]
    head += [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": raw})


class BodyLimitMiddleware:
    """Refuse request bodies over ``limit`` bytes with 413, whether declared or streamed."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None and declared > self.limit:
            await _send_json(
                send, 413, error_body("payload_too_large", _too_large_message(self.limit)), {"connection": "close"}
            )
            return
        seen = 0

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLarge(self.limit)
            return message

        await self.app(scope, limited_receive, send)


def _content_length(scope: Scope) -> int | None:
    for key, value in scope.get("headers", ()):
        if key == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


class AdmissionMiddleware:
    """Admit at most ``capacity()`` evaluation requests at once (uploading, waiting or running).

    The count lives on the event loop (no lock needed). A request past the capacity gets 503 with
    Retry-After before its body is read, so a saturated server does not spend time receiving uploads it
    would refuse.
    """

    def __init__(
        self, app: ASGIApp, *, paths: frozenset[str], capacity: Callable[[], int], retry_after_s: Callable[[], int]
    ) -> None:
        self.app = app
        self.paths = paths
        self.capacity = capacity
        self.retry_after_s = retry_after_s
        self.in_flight = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or scope["path"].rstrip("/") not in self.paths:
            await self.app(scope, receive, send)
            return
        if self.in_flight >= self.capacity():
            retry = self.retry_after_s()
            await _send_json(
                send,
                503,
                error_body(
                    "busy",
                    f"all evaluation slots are taken ({self.in_flight} requests in progress); retry in {retry} s",
                ),
                {"retry-after": str(retry), "connection": "close"},
            )
            return
        self.in_flight += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= 1
