"""ASGI guards around the request body: refusals that need none, the body received in full before the app sees
it, then evaluation admission.

:class:`RefuseBeforeBody` (outermost, inside the door that resolves the caller) answers at once what would be
refused without needing the body: a benchmark submission past its quota, or while the job queue is full.

:class:`BodyMiddleware` receives every request body itself, so that a slow sender holds no
evaluation place while it sends:

* a declared ``Content-Length`` over the upload cap is refused with 413 before anything is read;
* at most ``max_receiving`` bodies are received at once; a request past that waits its turn, its body unread
  (and no ``100 Continue`` sent to a client that asked for one: uvicorn sends it at the first read), for up to
  ``wait_s``, and only past that is it answered 503 ``busy`` with Retry-After. A benchmark submission over its
  quota is answered by :class:`RefuseBeforeBody` (outside) before it waits, and checked again when its turn
  comes, before its body is read;
* a body must arrive in full within ``timeout_s``, or it is answered 408 and its connection closed;
* a body that grows past the cap (chunked, or a lying header) is not read further, and the app is called
  with a ``receive`` that raises :class:`BodyTooLarge`, so the JSON API and the web page answer that 413 as
  they answer their other errors;
* a client that goes away mid-body gets nothing, and the app is not called.

Bodies are kept in memory, as the chunks that arrived, while all the bodies in memory together stay within a
budget (``KITTI_EVAL_BODY_MEMORY_MB``). A body that declares its length (``Content-Length``, as curl, httpx and
browsers send a file) and fits in the budget waits, its turn taken and its body unread, until the bodies before
it give back enough of the budget, first come first served, for up to ``memory_wait_s``
(``KITTI_EVAL_BODY_MEMORY_WAIT_S``); only past that, or when it is larger than the whole budget, or when its
length is not declared and the budget is full, does a body go to an unnamed temporary file in the service's
scratch folder (the operating system removes it when it is closed, or when the process dies). A body on disk is
written once by this middleware, read back, and its uploaded file written again by the form parser and read
back again (it is past ``PART_MEMORY_BYTES``): at a deadline, 64 val-sized bodies received at once spilled so,
and the answers took twice as long as with every body in memory. A body of up to ``_CHUNK`` never waits. The
app then reads the body through a ``receive`` that replays it. Starlette spools uploaded files to disk too but puts
no cap on their total size (its ``max_part_size`` covers plain form fields only), and FastAPI parses the whole
form before a route runs, which is why the cap is enforced on the byte stream here.

:class:`AdmissionMiddleware` (inside it) counts the evaluation requests in progress, whose bodies have
arrived by then, for a graceful shutdown, and refuses new ones while the service drains.
"""

from __future__ import annotations

import json
import tempfile
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from contextvars import ContextVar
from pathlib import Path
from typing import IO, Any

import anyio
import anyio.to_thread
from starlette.exceptions import HTTPException
from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .errors import ApiError, error_body, fault_of
from .observability import AdmissionState

__all__ = [
    "BodyMiddleware",
    "RefuseBeforeBody",
    "AdmissionMiddleware",
    "BodyTooLarge",
    "BeforeBodyCheck",
    "BeforeBody",
    "MEMORY_BYTES",
    "PART_MEMORY_BYTES",
    "part_memory_bytes",
]

#: the request bodies kept in memory, all together (more go to temporary files)
MEMORY_BYTES = 256 << 20
#: an uploaded file (a part of a multipart body) kept in memory while its request is handled; larger ones are
#: spooled to a temporary file by Starlette's form parser
PART_MEMORY_BYTES = 16 << 20
#: the request's own, while the app handles it: set by :class:`BodyMiddleware` (see :func:`part_memory_bytes`)
_PART_MEMORY: ContextVar[int] = ContextVar("part_memory_bytes", default=PART_MEMORY_BYTES)


def part_memory_bytes() -> int:
    """The size up to which an uploaded file of the request being handled stays in memory (Starlette's form
    parser spools a larger one to a temporary file): a body :class:`BodyMiddleware` held in memory, within the
    bodies' budget, keeps its files in memory whatever their size (they are the body's bytes, already counted:
    writing a val-sized result.pkl to disk chunk by chunk and reading it back took a fifth of the web process's
    samples in a profile of uploads); a body past the budget, or one that did not go through it, keeps those up
    to ``PART_MEMORY_BYTES``."""
    return _PART_MEMORY.get()


#: what is written to (and replayed from) the temporary file at a time
_CHUNK = 1 << 20


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


def _header(scope: Scope, name: bytes) -> bytes | None:
    for key, value in scope.get("headers", ()):
        if key == name:
            return bytes(value)
    return None


def _content_length(scope: Scope) -> int | None:
    value = _header(scope, b"content-length")
    if value is None:
        return None
    try:
        return int(value)
    except ValueError:
        return None


#: a body holding room in memory for bytes yet to come keeps it while at least this many arrive in each
#: ``_SLOW_WINDOW_S`` (64 KB/s, half a megabit a second); a slower sender gives the room back (see ``_Body.slow``)
_SLOW_WINDOW_S = 5.0
_SLOW_BYTES = 320 << 10


class _Pace:
    """Whether a body's bytes keep arriving at least as fast as ``min_bytes`` each ``window_s``; ``slow`` is
    called once when a window ends short of it."""

    def __init__(self, window_s: float, min_bytes: int, slow: Callable[[], None]) -> None:
        self.window_s, self.min_bytes, self.slow = window_s, min_bytes, slow
        self.ends = anyio.current_time() + window_s
        self.got = 0
        self.done = False

    def remaining(self) -> float:
        return max(0.0, self.ends - anyio.current_time())

    def arrived(self, n: int) -> None:
        self.got += n
        self.check()

    def check(self) -> None:
        now = anyio.current_time()
        if self.done or now < self.ends:
            return
        if self.got < self.min_bytes or now >= self.ends + self.window_s:  # short, or a whole window since empty
            self.done = True
            self.slow()
            return
        self.ends, self.got = now + self.window_s, 0


async def _read_body(
    receive: Receive,
    add: Callable[[bytes], Awaitable[None]] | None,
    limit: int,
    timeout_s: float,
    pace: _Pace | None = None,
) -> str:
    """Read a request body, each chunk handed to ``add`` (None: dropped): complete, too_large (not read past the
    ``limit``), late (not all there within ``timeout_s``) or gone (the client disconnected). ``pace`` is told of
    the bytes as they come, and of a window that ends with none (waiting for a chunk no longer than it lasts)."""
    size = 0
    with anyio.move_on_after(timeout_s):
        while True:
            if pace is not None and not pace.done:
                with anyio.move_on_after(pace.remaining()) as quiet:
                    message = await receive()
                if quiet.cancelled_caught:  # nothing in this window (nothing taken from the connection)
                    pace.check()
                    continue
                pace.arrived(len(message.get("body", b"")) if message["type"] == "http.request" else 0)
            else:
                message = await receive()
            if message["type"] == "http.disconnect":
                return "gone"
            if message["type"] != "http.request":
                continue
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                return "too_large"
            if add is not None:
                await add(chunk)
            if not message.get("more_body", False):
                return "complete"
    return "late"


class _Memory:
    """The bytes of request bodies held in memory, all bodies together, against a budget; the bodies waiting for
    room in it, first come first served."""

    def __init__(self, budget: int) -> None:
        self.budget = budget
        self.held = 0
        #: bodies waiting for room: (bytes wanted, set once they are granted, and counted in ``held``)
        self.waiting: deque[tuple[int, anyio.Event]] = deque()

    def take(self, n: int) -> bool:
        """Take ``n`` bytes now if they fit (a chunk of a body that did not declare its length)."""
        if self.held + n > self.budget:
            return False
        self.held += n
        return True

    async def reserve(self, n: int, wait_s: float) -> tuple[int, bool]:
        """Take ``n`` bytes (at most the budget) once they fit, after the bodies that asked before, waiting up to
        ``wait_s``: the bytes taken (``n``, or 0 when no room came in time) and whether it had to wait. Bytes
        granted are counted in ``held`` until given back, however the wait ends (a cancelled waiter that had
        just been granted gives them back itself)."""
        if not self.waiting and self.take(n):
            return n, False
        granted = anyio.Event()
        entry = (n, granted)
        self.waiting.append(entry)
        try:
            with anyio.move_on_after(wait_s):
                await granted.wait()
        except BaseException:
            if granted.is_set():
                self.give(n)
            raise
        finally:
            if not granted.is_set():
                self.waiting.remove(entry)
                self._grant()  # those behind it may fit now
        return (n if granted.is_set() else 0), True

    def give(self, n: int) -> None:
        self.held -= n
        self._grant()

    def _grant(self) -> None:
        while self.waiting and self.held + self.waiting[0][0] <= self.budget:
            n, granted = self.waiting.popleft()
            self.held += n
            granted.set()


class _Body:
    """A request body as it arrives: the chunks themselves in memory while the bodies in memory stay within the
    budget (no copy: the app is handed the same chunks), else in an unnamed temporary file."""

    def __init__(self, spool_dir: Path | None, memory: _Memory) -> None:
        self.spool_dir = spool_dir
        self.memory = memory
        self.size = 0
        self.chunks: deque[bytes] = deque()  # in memory, not yet handed over (while there is no file)
        self.held = 0  # bytes of the memory budget this body holds, until it is closed
        self.unfilled = 0  # of them, reserved for its declared length and not yet arrived
        self.pending = bytearray()  # not yet written to the file
        self.file: IO[bytes] | None = None

    async def reserve(self, n: int, wait_s: float) -> bool:
        """Wait for room in the memory budget for the whole body, ``n`` bytes as declared (see
        :meth:`_Memory.reserve`); whether it had to wait. Without room in time, the body goes to a file as it
        arrives."""
        taken, waited = await self.memory.reserve(n, wait_s)
        self.held += taken
        self.unfilled += taken
        return waited

    def slow(self) -> None:
        """Its bytes come too slowly to hold room for the rest: the room reserved and not yet filled goes back to
        the budget (and to the bodies waiting for it); what arrives next is kept in memory if it fits, else the
        body goes to a file. A sender that declares a large body and sends nothing holds the room for one pace
        window (``_SLOW_WINDOW_S``), not for the whole ``KITTI_EVAL_BODY_TIMEOUT_S``."""
        if self.unfilled:
            self.memory.give(self.unfilled)
            self.held -= self.unfilled
            self.unfilled = 0

    async def add(self, data: bytes) -> None:
        self.size += len(data)
        if self.file is None:
            if self.unfilled >= len(data):
                self.unfilled -= len(data)
                self.chunks.append(data)
                return
            if self.memory.take(len(data)):
                self.held += len(data)
                self.chunks.append(data)
                return
            # past the budget: this body goes to a file, with what it had in memory
            self.file = await anyio.to_thread.run_sync(self._open)
            self.pending += b"".join(self.chunks)
            self.chunks.clear()
            self.memory.give(self.held)
            self.held = self.unfilled = 0
        self.pending += data
        if len(self.pending) >= _CHUNK:
            await self._flush()

    def _open(self) -> IO[bytes]:
        return tempfile.TemporaryFile(dir=self.spool_dir if self.spool_dir and self.spool_dir.is_dir() else None)

    async def _flush(self) -> None:
        assert self.file is not None
        data, self.pending = bytes(self.pending), bytearray()
        await anyio.to_thread.run_sync(self.file.write, data)

    def replay(self, then: Receive) -> Receive:
        """A ``receive`` that hands the body over again, then passes on to ``then`` (for ``http.disconnect``).
        Chunks in memory are let go as they are handed over (the app keeps what it needs of them); the budget
        they held is given back when the body is closed, at the end of the request."""
        done = False

        async def receive() -> Message:
            nonlocal done
            if done:
                return await then()
            if self.file is None:
                chunk = self.chunks.popleft() if self.chunks else b""
                done = not self.chunks
                return {"type": "http.request", "body": chunk, "more_body": not done}
            chunk = await anyio.to_thread.run_sync(self.file.read, _CHUNK)
            done = self.file.tell() >= self.size
            return {"type": "http.request", "body": chunk, "more_body": not done}

        return receive

    async def finish(self) -> None:
        """All of it has arrived: the rest goes to the file, which is rewound for the replay."""
        if self.file is not None:
            await self._flush()
            await anyio.to_thread.run_sync(self.file.seek, 0)

    def close(self) -> None:
        self.chunks.clear()
        self.memory.give(self.held)
        self.held = self.unfilled = 0
        self.pending = bytearray()
        if self.file is not None:
            self.file.close()
            self.file = None


class _ClientTurns:
    """Turns to send a body, ``per_client`` for each client address: a client holding them all waits for one of
    its own before it may take one of everyone's. Entries go when no request of their client holds or waits."""

    def __init__(self, per_client: int) -> None:
        self.per_client = per_client
        self._turns: dict[str, tuple[anyio.Semaphore, list[int]]] = {}

    async def take(self, client: str, wait_s: float) -> tuple[bool, bool]:
        """(whether a turn of ``client``'s was taken within ``wait_s``, whether it had to wait)."""
        turns, users = self._turns.setdefault(client, (anyio.Semaphore(self.per_client), [0]))
        users[0] += 1
        waited = turns.value == 0
        taken = False
        try:
            with anyio.move_on_after(wait_s):
                await turns.acquire()
                taken = True
        finally:
            if not taken:
                self._leave(client)
        return taken, waited

    def give(self, client: str) -> None:
        self._turns[client][0].release()
        self._leave(client)

    def _leave(self, client: str) -> None:
        users = self._turns[client][1]
        users[0] -= 1
        if users[0] == 0:
            del self._turns[client]

    def __len__(self) -> int:
        return len(self._turns)


class BodyMiddleware:
    """Receive each request body in full before the app runs: capped, on a deadline, a bounded number at once."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        limit: int,
        timeout_s: float,
        max_receiving: int,
        retry_after_s: Callable[[], int],
        spool_dir: Path | None = None,
        memory_bytes: int = MEMORY_BYTES,
        memory_wait_s: float = 60.0,
        state: AdmissionState | None = None,
        wait_s: float = 300.0,
        before_body: BeforeBody | None = None,
        per_client: int | None = None,
        client_of: Callable[[Scope], str] | None = None,
    ) -> None:
        self.app = app
        self.limit = limit
        #: turns of each client address (``client_of``), at most ``per_client`` of everyone's at once: 64
        #: connections of one client that send nothing would otherwise hold every turn until their deadline
        self.client_turns = _ClientTurns(per_client) if per_client and client_of is not None else None
        self.client_of = client_of
        self.memory = _Memory(memory_bytes)
        self.memory_wait_s = memory_wait_s
        #: the pace below which a body gives back the room it holds for bytes yet to come (see ``_Body.slow``)
        self.slow_window_s, self.slow_bytes = _SLOW_WINDOW_S, _SLOW_BYTES
        self.timeout_s = timeout_s
        self.max_receiving = max_receiving
        self.retry_after_s = retry_after_s
        self.spool_dir = spool_dir
        self.state = state or AdmissionState()
        self.wait_s = wait_s
        #: the refusals known before a body, asked again when a waiting request's turn comes
        self.before_body = before_body
        self._turns: anyio.Semaphore | None = None

    @property
    def receiving(self) -> int:
        """Bodies being received now."""
        return self.state.receiving

    @receiving.setter
    def receiving(self, value: int) -> None:
        self.state.receiving = value

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if not declared and _header(scope, b"transfer-encoding") is None:
            await self.app(scope, receive, send)  # no body
            return
        if declared is not None and declared > self.limit:
            await _send_json(
                send, 413, error_body("payload_too_large", _too_large_message(self.limit)), {"connection": "close"}
            )
            return
        if self._turns is None:
            self._turns = anyio.Semaphore(self.max_receiving)
        body = _Body(self.spool_dir, self.memory)
        try:  # the body's memory and file are given back whichever way the request ends
            await self._receive_and_run(self._turns, body, scope, receive, send)
        finally:
            body.close()

    async def _receive_and_run(
        self, turns: anyio.Semaphore, body: _Body, scope: Scope, receive: Receive, send: Send
    ) -> None:
        """Receive the body in its turns (:meth:`_receive_in_turn`), then answer a refusal asked again after a
        wait, or run the app on the body, or answer why there is none."""
        received = await self._receive_in_turn(turns, body, scope, receive, send)
        if received is None:  # answered already
            return
        outcome, refused = received
        if refused is not None:  # answered before the body, as outside
            await self.before_body.answer(refused, scope, receive, send)  # type: ignore[union-attr]
            return
        if outcome == "complete":
            # a body held in memory keeps its uploaded files in memory too (part_memory_bytes)
            token = _PART_MEMORY.set(max(PART_MEMORY_BYTES, body.size)) if body.file is None else None
            try:
                await self.app(scope, body.replay(receive), send)
            finally:
                if token is not None:
                    _PART_MEMORY.reset(token)
        elif outcome == "too_large":
            body.close()
            await self.app(scope, self._too_large, send)
        elif outcome == "late":
            body.close()
            message = (
                f"the request body did not arrive within {self.timeout_s:g} s of its turn to be read "
                "(KITTI_EVAL_BODY_TIMEOUT_S)"
            )
            await _send_json(send, 408, error_body("request_timeout", message), {"connection": "close"})
        # "gone": the client disconnected; there is no one to answer

    async def _receive_in_turn(
        self, turns: anyio.Semaphore, body: _Body, scope: Scope, receive: Receive, send: Send
    ) -> tuple[str, ApiError | None] | None:
        """Wait for a turn of the client's (``per_client`` of them, bounded by ``wait_s``), then receive the body in
        a turn of everyone's (:meth:`_receive_in_shared_turn`); the client's turn is given back with everyone's,
        before the app runs. The outcome and a refusal asked again, or None when the request was answered."""
        client_turns = self.client_turns
        client = self.client_of(scope) if client_turns is not None and self.client_of is not None else None
        waited = False
        if client is not None and client_turns is not None:
            self.state.body_waiting += 1
            try:
                taken, waited = await client_turns.take(client, self.wait_s)
            finally:
                self.state.body_waiting -= 1
            if not taken:
                await self._busy(
                    send,
                    f"this client has {client_turns.per_client} request bodies being received "
                    f"(KITTI_EVAL_MAX_RECEIVING_PER_CLIENT), and none ended within {self.wait_s:g} s "
                    "(KITTI_EVAL_RECEIVE_WAIT_S)",
                )
                return None
        try:
            return await self._receive_in_shared_turn(turns, body, scope, receive, send, waited)
        finally:
            if client is not None and client_turns is not None:
                client_turns.give(client)

    async def _receive_in_shared_turn(
        self, turns: anyio.Semaphore, body: _Body, scope: Scope, receive: Receive, send: Send, waited: bool
    ) -> tuple[str, ApiError | None] | None:
        """Wait for a turn to receive (bounded by ``wait_s``), then for room in memory for a body of declared length
        (bounded by ``memory_wait_s``), ask a request that waited its refusals again, receive the body and give the
        turn back. The outcome and the refusal, or None when the request was answered."""
        if turns.value == 0:
            waited = True
            self.state.body_waiting += 1
            try:
                with anyio.move_on_after(self.wait_s) as waiting:
                    await turns.acquire()
            finally:
                self.state.body_waiting -= 1
            if waiting.cancelled_caught:  # still no turn after wait_s
                await self._busy(
                    send,
                    f"every one of the {self.max_receiving} turns to send a request body "
                    f"(KITTI_EVAL_MAX_RECEIVING_BODIES) stayed taken for {self.wait_s:g} s "
                    "(KITTI_EVAL_RECEIVE_WAIT_S)",
                )
                return None
        else:
            await turns.acquire()
        outcome = ""
        try:  # the turn is given back once, whatever happens before the body is read or while it is
            declared = _content_length(scope)
            if declared is not None and _CHUNK < declared <= self.memory.budget:
                self.state.body_waiting += 1
                try:
                    waited = await body.reserve(declared, self.memory_wait_s) or waited
                finally:
                    self.state.body_waiting -= 1
            # after a wait, the refusals known before a body are asked again (e.g. the quota was used meanwhile)
            refused = await self.before_body.refusal(scope) if waited and self.before_body is not None else None
            if refused is None:
                self.receiving += 1
                try:
                    pace = _Pace(self.slow_window_s, self.slow_bytes, body.slow) if body.unfilled else None
                    outcome = await _read_body(receive, body.add, self.limit, self.timeout_s, pace)
                    if outcome == "complete":
                        await body.finish()
                except OSError as e:  # the spool's disk is full: 507, and the partial file goes with body.close()
                    fault = fault_of(e, self.retry_after_s())
                    if fault is None:
                        raise
                    body.close()
                    await _send_json(
                        send,
                        fault.status_code,
                        error_body(fault.code, fault.message),
                        {**fault.headers, "connection": "close"},
                    )
                    return None
                finally:
                    self.receiving -= 1
        finally:
            turns.release()
        return outcome, refused

    async def _busy(self, send: Send, why: str) -> None:
        """Answer 503 ``busy``: ``why``, and when to retry (Retry-After); the connection is closed."""
        retry = self.retry_after_s()
        headers = {"retry-after": str(retry), "connection": "close"}
        await _send_json(send, 503, error_body("busy", f"{why}; retry in {retry} s"), headers)

    async def _too_large(self) -> Message:
        raise BodyTooLarge(self.limit)


#: what a request would be refused with now, known before its body: (caller, path parameters, declared body
#: size, its Idempotency-Key header) -> the error, or None to let the request go on
BeforeBodyCheck = Callable[[Any, dict[str, str], int, "str | None"], "ApiError | None"]


class BeforeBody:
    """The refusals that need no body: ``routes`` are (method, path as the route declares it, check); a check runs on
    a thread (it asks the database) for a caller the door resolved from a bearer token, and says None for anything
    it does not know (the route then answers as always). Asked by :class:`RefuseBeforeBody` when a request arrives,
    and by :class:`BodyMiddleware` again when a request that waited for its turn to send its body gets it."""

    def __init__(
        self,
        routes: Sequence[tuple[str, str, BeforeBodyCheck]],
        *,
        caller_key: str,
        limit: int,
        timeout_s: float,
    ) -> None:
        self.routes = [(method.upper(), compile_path(path)[0], check) for method, path, check in routes]
        self.caller_key = caller_key
        self.limit = limit
        self.timeout_s = timeout_s

    async def refusal(self, scope: Scope) -> ApiError | None:
        if scope["type"] != "http":
            return None
        caller = scope.get(self.caller_key)
        if caller is None or getattr(caller, "session", False):
            return None
        method = str(scope.get("method", "")).upper()
        for wanted, pattern, check in self.routes:
            found = pattern.match(scope.get("path", "")) if method == wanted else None
            if found is not None:
                declared = _content_length(scope) or 0
                raw_key = _header(scope, b"idempotency-key")
                idempotency_key = raw_key.decode("latin-1") if raw_key is not None else None
                return await anyio.to_thread.run_sync(check, caller, found.groupdict(), declared, idempotency_key)
        return None

    async def answer(self, error: ApiError, scope: Scope, receive: Receive, send: Send) -> None:
        """Answer the refusal. A client waiting for ``100 Continue`` (``Expect: 100-continue``, as curl sends with a
        large file) is answered before it sends the body, and its connection closed; another's body is read and
        dropped first, so that it reads its answer on a connection that stays usable (answering mid-body and
        closing would reset the connection under a client still sending)."""
        headers = dict(error.headers)
        body = error_body(error.code, error.message, **getattr(error, "details", {}))
        if (_header(scope, b"expect") or b"").lower() == b"100-continue":
            await _send_json(send, error.status_code, body, {**headers, "connection": "close"})
            return
        outcome = await _read_body(receive, None, self.limit, self.timeout_s)
        if outcome == "gone":
            return
        if outcome != "complete":
            headers["connection"] = "close"
        await _send_json(send, error.status_code, body, headers)


class RefuseBeforeBody:
    """Answer at once a request whose refusal needs no body (:class:`BeforeBody`): a benchmark submission past its
    participant's quota, or while the job queue is full, is refused the same way once its file has arrived, so
    nothing of the file is kept, parsed or stored, and it does not wait for a turn to send it."""

    def __init__(self, app: ASGIApp, *, before_body: BeforeBody) -> None:
        self.app = app
        self.before_body = before_body

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        error = await self.before_body.refusal(scope)
        if error is None:
            await self.app(scope, receive, send)
            return
        await self.before_body.answer(error, scope, receive, send)


class AdmissionMiddleware:
    """Count the evaluation requests in progress (accepted, stored, or waiting for their result), which a
    graceful shutdown lets finish, and refuse new ones while the service drains.

    It runs inside :class:`BodyMiddleware`, so a request is counted from the moment its body has arrived. It
    refuses nothing for being busy: what the service holds is bounded by the job queue's limits
    (:meth:`~kitti_eval_server.jobs.queue.JobQueue.admit`) and the requests waiting for a result by
    ``max_queued_evals`` (past it a request is answered 202 at once)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        paths: frozenset[str],
        retry_after_s: Callable[[], int],
        state: AdmissionState | None = None,
        draining: Callable[[], bool] = lambda: False,
    ) -> None:
        self.app = app
        self.paths = paths
        self.retry_after_s = retry_after_s
        self.state = state or AdmissionState()
        self.draining = draining

    @property
    def in_flight(self) -> int:
        """Evaluation requests in progress."""
        return self.state.in_flight

    @in_flight.setter
    def in_flight(self, value: int) -> None:
        self.state.in_flight = value

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or scope["path"].rstrip("/") not in self.paths:
            await self.app(scope, receive, send)
            return
        if self.draining():
            retry = self.retry_after_s()
            await _send_json(
                send,
                503,
                error_body(
                    "shutting_down", f"this server is shutting down; retry in {retry} s (another replica may answer)"
                ),
                {"retry-after": str(retry), "connection": "close"},
            )
            return
        self.in_flight += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= 1
