"""Accounts mode at the door: every request but the probes, the static files and the sign-in page carries a
token (``Authorization: Bearer``, or the web session's cookie), checked before its body is read.

A client (by IP address: :func:`client_of`) whose tokens were refused ``auth_max_failures`` times within
``auth_failure_window_s`` gets 429 with Retry-After until the window has passed, without its token being looked
at. The count lives in the process: each replica keeps its own, so behind a load balancer over n replicas a
client gets at most n times the limit.
"""

from __future__ import annotations

import ipaddress
import re
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable
from functools import partial
from http.cookies import SimpleCookie

import anyio.to_thread
from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from .accounts import Accounts, Caller, TokenRefused
from .errors import TooManyRequests, Unauthorized, error_response, fault_of

__all__ = ["AuthMiddleware", "FailureLimiter", "CALLER_KEY", "SESSION_COOKIE", "CSRF_COOKIE", "is_public", "client_of"]

CALLER_KEY = "kitti_eval.caller"
SESSION_COOKIE = "kitti_eval_session"
#: the sign-in form's CSRF token (before there is a session)
CSRF_COOKIE = "kitti_eval_signin"
_PUBLIC = frozenset({"/healthz", "/readyz", "/signin", "/favicon.ico"})
_PUBLIC_PREFIXES = ("/static/", "/static-offline-docs/")
#: a benchmark's description and board: read without a token when the benchmark is public (the route decides;
#: a request that carries a token is checked as anywhere else)
_BOARD_PATHS = re.compile(r"^(/v1/benchmarks(/[^/]+(/leaderboard|/frames)?)?|/benchmarks(/[^/]+)?)$")
#: clients whose failures are remembered at once (the oldest are forgotten first)
_MAX_CLIENTS = 10_000


def is_public(path: str) -> bool:
    """Paths answered without a token: the probes, the static files, the sign-in page, and the boards of public
    benchmarks (:func:`is_board`)."""
    return path in _PUBLIC or path.startswith(_PUBLIC_PREFIXES) or is_board(path)


def is_board(path: str) -> bool:
    """Read (GET) without a token, a benchmark's page, description, frame ids and leaderboard are served when the
    benchmark is public; the route answers 404 for the others."""
    return _BOARD_PATHS.fullmatch(path) is not None


def is_api(path: str) -> bool:
    """Paths a program calls (answered with JSON); the others are pages (answered with the sign-in page)."""
    return path.startswith("/v1/") or path in ("/v1", "/openapi.json", "/metrics")


Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def client_of(scope: Scope) -> str:
    """The client's address: the socket peer, or, when the peer is a trusted proxy
    (``KITTI_EVAL_TRUSTED_PROXIES``), the right-most address of ``X-Forwarded-For`` that is not itself a trusted
    proxy (all of them trusted: the left-most). A header that does not give one (absent, or not an address
    where the walk stops) leaves the peer. The proxies are ``app.state.trusted_proxies`` (set by ``create_app``).
    The failure limit, the audit log and the log lines all name this address."""
    client = scope.get("client")
    peer = str(client[0]) if client else "unknown"
    app = scope.get("app")
    trusted: tuple[Network, ...] = getattr(getattr(app, "state", None), "trusted_proxies", None) or ()
    if not trusted or not _is_trusted(_address(peer), trusted):
        return peer
    hops = [hop.strip() for value in _headers(scope, b"x-forwarded-for") for hop in value.split(",")]
    for hop in reversed(hops):
        address = _address(hop)
        if address is None:
            return peer
        if not _is_trusted(address, trusted):
            return str(address)
    first = _address(hops[0]) if hops else None
    return str(first) if first is not None else peer


def _address(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        address = ipaddress.ip_address(text)
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped  # a dual-stack socket's view of an IPv4 peer
    return address


def _is_trusted(address: ipaddress.IPv4Address | ipaddress.IPv6Address | None, trusted: tuple[Network, ...]) -> bool:
    return address is not None and any(address in network for network in trusted)


class FailureLimiter:
    """Refused tokens per client within a sliding window; in memory, per process."""

    def __init__(self, max_failures: int, window_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_failures = max_failures
        self.window_s = window_s
        self.clock = clock
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()

    def _recent(self, client: str) -> deque[float] | None:
        times = self._failures.get(client)
        if times is None:
            return None
        cutoff = self.clock() - self.window_s
        while times and times[0] <= cutoff:
            times.popleft()
        if not times:
            del self._failures[client]
            return None
        return times

    def retry_after(self, client: str) -> int | None:
        """Seconds until the client may try again, or None when it may now."""
        times = self._recent(client)
        if times is None or len(times) < self.max_failures:
            return None
        return max(1, int(times[0] + self.window_s - self.clock()) + 1)

    def fail(self, client: str) -> None:
        times = self._recent(client) or deque()
        times.append(self.clock())
        while len(times) > self.max_failures:
            times.popleft()
        self._failures[client] = times
        self._failures.move_to_end(client)
        while len(self._failures) > _MAX_CLIENTS:
            self._failures.popitem(last=False)

    def check(self, client: str) -> None:
        retry = self.retry_after(client)
        if retry is not None:
            raise TooManyRequests(f"too many refused tokens from this address; retry in {retry} s", retry)


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return bytes(value).decode("latin-1")
    return None


def _headers(scope: Scope, name: bytes) -> list[str]:
    """Every value of a header, in order (a header sent several times reads as their comma-joined list)."""
    return [bytes(value).decode("latin-1") for key, value in scope.get("headers", ()) if key.lower() == name]


def bearer(scope: Scope) -> str | None:
    value = _header(scope, b"authorization")
    if value is None:
        return None
    scheme, _, credentials = value.strip().partition(" ")
    credentials = credentials.strip()
    return credentials if scheme.lower() == "bearer" and credentials else None


def cookie(scope: Scope, name: str) -> str | None:
    value = _header(scope, b"cookie")
    if not value:
        return None
    jar: SimpleCookie = SimpleCookie()
    try:
        jar.load(value)
    except Exception:  # noqa: BLE001 - a malformed cookie header is no cookie
        return None
    morsel = jar.get(name)
    return morsel.value if morsel is not None and morsel.value else None


class AuthMiddleware:
    """Resolve the caller of every non-public request (``scope[CALLER_KEY]``) or answer 401/429 itself."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        accounts: Accounts,
        limiter: FailureLimiter,
        sign_in_page: Callable[[Scope, int, str | None], Awaitable[Response]],
        own_token_paths: frozenset[str] = frozenset(),
        retry_after_s: Callable[[], int] = lambda: 2,
    ) -> None:
        self.app = app
        self.retry_after_s = retry_after_s  # of a 503 when the token cannot be looked up
        self.accounts = accounts
        self.limiter = limiter
        self.sign_in_page = sign_in_page
        #: paths that check a token of their own (``/metrics`` with KITTI_EVAL_METRICS_TOKEN: a scraper's)
        self.own_token_paths = own_token_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        board = scope["type"] == "http" and is_board(path)
        if scope["type"] != "http" or (is_public(path) and not board) or path in self.own_token_paths:
            await self.app(scope, receive, send)
            return
        client = client_of(scope)
        token = bearer(scope)
        via_cookie = False
        if token is None:
            token = cookie(scope, SESSION_COOKIE)
            via_cookie = token is not None
        if token is None and board and scope.get("method") in ("GET", "HEAD"):
            await self.app(scope, receive, send)  # no caller: the route serves public benchmarks only
            return
        retry = self.limiter.retry_after(client)
        if retry is not None:
            error: Unauthorized | TooManyRequests = TooManyRequests(
                f"too many refused tokens from this address; retry in {retry} s", retry
            )
            await self._refuse(scope, receive, send, error)
            return
        if token is None:
            await self._refuse(scope, receive, send, Unauthorized("sign in: send 'Authorization: Bearer <token>'"))
            return
        try:
            try:
                caller: Caller = await anyio.to_thread.run_sync(
                    lambda: self.accounts.resolve(token, session=via_cookie)
                )
            except TokenRefused as e:
                self.limiter.fail(client)
                await anyio.to_thread.run_sync(partial(self.accounts.refused, e, client=client, target=path))
                await self._refuse(scope, receive, send, e, clear_cookie=via_cookie)
                return
        except Exception as e:  # the token could not be looked up: the database is down or locked
            fault = fault_of(e, self.retry_after_s())
            if fault is None:
                raise
            response = error_response(fault.status_code, fault.code, fault.message, fault.headers)
            response.headers["connection"] = "close"  # the body, if any, is not read
            await response(scope, receive, send)
            return
        scope[CALLER_KEY] = caller
        await self.app(scope, receive, send)

    async def _refuse(
        self,
        scope: Scope,
        receive: Receive,
        send: Send,
        error: Unauthorized | TooManyRequests,
        clear_cookie: bool = False,
    ) -> None:
        if is_api(scope["path"]):
            response: Response = error_response(error.status_code, error.code, error.message, error.headers)
        else:
            response = await self.sign_in_page(scope, error.status_code, error.message)
            response.headers.update(error.headers)
        if clear_cookie:
            response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
        response.headers["connection"] = "close"  # the body, if any, is not read
        await response(scope, receive, send)
