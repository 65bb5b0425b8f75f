"""The door: every request meets the access its route declared before anything else reads it.

Each route declares its :class:`~kitti_eval_server.access.policy.Access` where it is declared (its access dependency
in :mod:`kitti_eval_server.access.deps`); the door finds the route a request is for and, in accounts mode, checks the
token (``Authorization: Bearer``, or the web session's cookie) before the body is read. A route that declares
no access is refused, in both modes (fail closed); an API path no route serves asks for a token before it is
told 404, a page path is told 404 at once. Only then does the route's dependency ask
:class:`~kitti_eval_server.access.policy.Policy` whether the caller may do what the route does.

A client (by IP address, :func:`client_of`) whose tokens were refused ``auth_max_failures`` times within
``auth_failure_window_s`` gets 429 with Retry-After until the window has passed, without its token being
looked at. The count lives in the process: each replica keeps its own, so behind a load balancer over n
replicas a client gets at most n times the limit.
"""

from __future__ import annotations

import ipaddress
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable, Mapping, Sequence
from functools import partial
from http.cookies import SimpleCookie
from typing import Any

import anyio.to_thread
from fastapi.routing import APIRoute
from starlette.responses import Response
from starlette.routing import BaseRoute, Match, Mount
from starlette.types import ASGIApp, Receive, Scope, Send

from ..errors import ApiError, Forbidden, TooManyRequests, Unauthorized, error_response, fault_of, is_api
from .accounts import Accounts, TokenRefused
from .policy import CSRF_HEADER, SAFE_METHODS, Access, Caller, Policy

__all__ = [
    "AuthMiddleware",
    "Door",
    "FailureLimiter",
    "CALLER_KEY",
    "SESSION_COOKIE",
    "CSRF_COOKIE",
    "HOST_PREFIX",
    "over_https",
    "session_cookie",
    "signin_cookie",
    "join_cookie",
    "access_of",
    "client_of",
    "flat_routes",
    "check_token",
]

#: the caller the door resolved from a token (accounts mode)
CALLER_KEY = "kitti_eval.caller"
SESSION_COOKIE = "kitti_eval_session"
#: the sign-in form's CSRF token (before there is a session)
CSRF_COOKIE = "kitti_eval_signin"
#: behind HTTPS the cookies' names carry this prefix: the browser then takes them only from this very origin
#: over a secure connection, for the whole site (Secure, Path=/, no Domain), so a page on another port or a
#: sibling subdomain cannot plant or shadow them
HOST_PREFIX = "__Host-"


def over_https(scope: Scope) -> bool:
    """Whether the request came over HTTPS: to the service itself, or to a trusted proxy
    (``KITTI_EVAL_TRUSTED_PROXIES``) that ends TLS and says so in ``X-Forwarded-Proto``, as it says whose request it
    passes on in ``X-Forwarded-For``."""
    if scope.get("scheme") == "https":
        return True
    forwarded = _headers(scope, b"x-forwarded-proto")[:1]
    return bool(forwarded) and forwarded[0].split(",")[0].strip().lower() == "https" and _from_trusted_proxy(scope)


def session_cookie(scope: Scope) -> str:
    """The session cookie's name for this request: ``__Host-kitti_eval_session`` over HTTPS."""
    return HOST_PREFIX + SESSION_COOKIE if over_https(scope) else SESSION_COOKIE


def signin_cookie(scope: Scope) -> tuple[str, str]:
    """The sign-in form's CSRF cookie: its name and path (over HTTPS ``__Host-kitti_eval_signin`` on ``/``, as
    the prefix requires; else limited to ``/signin``)."""
    return (HOST_PREFIX + CSRF_COOKIE, "/") if over_https(scope) else (CSRF_COOKIE, "/signin")


def join_cookie(scope: Scope) -> tuple[str, str]:
    """The join page's CSRF cookie (the sign-in form's kind of token: there is no session yet): its name and path
    (over HTTPS the sign-in form's ``__Host-`` cookie on ``/``; else limited to ``/join``)."""
    return (HOST_PREFIX + CSRF_COOKIE, "/") if over_https(scope) else (CSRF_COOKIE, "/join")


#: clients whose failures are remembered at once (the oldest are forgotten first)
_MAX_CLIENTS = 10_000


def access_of(dependant: Any) -> set[Access]:
    """The accesses a route's dependencies declare (exactly one for a route that declares its access)."""
    found: set[Access] = set()
    for sub in getattr(dependant, "dependencies", ()):
        access = getattr(sub.call, "access", None)
        if isinstance(access, Access):
            found.add(access)
        found |= access_of(sub)
    return found


def flat_routes(routes: Sequence[BaseRoute]) -> list[BaseRoute]:
    """The app's routes with those of included routers (newer FastAPI keeps an included router whole)."""
    out: list[BaseRoute] = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        out += flat_routes(inner.routes) if inner is not None else [route]
    return out


class Door:
    """Which access the route a request is for declared: an :class:`APIRoute`'s access dependency, or, for
    what FastAPI and Starlette add themselves (the OpenAPI document, the docs page, mounted static files),
    the access given where the app adds them (``declared``: path -> access)."""

    def __init__(self, routes: Callable[[], Sequence[BaseRoute]], declared: Mapping[str, Access]) -> None:
        self._routes = routes
        self._declared = dict(declared)
        self._table: list[tuple[BaseRoute, Access | None]] | None = None

    def table(self) -> list[tuple[BaseRoute, Access | None]]:
        """(route, its access or None when it declares none), built once."""
        if self._table is None:
            table: list[tuple[BaseRoute, Access | None]] = []
            for route in flat_routes(self._routes()):
                if isinstance(route, APIRoute):
                    found = access_of(route.dependant)
                    if len(found) > 1:
                        raise RuntimeError(f"route {route.path} declares several accesses: {sorted(found)}")
                    table.append((route, found.pop() if found else self._declared.get(route.path)))
                else:
                    table.append((route, self._declared.get(getattr(route, "path", ""))))
            self._table = table
        return self._table

    def template(self, scope: Scope) -> str | None:
        """The path template of the route that serves ``scope``'s path (None: none does), for the request metrics
        of an answer given before the router ran."""
        partial: str | None = None
        for route, _ in self.table():
            match, _ = route.matches(scope)
            path = getattr(route, "path_format", None) or getattr(route, "path", None)
            if match is Match.FULL and isinstance(path, str):
                return path
            if match is Match.PARTIAL and partial is None and isinstance(path, str) and not isinstance(route, Mount):
                partial = path
        return partial

    def access(self, scope: Scope) -> tuple[bool, Access | None]:
        """(whether a route serves the path, its access); a method the route does not take still finds it."""
        partial_match: tuple[bool, Access | None] | None = None
        for route, access in self.table():
            match, _ = route.matches(scope)
            if match is Match.FULL:
                return True, access
            if match is Match.PARTIAL and partial_match is None and not isinstance(route, Mount):
                partial_match = (True, access)
        return partial_match or (False, None)


Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def client_of(scope: Scope) -> str:
    """The client's address: the socket peer, or, when the peer is a trusted proxy
    (``KITTI_EVAL_TRUSTED_PROXIES``), the right-most address of ``X-Forwarded-For`` that is not itself a trusted
    proxy (all of them trusted: the left-most). A header that does not give one (absent, or not an address
    where the walk stops) leaves the peer. The proxies are ``app.state.trusted_proxies`` (set by ``create_app``).
    The failure limit, the audit log and the log lines all name this address."""
    client = scope.get("client")
    peer = str(client[0]) if client else "unknown"
    if not _from_trusted_proxy(scope):
        return peer
    trusted = _trusted(scope)
    hops = [hop.strip() for value in _headers(scope, b"x-forwarded-for") for hop in value.split(",")]
    for hop in reversed(hops):
        address = _address(hop)
        if address is None:
            return peer
        if not _is_trusted(address, trusted):
            return str(address)
    first = _address(hops[0]) if hops else None
    return str(first) if first is not None else peer


def _from_trusted_proxy(scope: Scope) -> bool:
    """Whether the socket peer is one of ``KITTI_EVAL_TRUSTED_PROXIES``."""
    client = scope.get("client")
    return client is not None and _is_trusted(_address(str(client[0])), _trusted(scope))


def _trusted(scope: Scope) -> tuple[Network, ...]:
    """The trusted proxies: ``app.state.trusted_proxies`` (set by ``create_app``)."""
    return getattr(getattr(scope.get("app"), "state", None), "trusted_proxies", None) or ()


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

    def __init__(
        self,
        max_failures: int,
        window_s: float,
        clock: Callable[[], float] = time.monotonic,
        *,
        what: str = "refused tokens",
    ) -> None:
        """``what``: what is counted, as the 429's message names it."""
        self.what = what
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
            raise TooManyRequests(f"too many {self.what} from this address; retry in {retry} s", retry)


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


_DEFAULT_PORTS = {"http": "80", "https": "443"}


def _origin_of(scheme: str, host: str) -> tuple[str, str]:
    """(scheme, host[:port] without the scheme's default port), lower case."""
    scheme, host = scheme.lower(), host.strip().lower()
    default = _DEFAULT_PORTS.get(scheme)
    if default and host.endswith(":" + default):
        host = host[: -len(default) - 1]
    return scheme, host


def cross_site(scope: Scope) -> str | None:
    """Why a change sent by a browser came from another origin than the service's own, or None. A browser
    says where a request comes from (``Sec-Fetch-Site``, ``Origin``); a client that says neither (curl, a
    script) is not a browser carrying someone's cookie. The service's own origin is the request's ``Host``
    (another port of the same host is another origin), or the ``X-Forwarded-Host`` a trusted proxy
    (``KITTI_EVAL_TRUSTED_PROXIES``) passes on; its scheme is compared when the request came over HTTPS
    (:func:`over_https`; behind a proxy that ends TLS and does not say so, it sees http where the browser says
    https)."""
    site = _header(scope, b"sec-fetch-site")
    if site is not None and site.strip().lower() not in ("same-origin", "none"):
        return f"the browser says it comes from another site (Sec-Fetch-Site: {site.strip()[:40]})"
    origin = _header(scope, b"origin")
    if origin is None:
        return None
    scheme, _, rest = origin.strip().partition("://")
    if not rest or origin.strip() == "null":
        return "the browser sent no usable Origin"
    sent_scheme, sent_host = _origin_of(scheme, rest.rstrip("/"))
    own_scheme = "https" if over_https(scope) else "http"
    hosts = [_header(scope, b"host") or ""]
    if _from_trusted_proxy(scope):  # a proxy that passes the browser's host on says so
        hosts += [h.split(",")[0].strip() for h in _headers(scope, b"x-forwarded-host")[:1]]
    own = {_origin_of(s, h)[1] for h in hosts for s in (own_scheme, sent_scheme)}
    if sent_host not in own:
        return "it comes from another origin"
    if own_scheme == "https" and sent_scheme != "https":
        return "it comes from another origin"
    return None


async def check_token(
    accounts: Accounts, limiter: FailureLimiter, token: str, *, client: str, target: str, session: bool = False
) -> Caller:
    """The door's check of a token (or a session, ``session``), also the sign-in form's: the caller it stands
    for; a refused token counts against the client's failures and goes to the audit log (TokenRefused)."""
    try:
        return await anyio.to_thread.run_sync(lambda: accounts.resolve(token, session=session))
    except TokenRefused as e:
        limiter.fail(client)
        await anyio.to_thread.run_sync(partial(accounts.refused, e, client=client, target=target))
        raise


class AuthMiddleware:
    """Refuse what the route's declared access refuses before the body is read: a route that declares none
    (both modes), and in accounts mode a request without a valid token (401/429) where one is needed, or a
    web session's change to the JSON API without its CSRF header. Sets the caller a token stands for
    (``scope[CALLER_KEY]``); the route's access dependency then asks the policy."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        policy: Policy,
        door: Door,
        accounts: Accounts,
        limiter: FailureLimiter,
        sign_in_page: Callable[[Scope, int, str | None], Awaitable[Response]],
        retry_after_s: Callable[[], int] = lambda: 2,
    ) -> None:
        self.app = app
        self.policy = policy
        self.door = door
        self.retry_after_s = retry_after_s  # of a 503 when the token cannot be looked up
        self.accounts = accounts
        self.limiter = limiter
        self.sign_in_page = sign_in_page

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        method = str(scope.get("method", "GET")).upper()
        served, access = self.door.access(scope)
        if served and access is None:
            await self._refuse(scope, receive, send, Forbidden("this route declares no access rule: refused"))
            return
        if method not in SAFE_METHODS and bearer(scope) is None:
            why = cross_site(scope)
            if why is not None:  # a page elsewhere posting with the visitor's cookie: sign-in or a session's change
                elsewhere = Forbidden(f"a change from another site is refused: {why}")
                await self._refuse(scope, receive, send, elsewhere)
                return
        if (not served and not is_api(path)) or access is Access.PUBLIC or not self.policy.has_accounts():
            # a page no route serves: the router's 404 (a browser's /favicon.ico gets no sign-in page, whose new
            # CSRF cookie would spoil the form it is showing); open mode: the route's dependency decides
            await self.app(scope, receive, send)
            return
        if access is Access.SCRAPER and self.policy.own_metrics_token():
            await self.app(scope, receive, send)  # its own token, compared by the route's dependency
            return
        client = client_of(scope)
        token = bearer(scope)
        via_cookie = False
        if token is None:
            token = cookie(scope, session_cookie(scope))
            via_cookie = token is not None
        if token is None and access is Access.ANYONE and method in ("GET", "HEAD"):
            await self.app(scope, receive, send)  # an anonymous reader: the route shows public things only
            return
        retry = self.limiter.retry_after(client)
        if retry is not None:
            error: ApiError = TooManyRequests(f"too many refused tokens from this address; retry in {retry} s", retry)
            await self._refuse(scope, receive, send, error)
            return
        if token is None:
            # a page's first visit is not a failure: the sign-in form, without an error
            unsigned = Unauthorized("sign in: send 'Authorization: Bearer <token>'")
            await self._refuse(scope, receive, send, unsigned, quiet=True)
            return
        if via_cookie and is_api(path) and method not in SAFE_METHODS and _header(scope, CSRF_HEADER.encode()) is None:
            error = Forbidden(
                "a change through the API with the web session's cookie needs the session's CSRF token in the "
                "X-CSRF-Token header (or use a token: 'Authorization: Bearer <token>')"
            )
            await self._refuse(scope, receive, send, error)
            return
        try:
            try:
                caller = await check_token(
                    self.accounts, self.limiter, token, client=client, target=path, session=via_cookie
                )
            except TokenRefused as e:
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
        scope[CALLER_KEY] = caller.at(client)
        await self.app(scope, receive, send)

    async def _refuse(
        self,
        scope: Scope,
        receive: Receive,
        send: Send,
        error: ApiError,
        clear_cookie: bool = False,
        quiet: bool = False,
    ) -> None:
        """The API's error, or for a page the sign-in form with the error (``quiet``: without it)."""
        if is_api(scope["path"]) or isinstance(error, Forbidden):
            response: Response = error_response(error.status_code, error.code, error.message, error.headers)
        else:
            response = await self.sign_in_page(scope, error.status_code, None if quiet else error.message)
            response.headers.update(error.headers)
        if clear_cookie:
            response.delete_cookie(
                session_cookie(scope), path="/", httponly=True, samesite="strict", secure=over_https(scope)
            )
        response.headers["connection"] = "close"  # the body, if any, is not read
        await response(scope, receive, send)
