"""Slow clients against a real uvicorn: bodies sent a byte at a time do not hold evaluation places, and a body
that misses its deadline is answered 408.

The service keeps its default places (2 evaluating + 8 queued = 10). Ten clients open uploads and send their
bodies one byte every 50 ms; meanwhile a normal upload must get its 201, and each slow one a 408 once the
(shortened) body deadline passes.
"""

from __future__ import annotations

import json
import os
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from server_helpers import ROOT, LiveServer

from kitti_eval_server.middleware import PART_MEMORY_BYTES, BodyMiddleware, BodyTooLarge, part_memory_bytes

SLOW_CLIENTS = 10
RECEIVING = 12  # bodies received at once: the slow clients and the normal upload fit
BODY_TIMEOUT_S = 3
PAUSE_S = 0.05
DEMO_PRED = (ROOT / "kitti_eval/data/demo/result.pkl.gz").read_bytes()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("slow") / "data"
    with LiveServer(data_dir, body_timeout_s=BODY_TIMEOUT_S, max_receiving_bodies=RECEIVING) as server:
        yield server


def multipart(gt: str, payload: bytes) -> tuple[bytes, str]:
    boundary = "slow-client-boundary"
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="gt"\r\n\r\n{gt}\r\n'
        f'--{boundary}\r\nContent-Disposition: form-data; name="predictions"; filename="result.pkl.gz"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    return body + payload + f"\r\n--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"


@dataclass
class SlowClient:
    """An upload whose body goes out one byte per ``PAUSE_S`` until the server answers (or ``stop``)."""

    port: int
    path: str = "/v1/evaluations"
    sent: int = 0
    status: int | None = None
    body: dict = field(default_factory=dict)
    answered_at: float | None = None
    error: BaseException | None = None

    def run(self, stop: threading.Event) -> None:
        try:
            self._run(stop)
        except BaseException as e:  # noqa: BLE001 - reported by the test
            self.error = e

    def _run(self, stop: threading.Event) -> None:
        body, ctype = multipart("demo", DEMO_PRED)
        with socket.create_connection(("127.0.0.1", self.port), timeout=15) as sock:
            head = (
                f"POST {self.path} HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\nContent-Type: {ctype}\r\n"
                f"Content-Length: {len(body)}\r\n\r\n"
            )
            sock.sendall(head.encode())
            while self.sent < len(body) and not stop.is_set():
                readable, _, _ = select.select([sock], [], [], PAUSE_S)
                if readable:  # the server answered: stop sending, read it
                    break
                sock.sendall(body[self.sent : self.sent + 1])
                self.sent += 1
            if stop.is_set():
                return
            raw = b""
            while chunk := sock.recv(65536):
                raw += chunk
        self.answered_at = time.monotonic()
        head, _, payload = raw.partition(b"\r\n\r\n")
        self.status = int(head.split(b" ", 2)[1])
        self.body = json.loads(payload)


def test_slow_bodies_do_not_starve_uploads_and_miss_their_deadline(live) -> None:
    import httpx

    stop = threading.Event()
    slow = [SlowClient(live.port) for _ in range(SLOW_CLIENTS)]
    threads = [threading.Thread(target=c.run, args=(stop,)) for c in slow]
    started = time.monotonic()
    for t in threads:
        t.start()
    try:
        time.sleep(0.5)  # every slow client has sent its head and a few bytes
        assert all(c.sent > 0 and c.status is None for c in slow), [(c.sent, c.status, c.error) for c in slow]
        with httpx.Client(base_url=live.url, timeout=30) as client:
            t0 = time.monotonic()
            response = client.post(
                "/v1/evaluations", data={"gt": "demo"}, files={"predictions": ("result.pkl.gz", DEMO_PRED)}
            )
            upload_s = time.monotonic() - t0
        assert response.status_code == 201, response.text
        assert response.json()["frames"] == 200
        assert all(c.status is None for c in slow)  # they were still sending all along
        print(f"\nupload while {SLOW_CLIENTS} clients trickle: {upload_s:.3f} s")
        for t in threads:
            t.join(BODY_TIMEOUT_S + 10)
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    for c in slow:
        assert c.error is None, c.error
        assert c.status == 408, (c.status, c.body)
        assert c.body["error"]["code"] == "request_timeout"
        assert f"{BODY_TIMEOUT_S} s" in c.body["error"]["message"]
        assert "KITTI_EVAL_BODY_TIMEOUT_S" in c.body["error"]["message"]
        assert c.answered_at is not None
        assert BODY_TIMEOUT_S - 0.5 < c.answered_at - started < BODY_TIMEOUT_S + 3
        assert c.sent < BODY_TIMEOUT_S / PAUSE_S + 10  # nothing was read after the deadline


def open_upload(port: int, declared: int = 10_000) -> socket.socket:
    """An upload whose head and first bytes are sent, and no more."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=15)
    head = (
        f"POST /v1/evaluations HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
        f"Content-Type: multipart/form-data; boundary=b\r\nContent-Length: {declared}\r\n\r\n--b\r\n"
    )
    sock.sendall(head.encode())
    return sock


def answered(sock: socket.socket) -> bool:
    return bool(select.select([sock], [], [], 0)[0])


def read_head(sock: socket.socket, timeout: float) -> bytes:
    """What the server sent until the end of a response's head (or ``timeout``)."""
    sock.settimeout(timeout)
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return data


def test_a_request_past_the_receiving_bodies_waits_its_turn_unread(live) -> None:
    """With every receiving place held, another upload is not refused: it waits, no 100 Continue is sent to it (its
    body is not read), and when a place frees (a client gone mid-body) it is read and answered 201."""
    held = [open_upload(live.port) for _ in range(RECEIVING)]
    waiting = None
    try:
        time.sleep(0.3)
        assert not any(answered(s) for s in held)
        body, ctype = multipart("demo", DEMO_PRED)
        waiting = socket.create_connection(("127.0.0.1", live.port), timeout=15)
        head = (
            f"POST /v1/evaluations HTTP/1.1\r\nHost: 127.0.0.1:{live.port}\r\nContent-Type: {ctype}\r\n"
            f"Content-Length: {len(body)}\r\nExpect: 100-continue\r\n\r\n"
        )
        waiting.sendall(head.encode())
        time.sleep(1.5)
        assert not answered(waiting)  # neither refused nor told to send its body
        held.pop().close()  # gone mid-body: its place is the waiting request's
        assert read_head(waiting, 10).startswith(b"HTTP/1.1 100 Continue")
        waiting.sendall(body)
        response = read_head(waiting, 60)
        assert response.startswith(b"HTTP/1.1 201"), response
        assert not any(answered(s) for s in held)
    finally:
        for sock in [*held, *([waiting] if waiting else [])]:
            sock.close()


# ------------------------------------------------------------------------------------- in process (ASGI)

MB = 1 << 20


class Recorder:
    """An app that reads the whole body and answers 200; or raises, when told to."""

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.body: bytes | None = None
        self.error: BaseException | None = None

    async def __call__(self, scope, receive, send) -> None:
        data = b""
        try:
            while True:
                message = await receive()
                data += message.get("body", b"")
                if not message.get("more_body", False):
                    break
        except BodyTooLarge as e:
            self.error = e
            return
        self.body = data
        if self.fail:
            raise RuntimeError("the app failed")
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})


def call(
    app,
    messages: list[dict],
    *,
    limit: int = 64 * MB,
    timeout_s: float = 5,
    spool_dir: Path | None = None,
    memory_bytes: int = 2 * MB,
):
    """Run BodyMiddleware(app) on one POST whose body arrives as ``messages`` (then nothing, ever), with bodies
    kept in memory up to ``memory_bytes``; the messages it sent back."""
    sent: list[dict] = []
    middleware = BodyMiddleware(
        app,
        limit=limit,
        timeout_s=timeout_s,
        max_receiving=4,
        retry_after_s=lambda: 2,
        spool_dir=spool_dir,
        memory_bytes=memory_bytes,
    )
    anyio.run(post, middleware, "/v1/evaluations", messages, sent)
    assert middleware.receiving == 0
    assert middleware.memory.held == 0  # every body gave its memory back
    return sent


async def post(app, path: str, messages: list[dict], sent: list[dict], declared: int | None = None) -> None:
    """One POST to ``path`` through ``app`` whose body arrives as ``messages`` (then nothing, ever), chunked, or
    with a Content-Length of ``declared``; what it sends back is appended to ``sent``."""
    pending = list(messages)

    async def receive() -> dict:
        if pending:
            return pending.pop(0)
        await anyio.sleep_forever()
        raise AssertionError("unreachable")

    async def send(message: dict) -> None:
        sent.append(message)

    head = [(b"transfer-encoding", b"chunked")] if declared is None else [(b"content-length", str(declared).encode())]
    await app({"type": "http", "method": "POST", "path": path, "headers": head}, receive, send)


def chunks_of(data: bytes, size: int = 64 * 1024) -> list[dict]:
    return [
        {"type": "http.request", "body": data[i : i + size], "more_body": i + size < len(data)}
        for i in range(0, len(data), size)
    ]


@pytest.fixture
def spools(monkeypatch) -> list:
    """The temporary files the middleware opens."""
    import tempfile

    opened = []
    original = tempfile.TemporaryFile

    def recording(*args, **kwargs):
        f = original(*args, **kwargs)
        opened.append(f)
        return f

    monkeypatch.setattr(tempfile, "TemporaryFile", recording)
    return opened


def test_a_large_body_is_spooled_unnamed_and_replayed_whole(spools, tmp_path) -> None:
    data = os.urandom(5 * MB + 123)
    app = Recorder()
    sent = call(app, chunks_of(data), spool_dir=tmp_path)
    assert app.body == data
    assert sent[0]["status"] == 200
    assert len(spools) == 1 and spools[0].closed
    assert list(tmp_path.iterdir()) == []  # unnamed: nothing to remove if the process dies


def test_a_body_within_the_memory_budget_stays_in_memory(spools) -> None:
    data = os.urandom(2 * MB)
    app = Recorder()
    call(app, chunks_of(data), memory_bytes=2 * MB)
    assert app.body == data and spools == []


@pytest.mark.parametrize("case", ["app fails", "client gone", "deadline", "too large"])
def test_the_spool_is_closed_however_the_request_ends(spools, tmp_path, case) -> None:
    data = os.urandom(3 * MB)
    app = Recorder(fail=case == "app fails")
    messages = chunks_of(data)
    if case == "client gone":
        messages = messages[:-1] + [{"type": "http.disconnect"}]
    elif case in ("deadline", "too large"):
        messages[-1]["more_body"] = True  # and then nothing more arrives
    if case == "too large":
        messages.append({"type": "http.request", "body": b"x" * MB, "more_body": True})
    kwargs = {"timeout_s": 0.3} if case == "deadline" else {"limit": 3 * MB + 10} if case == "too large" else {}
    if case == "app fails":
        with pytest.raises(RuntimeError, match="the app failed"):
            call(app, messages, spool_dir=tmp_path)
        sent = []
    else:
        sent = call(app, messages, spool_dir=tmp_path, **kwargs)
    assert len(spools) == 1 and spools[0].closed
    if case == "client gone":
        assert sent == [] and app.body is None and app.error is None  # no one to answer; the app never ran
    elif case == "deadline":
        assert sent[0]["status"] == 408 and app.body is None
        assert json.loads(sent[1]["body"])["error"]["code"] == "request_timeout"
        assert (b"connection", b"close") in sent[0]["headers"]
    elif case == "too large":
        assert isinstance(app.error, BodyTooLarge) and app.error.status_code == 413


def test_bodies_share_the_memory_budget_and_give_it_back(spools, tmp_path) -> None:
    """While one body is held in memory (its app has not answered), a second that would pass the budget goes to
    a file; both replay whole, and the budget is free again once both have been answered."""
    first, second = os.urandom(3 * MB), os.urandom(2 * MB)
    bodies: dict[str, bytes] = {}
    held_while_first_ran: list[int] = []
    second_done, first_in = anyio.Event(), anyio.Event()

    async def app(scope, receive, send) -> None:
        data = b""
        while True:
            message = await receive()
            data += message.get("body", b"")
            if not message.get("more_body", False):
                break
        bodies[scope["path"]] = data
        if scope["path"] == "/first":
            held_while_first_ran.append(middleware.memory.held)
            first_in.set()
            await second_done.wait()  # the first keeps its memory until the second has been answered
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})
        if scope["path"] == "/second":
            second_done.set()

    middleware = BodyMiddleware(
        app,
        limit=64 * MB,
        timeout_s=5,
        max_receiving=4,
        retry_after_s=lambda: 2,
        spool_dir=tmp_path,
        memory_bytes=4 * MB,
    )

    def request(path: str, data: bytes):
        return post(middleware, path, chunks_of(data), [])

    async def both() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(request, "/first", first)
            await first_in.wait()
            tg.start_soon(request, "/second", second)

    anyio.run(both)
    assert bodies == {"/first": first, "/second": second}
    assert held_while_first_ran == [3 * MB]  # the first in memory
    assert len(spools) == 1 and spools[0].closed  # the second in a file: 3 + 2 MB would pass the 4 MB budget
    assert middleware.memory.held == 0


def test_a_request_waits_for_its_turn_as_long_as_the_setting_says_then_busy() -> None:
    """One receiving place, held by a body that never ends: the next request waits ``wait_s`` without a byte of it
    read, then is answered 503 busy naming the setting."""
    sent: list[dict] = []
    read: list[int] = []

    async def send(message: dict) -> None:
        sent.append(message)

    middleware = BodyMiddleware(
        Recorder(), limit=MB, timeout_s=30, max_receiving=1, retry_after_s=lambda: 3, wait_s=0.5
    )

    async def counted(messages: list[dict]):
        async def receive() -> dict:
            read.append(1)
            if messages:
                return messages.pop(0)
            await anyio.sleep_forever()
            raise AssertionError("unreachable")

        return receive

    async def main() -> None:
        scope = {"type": "http", "method": "POST", "path": "/x", "headers": [(b"content-length", b"10")]}
        hold = [{"type": "http.request", "body": b"12345", "more_body": True}]
        async with anyio.create_task_group() as tg:
            tg.start_soon(middleware, scope, await counted(hold), send)
            await anyio.sleep(0.05)
            assert middleware.receiving == 1
            started = time.monotonic()
            before = len(read)
            await middleware(scope, await counted([{"type": "http.request", "body": b"x" * 10}]), send)
            assert 0.45 < time.monotonic() - started < 2 and len(read) == before  # waited, nothing read
            tg.cancel_scope.cancel()

    anyio.run(main)
    assert sent[0]["status"] == 503
    error = json.loads(sent[1]["body"])["error"]
    assert error["code"] == "busy" and "KITTI_EVAL_RECEIVE_WAIT_S" in error["message"]
    assert (b"retry-after", b"3") in sent[0]["headers"]


def test_a_waiting_request_is_asked_the_refusals_before_its_body_again_when_its_turn_comes() -> None:
    """A submission that waited for its turn is checked again (the quota may have been used meanwhile) before its
    body is read: refused, it is answered without a byte of its body read, and its place goes to the next."""
    from kitti_eval_server.errors import ApiError
    from kitti_eval_server.middleware import BeforeBody

    class Used(ApiError):
        status_code = 429
        code = "quota_exceeded"

    asked: list[str] = []

    def check(caller, params, size, key) -> ApiError | None:
        asked.append(params["name"])
        return Used("the quota is used")  # used meanwhile (the first request did not wait: not asked here)

    before_body = BeforeBody([("POST", "/b/{name}", check)], caller_key="caller", limit=MB, timeout_s=5)
    app = Recorder()
    middleware = BodyMiddleware(
        app, limit=MB, timeout_s=30, max_receiving=1, retry_after_s=lambda: 3, before_body=before_body
    )
    sent: list[dict] = []
    read: list[int] = []

    async def send(message: dict) -> None:
        sent.append(message)

    def receiving(stream):
        async def receive() -> dict:
            read.append(1)
            return await stream.receive()

        return receive

    async def main() -> None:
        head = [(b"content-length", b"5"), (b"expect", b"100-continue")]
        scope = {"type": "http", "method": "POST", "path": "/b/bench", "headers": head, "caller": object()}
        first_in, first = anyio.create_memory_object_stream[dict](10)
        second_in, second = anyio.create_memory_object_stream[dict](10)
        await first_in.send({"type": "http.request", "body": b"12", "more_body": True})
        await second_in.send({"type": "http.request", "body": b"12345"})
        async with anyio.create_task_group() as tg:
            tg.start_soon(middleware, scope, receiving(first), send)
            await anyio.sleep(0.05)
            tg.start_soon(middleware, scope, receiving(second), send)
            await anyio.sleep(0.05)
            assert middleware.state.body_waiting == 1 and len(read) == 2  # the first's chunk, and its wait for more
            await first_in.send({"type": "http.request", "body": b"345"})  # the first ends: the second's turn
            await anyio.sleep(0.2)
            tg.cancel_scope.cancel()

    anyio.run(main)
    assert app.body == b"12345" and asked == ["bench"]  # the first was read; the check ran for the waiting one
    statuses = [m["status"] for m in sent if m["type"] == "http.response.start"]
    assert statuses == [200, 429]
    assert len(read) == 2  # the first's two reads; nothing of the second


def test_a_turn_is_given_back_when_the_check_of_a_waiting_request_fails() -> None:
    """The check asked when a waiting request's turn comes reads the database: if it fails, the request fails, and
    its turn goes to the next one (kept, every later request would wait for a turn that never comes back)."""
    from kitti_eval_server.middleware import BeforeBody

    def check(caller, params, size, key):
        raise RuntimeError("the database is away")

    before_body = BeforeBody([("POST", "/b/{name}", check)], caller_key="caller", limit=MB, timeout_s=5)
    middleware = BodyMiddleware(
        Recorder(), limit=MB, timeout_s=30, max_receiving=1, retry_after_s=lambda: 3, before_body=before_body
    )
    failed: list[BaseException] = []

    async def send(message: dict) -> None:
        pass

    async def main() -> None:
        scope = {"type": "http", "method": "POST", "path": "/b/bench", "headers": [(b"content-length", b"5")]}
        scope["caller"] = object()
        first_in, first = anyio.create_memory_object_stream[dict](10)
        second_in, second = anyio.create_memory_object_stream[dict](10)
        await first_in.send({"type": "http.request", "body": b"12", "more_body": True})

        async def waiting() -> None:
            try:
                await middleware(scope, second.receive, send)
            except RuntimeError as e:
                failed.append(e)

        async with anyio.create_task_group() as tg:
            tg.start_soon(middleware, scope, first.receive, send)
            await anyio.sleep(0.05)
            tg.start_soon(waiting)
            await anyio.sleep(0.05)
            assert middleware.state.body_waiting == 1
            await first_in.send({"type": "http.request", "body": b"345"})  # the first ends: the second's turn
            await anyio.sleep(0.2)
            tg.cancel_scope.cancel()

    anyio.run(main)
    assert [str(e) for e in failed] == ["the database is away"]
    assert middleware._turns is not None and middleware._turns.value == 1  # given back: the next one may send
    assert middleware.receiving == 0 and middleware.memory.held == 0


class FormReader:
    """An app that parses the multipart body as the routes do (Starlette's form parser, its spooled file's size
    as the service sets it) and records the uploaded file's bytes and the size up to which it stays in memory."""

    def __init__(self) -> None:
        self.part_memory = 0
        self.content = b""

    async def __call__(self, scope, receive, send) -> None:
        from starlette.requests import Request

        self.part_memory = part_memory_bytes()
        form = await Request(scope, receive).form()
        upload = form["f"]
        self.content = await upload.read()
        await form.close()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})


def multipart_messages(content: bytes) -> list[dict]:
    body = b"".join(
        [
            b'--b\r\nContent-Disposition: form-data; name="f"; filename="result.pkl"\r\n',
            b"Content-Type: application/octet-stream\r\n\r\n",
            content,
            b"\r\n--b--\r\n",
        ]
    )
    return chunks_of(body, 1 * MB)


@pytest.mark.parametrize("memory_mb", [48, 2])
def test_an_uploaded_file_stays_in_memory_when_its_body_was_held_in_memory(spools, monkeypatch, memory_mb) -> None:
    """A val-sized file (past PART_MEMORY_BYTES) whose body was held in memory is not written to a temporary file
    and read back by the form parser; a body past the memory budget (spooled itself) keeps the parser's bound."""
    from starlette.formparsers import MultiPartParser

    monkeypatch.setattr(MultiPartParser, "spool_max_size", property(lambda _: part_memory_bytes()))
    content = os.urandom(PART_MEMORY_BYTES + 3 * MB)
    app = FormReader()
    messages = multipart_messages(content)
    sent = []
    middleware = BodyMiddleware(
        app, limit=64 * MB, timeout_s=5, max_receiving=4, retry_after_s=lambda: 2, memory_bytes=memory_mb * MB
    )

    async def run() -> None:
        pending = list(messages)

        async def receive() -> dict:
            return pending.pop(0) if pending else {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)

        headers = [(b"content-type", b"multipart/form-data; boundary=b"), (b"transfer-encoding", b"chunked")]
        await middleware(
            {"type": "http", "method": "POST", "path": "/v1/evaluations", "headers": headers}, receive, send
        )

    anyio.run(run)
    assert sent[0]["status"] == 200 and app.content == content
    assert part_memory_bytes() == PART_MEMORY_BYTES  # outside a request
    if memory_mb == 48:  # held in memory: the file too, no temporary file at all
        assert app.part_memory >= len(content) and spools == []
    else:  # the body spooled, and the file past PART_MEMORY_BYTES spooled by the parser as before
        assert app.part_memory == PART_MEMORY_BYTES and len(spools) == 2


# ------------------------------------------------------------------ bodies of declared length wait for memory


class Holding:
    """An app that reads the whole body, then holds its request (and so its body's memory) until told to end it."""

    def __init__(self) -> None:
        self.bodies: dict[str, bytes] = {}
        self.arrived: dict[str, anyio.Event] = {}
        self.release: dict[str, anyio.Event] = {}

    def expect(self, *paths: str) -> None:
        for path in paths:
            self.arrived[path], self.release[path] = anyio.Event(), anyio.Event()

    async def __call__(self, scope, receive, send) -> None:
        data = b""
        while True:
            message = await receive()
            data += message.get("body", b"")
            if not message.get("more_body", False):
                break
        self.bodies[scope["path"]] = data
        self.arrived[scope["path"]].set()
        await self.release[scope["path"]].wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})


async def post_declared(app, path: str, data: bytes) -> None:
    """One POST of ``data`` with its Content-Length, as curl sends a file."""
    await post(app, path, chunks_of(data), [], declared=len(data))


def holding_middleware(app, tmp_path: Path, **kwargs) -> BodyMiddleware:
    options = {"limit": 64 * MB, "timeout_s": 5, "max_receiving": 4, "retry_after_s": lambda: 2}
    return BodyMiddleware(app, spool_dir=tmp_path, **{**options, **kwargs})


def test_a_body_of_declared_length_waits_for_room_in_memory_instead_of_going_to_disk(spools, tmp_path) -> None:
    """Budget 4 MB; a 3 MB body is held by its request. A 2 MB body that declares its length is not read (and
    not written to a file) while it would pass the budget: it waits, counted among the bodies waiting, and is
    received in memory once the first request ends. No temporary file at all."""
    first, second = os.urandom(3 * MB), os.urandom(2 * MB)
    app = Holding()
    app.expect("/first", "/second")
    middleware = holding_middleware(app, tmp_path, memory_bytes=4 * MB, memory_wait_s=30)
    seen: dict[str, object] = {}

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(post_declared, middleware, "/first", first)
            await app.arrived["/first"].wait()
            tg.start_soon(post_declared, middleware, "/second", second)
            await anyio.sleep(0.2)
            seen["while"] = (middleware.memory.held, middleware.state.body_waiting, "/second" in app.bodies)
            app.release["/first"].set()
            await app.arrived["/second"].wait()
            seen["after"] = middleware.memory.held
            app.release["/second"].set()

    anyio.run(main)
    assert seen["while"] == (3 * MB, 1, False)  # the first's 3 MB held; the second waits, unread
    assert seen["after"] == 2 * MB  # the first gave its 3 MB back; the second holds its own
    assert app.bodies == {"/first": first, "/second": second}
    assert spools == []  # neither went to disk
    assert middleware.memory.held == 0 and not middleware.memory.waiting


def test_a_body_that_waited_for_memory_too_long_goes_to_a_file(spools, tmp_path) -> None:
    """The same, with ``memory_wait_s`` 0.2 s and the first request held past it: the second goes to a file after
    0.2 s and is answered while the first still holds its memory."""
    first, second = os.urandom(3 * MB), os.urandom(2 * MB)
    app = Holding()
    app.expect("/first", "/second")
    middleware = holding_middleware(app, tmp_path, memory_bytes=4 * MB, memory_wait_s=0.2)

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(post_declared, middleware, "/first", first)
            await app.arrived["/first"].wait()
            tg.start_soon(post_declared, middleware, "/second", second)
            with anyio.fail_after(5):
                await app.arrived["/second"].wait()
            assert middleware.memory.held == 3 * MB  # the first's alone: the second is on disk
            app.release["/second"].set()
            app.release["/first"].set()

    anyio.run(main)
    assert app.bodies == {"/first": first, "/second": second}
    assert len(spools) == 1 and spools[0].closed
    assert middleware.memory.held == 0 and not middleware.memory.waiting


@pytest.mark.parametrize("size", [5 * MB, 64 * 1024])
def test_a_body_larger_than_the_budget_or_a_small_one_does_not_wait(spools, tmp_path, size) -> None:
    """A body larger than the whole budget could never fit: it goes to a file at once. A body of up to 1 MB (a
    JSON request) never waits behind uploads: in memory if it fits, else in a file at once."""
    app = Holding()
    app.expect("/first", "/big")
    middleware = holding_middleware(app, tmp_path, memory_bytes=4 * MB, memory_wait_s=30)
    data = os.urandom(size)

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(post_declared, middleware, "/first", os.urandom(4 * MB))  # the whole budget
            await app.arrived["/first"].wait()
            tg.start_soon(post_declared, middleware, "/big", data)
            with anyio.fail_after(5):
                await app.arrived["/big"].wait()
            app.release["/big"].set()
            app.release["/first"].set()

    anyio.run(main)
    assert app.bodies["/big"] == data and len(spools) == 1
    assert middleware.memory.held == 0


def test_a_submission_that_waited_for_memory_is_asked_its_refusals_again() -> None:
    """A submission whose body waited for room in memory is checked again before it is read (the quota may have
    been used meanwhile), as one that waited for its turn."""
    from kitti_eval_server.errors import ApiError
    from kitti_eval_server.middleware import BeforeBody

    class Used(ApiError):
        status_code = 429
        code = "quota_exceeded"

    asked: list[str] = []

    def check(caller, params, size, key) -> ApiError | None:
        asked.append(params["name"])
        return Used("the quota is used")

    app = Holding()
    app.expect("/first")
    before_body = BeforeBody([("POST", "/b/{name}", check)], caller_key="caller", limit=64 * MB, timeout_s=5)
    middleware = BodyMiddleware(
        app, limit=64 * MB, timeout_s=5, max_receiving=4, retry_after_s=lambda: 3, memory_bytes=4 * MB,
        before_body=before_body,
    )  # fmt: skip
    sent: list[dict] = []
    data = os.urandom(2 * MB)
    head = [(b"content-length", str(len(data)).encode()), (b"expect", b"100-continue")]
    read: list[int] = []

    async def receive() -> dict:
        read.append(1)
        return {"type": "http.request", "body": data}

    async def send(message: dict) -> None:
        sent.append(message)

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(post_declared, middleware, "/first", os.urandom(3 * MB))
            await app.arrived["/first"].wait()
            scope = {"type": "http", "method": "POST", "path": "/b/bench", "headers": head, "caller": object()}
            tg.start_soon(middleware, scope, receive, send)
            await anyio.sleep(0.1)
            assert asked == [] and middleware.state.body_waiting == 1
            app.release["/first"].set()

    anyio.run(main)
    assert asked == ["bench"] and read == []  # asked after its wait; not a byte of it read
    assert [m["status"] for m in sent if m["type"] == "http.response.start"] == [429]
    assert middleware.memory.held == 0 and not middleware.memory.waiting


waiter = st.tuples(
    st.integers(1, 100),  # bytes wanted, of a budget of 100 (each waiter's own number: it names it)
    st.integers(0, 4),  # ms held once granted
    st.integers(0, 20),  # ms it may wait
    st.booleans(),  # whether its client goes away (its task is cancelled) within 3 ms
)


@settings(max_examples=100, deadline=None)
@given(st.lists(waiter, min_size=1, max_size=12, unique_by=lambda w: w[0]))
def test_the_memory_budget_is_never_passed_and_grants_come_first_come_first_served(waiters) -> None:
    """Bodies asking for room in turn, holding it, timing out or going away in any order: what is held never
    passes the budget; those that waited are granted in the order they asked; afterwards nothing is held and
    no one waits (a waiter cancelled just after its grant gave its bytes back)."""
    from kitti_eval_server.middleware import _Memory

    class Recorded(_Memory):
        def _grant(self) -> None:
            before = [n for n, _ in self.waiting]
            super()._grant()
            still = {n for n, _ in self.waiting}
            granted.extend(n for n in before if n not in still)
            assert self.held <= self.budget

    memory = Recorded(100)
    asked: list[int] = []
    granted: list[int] = []

    async def one(n: int, hold_ms: int, wait_ms: int, goes_away: bool) -> None:
        with anyio.move_on_after(0.003 if goes_away else 60):
            asked.append(n)
            taken, _ = await memory.reserve(n, wait_ms / 1000)
            assert memory.held <= memory.budget
            if taken:
                try:
                    await anyio.sleep(hold_ms / 1000)
                finally:
                    memory.give(taken)

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            for w in waiters:
                tg.start_soon(one, *w)
                await anyio.sleep(0.001)

    anyio.run(main)
    assert memory.held == 0 and not memory.waiting
    assert granted == sorted(granted, key=asked.index)


def test_a_body_that_sends_too_slowly_gives_back_the_room_it_held(spools, tmp_path) -> None:
    """Budget 4 MB. A request declares 3 MB, sends 64 KB and then nothing: once a pace window (0.2 s here) ends
    with too few bytes, the room reserved for the rest goes back, and a 2 MB body waiting for it is received in
    memory at once, long before the silent one's body deadline (408)."""
    second = os.urandom(2 * MB)
    app = Holding()
    app.expect("/second")
    middleware = holding_middleware(app, tmp_path, memory_bytes=4 * MB, memory_wait_s=30, timeout_s=3)
    middleware.slow_window_s = 0.2
    sent: list[dict] = []
    took: dict[str, float] = {}

    start = [{"type": "http.request", "body": b"x" * (64 * 1024), "more_body": True}]  # then nothing

    async def main() -> None:
        started = anyio.current_time()
        async with anyio.create_task_group() as tg:
            tg.start_soon(post, middleware, "/silent", start, sent, 3 * MB)
            await anyio.sleep(0.05)
            assert middleware.memory.held == 3 * MB  # the silent one's reservation
            tg.start_soon(post_declared, middleware, "/second", second)
            await app.arrived["/second"].wait()
            took["second"] = anyio.current_time() - started
            app.release["/second"].set()

    anyio.run(main)
    assert took["second"] < 1.5  # within a pace window or two, not the 3 s deadline
    assert app.bodies == {"/second": second} and spools == []
    assert [m["status"] for m in sent if m["type"] == "http.response.start"] == [408]
    assert middleware.memory.held == 0 and not middleware.memory.waiting


def test_a_body_arriving_at_pace_keeps_its_room() -> None:
    """A body whose bytes keep coming (each window above the pace) is never told it is slow; one window short is
    told once."""
    from kitti_eval_server.middleware import _Pace

    told: list[int] = []

    async def main() -> None:
        pace = _Pace(1.0, 500, lambda: told.append(1))
        for _ in range(30):
            await anyio.sleep(0.05)
            pace.arrived(600)  # about 20 arrivals a window: any one of them is enough
        assert told == []
        await anyio.sleep(2.5)
        pace.check()
        pace.check()

    anyio.run(main)
    assert told == [1]


def test_one_client_cannot_hold_every_turn_to_send_a_body() -> None:
    """Four turns, two a client. Client A opens three uploads that send nothing: its third waits, unread, for one
    of its own (counted among the bodies waiting), while client B's upload takes a turn at once and is answered;
    past ``wait_s`` A's third is answered 503 ``busy`` naming the setting. Nothing is held afterwards."""
    app = Recorder()
    middleware = BodyMiddleware(
        app, limit=MB, timeout_s=30, max_receiving=4, retry_after_s=lambda: 3, wait_s=1.0,
        per_client=2, client_of=lambda scope: scope["client"][0],
    )  # fmt: skip
    answers: dict[str, list[dict]] = {}
    read: dict[str, int] = {}

    def request(name: str, address: str, chunks: list[dict]):
        pending = list(chunks)
        answers[name], read[name] = [], 0

        async def receive() -> dict:
            read[name] += 1
            if pending:
                return pending.pop(0)
            await anyio.sleep_forever()
            raise AssertionError("unreachable")

        async def send(message: dict) -> None:
            answers[name].append(message)

        head = [(b"content-length", b"5")]
        scope = {"type": "http", "method": "POST", "path": "/x", "headers": head, "client": (address, 1)}
        return middleware(scope, receive, send)

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            for i in range(3):
                tg.start_soon(request, f"a{i}", "10.0.0.1", [])  # sends nothing
                await anyio.sleep(0.02)
            assert middleware.state.body_waiting == 1 and read["a2"] == 0
            tg.start_soon(request, "b", "10.0.0.2", [{"type": "http.request", "body": b"12345"}])
            with anyio.fail_after(0.9):  # B is not held behind A: answered before A's third gives up (1 s)
                while app.body is None:
                    await anyio.sleep(0.01)
            assert not answers["a2"]
            with anyio.fail_after(10):  # past wait_s: A's third is answered
                while not answers["a2"]:
                    await anyio.sleep(0.05)
            tg.cancel_scope.cancel()

    anyio.run(main)
    statuses = {
        name: [m["status"] for m in sent if m["type"] == "http.response.start"] for name, sent in answers.items()
    }
    assert statuses == {"a0": [], "a1": [], "a2": [503], "b": [200]}, statuses
    body = json.loads(next(m["body"] for m in answers["a2"] if m["type"] == "http.response.body"))
    assert body["error"]["code"] == "busy" and "KITTI_EVAL_MAX_RECEIVING_PER_CLIENT" in body["error"]["message"]
    assert read["a2"] == 0  # not a byte of it read
    assert middleware.receiving == 0 and len(middleware.client_turns) == 0  # type: ignore[arg-type]
