"""The application factory, the ASGI ``app`` for ``uvicorn kitti_eval_server.main:app``, and ``serve()`` for the CLI.

``app`` is built on first access (from the environment), so importing this module does nothing else.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from functools import cache
from typing import Any

import anyio.to_thread
from fastapi import FastAPI
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.formparsers import MultiPartParser
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from kitti_eval import __version__

from .access.auth import CALLER_KEY, AuthMiddleware, Door, access_of, client_of, flat_routes
from .access.headers import SecurityHeaders
from .access.policy import Access, Caller
from .benchmarks.phases import addressed_row
from .data_folder import private_files
from .errors import ApiError, StartupRefused, install_error_handlers
from .idempotency import parse_key
from .middleware import (
    AdmissionMiddleware,
    BeforeBody,
    BeforeBodyCheck,
    BodyMiddleware,
    RefuseBeforeBody,
    part_memory_bytes,
)
from .observability import Metrics, RequestMiddleware, configure_logging, route_uvicorn_logs, wants_json
from .routes import (
    admin,
    benchmarks,
    evaluations,
    frames,
    gates,
    ground_truths,
    health,
    jobs,
    join,
    me,
    metrics,
    phases,
)
from .service import Service
from .settings import Settings, default_data_dir_text, serve_overrides, settings_error
from .shutdown import Drainer
from .web import STATIC_DIR
from .web import router as web_router
from .web.benchmarks import router as benchmark_pages
from .web.join import router as join_pages
from .web.routes import error_page, sign_in_page

__all__ = ["create_app", "serve"]  # and `app`, built on first access

log = logging.getLogger("kitti_eval.server")

_DESCRIPTION = """Exact KITTI 3D object detection evaluation as a service.

Upload an OpenPCDet `result.pkl` (or a zip/tar of KITTI txt results) with `POST /v1/evaluations`, name a
registered ground truth (`demo` is there out of the box), and get back the JSON `kitti-eval --format json`
prints, stored with the inputs' sha256 and your labels. Errors are always `{"error": {"code", "message"}}`.
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the application. Nothing touches the disk or the database until the lifespan starts."""
    settings = settings or Settings()
    log_json = configure_logging(settings.log_format)
    service = Service(settings)
    app_metrics = Metrics(service) if settings.metrics == "on" else None
    if app_metrics is not None:
        service.ground_truths.cache.on_lookup = app_metrics.cache_hit
        service.workers.on_ended = app_metrics.job_ended

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            await anyio.to_thread.run_sync(service.start)
        except StartupRefused as e:  # said once, in the service's log: the server is not given a traceback
            app.state.startup_refused = e.message
            log.error("%s", e.message)
            service.stop()
            raise
        except BaseException:  # anything else: the worker processes it started already are stopped with it
            service.stop()
            raise
        drainer = Drainer(service)
        drainer.install()  # SIGTERM drains the admitted evaluations before the server stops
        try:
            yield
        finally:
            drainer.uninstall()
            service.stop()

    # /docs (Swagger UI) with its script, stylesheet and icon served from the fastapi-offline package (under
    # /static-offline-docs), not from a CDN, so the docs work without internet. No ReDoc: its bundle still
    # fetches a logo from cdn.redoc.ly.
    app = FastAPIOffline(
        title="kitti-eval",
        version=__version__,
        description=_DESCRIPTION,
        lifespan=lifespan,
        debug=False,
        redoc_url=None,
    )
    app.state.service = service
    app.state.policy = service.policy
    app.state.error_page = error_page
    app.state.startup_refused = None  # the reason the service refused to start (StartupRefused), if it did
    app.state.trusted_proxies = settings.trusted_networks  # read by auth.client_of
    app.state.metrics = app_metrics
    app.state.benchmarks = service.benchmarks
    install_error_handlers(app)
    app.include_router(health.router)
    app.include_router(evaluations.router)
    app.include_router(jobs.router)
    app.include_router(ground_truths.router)
    app.include_router(gates.router)
    app.include_router(frames.router)
    app.include_router(metrics.router)
    app.include_router(admin.router)
    app.include_router(me.router)
    app.include_router(join.router)
    app.include_router(phases.router)
    app.include_router(benchmarks.router)
    app.include_router(web_router)
    app.include_router(benchmark_pages)
    app.include_router(join_pages)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    # outermost last: a request is admitted to the evaluations once its body has arrived in full
    app.add_middleware(
        AdmissionMiddleware,
        paths=frozenset({"/v1/evaluations", "/v1/gates/evaluations", "/ui/evaluations"}),
        retry_after_s=lambda: settings.retry_after_s,
        state=service.admission,
        draining=service.draining.is_set,
    )
    # an uploaded file stays in memory while its request is stored when its body was held in memory, else up to
    # PART_MEMORY_BYTES (part_memory_bytes): past Starlette's spooled file's size (MultiPartParser.spool_max_size,
    # 1 MB by default) every val-sized upload would be written to a temporary file and read back once more
    MultiPartParser.spool_max_size = property(lambda _: part_memory_bytes())  # type: ignore[assignment]
    # before the body: a submission the quota or the queue refuses now is answered without its file, when it
    # arrives and again when its turn to send its file comes
    before_body = BeforeBody(
        [
            (method, path, _submission_refused(service, cache(lambda p=path: _declared(app, "POST", p))))
            for method, path in (("POST", SUBMISSIONS), ("POST", PHASE_SUBMISSIONS))
        ],
        caller_key=CALLER_KEY,
        limit=settings.max_upload_bytes,
        timeout_s=settings.body_timeout_s,
    )
    app.add_middleware(
        BodyMiddleware,
        limit=settings.max_upload_bytes,
        timeout_s=settings.body_timeout_s,
        max_receiving=settings.receiving_bodies,
        retry_after_s=lambda: settings.retry_after_s,
        spool_dir=service.data_dir / "tmp",
        memory_bytes=settings.body_memory_bytes,
        memory_wait_s=settings.body_memory_wait_s,
        state=service.admission,
        wait_s=settings.receive_wait_s,
        before_body=before_body,
        per_client=settings.max_receiving_per_client,
        client_of=client_of,
    )
    app.add_middleware(RefuseBeforeBody, before_body=before_body)
    # the door: each route's declared access before its body is read (a request without a valid token sends
    # no body anyone reads); what FastAPI and Starlette add themselves is declared here, where it is added
    door = Door(
        lambda: app.routes,
        {
            # the API's description (routes and fields, no data) is public: the pages' "API" link reaches it
            "/openapi.json": Access.PUBLIC,
            "/docs": Access.PUBLIC,
            "/docs/oauth2-redirect": Access.PUBLIC,
            "/static": Access.PUBLIC,
            "/static-offline-docs": Access.PUBLIC,
        },
    )
    app.state.door = door
    app.add_middleware(
        AuthMiddleware,
        policy=service.policy,
        door=door,
        accounts=service.accounts,
        limiter=service.limiter,
        sign_in_page=sign_in_page,
        retry_after_s=lambda: settings.retry_after_s,
    )
    app.add_middleware(_PlainStartupRefusal)
    # every request gets its id, its log line and its metrics, whoever answers it
    app.add_middleware(RequestMiddleware, metrics=app_metrics, log_json=lambda: log_json, route_template=door.template)
    app.add_middleware(SecurityHeaders)  # on every response, a refusal's and a failure's too
    return app


#: the route whose refusals (a used quota, a full queue) are answered before its file, and a phase's (its quota,
#: the team's in a team): the routes' own paths
SUBMISSIONS = benchmarks.router.prefix + benchmarks.SUBMISSIONS
PHASE_SUBMISSIONS = phases.router.prefix + phases.PHASE_SUBMISSIONS


def _declared(app: FastAPI, method: str, path: str) -> Access:
    """The access the route serving ``method path`` declared (its access dependency)."""
    for route in flat_routes(app.routes):
        if isinstance(route, APIRoute) and route.path == path and method in (route.methods or ()):
            (access,) = access_of(route.dependant)
            return access
    raise RuntimeError(f"no route serves {method} {path}")


def _submission_refused(service: Service, access: Callable[[], Access]) -> BeforeBodyCheck:
    """A submission's refusal before its file: as the route's declared ``access`` would admit the caller, then
    :meth:`Submissions.refused_now <kitti_eval_server.benchmarks.submissions.Submissions.refused_now>`."""

    def check(caller: Caller, params: dict[str, str], size: int, idempotency_key: str | None) -> ApiError | None:
        try:
            admitted = service.policy.admit(access(), caller, method="POST", bearer=None, csrf=None)
            checked_key = parse_key(idempotency_key)
        except ApiError:
            return None  # the route refuses it, as always
        # the phase's row, for a caller who sees the benchmark (the route answers the others); else the current one
        row = addressed_row(service.benchmarks.catalog, params["name"], params.get("phase"), admitted)
        return service.benchmarks.submissions.refused_now(row, admitted, size, checked_key) if row else None

    return check


class _PlainStartupRefusal:
    """A failed startup's message is the traceback (Starlette's), which uvicorn prints; when the service refused
    to start (:class:`StartupRefused`, already in its log) the message is dropped, so no traceback is shown."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "lifespan":
            await self.app(scope, receive, send)
            return

        async def plain(message: Message) -> None:
            if message["type"] == "lifespan.startup.failed" and scope["app"].state.startup_refused:
                message = {"type": "lifespan.startup.failed", "message": ""}
            await send(message)

        await self.app(scope, receive, plain)


_app: FastAPI | None = None


def __getattr__(name: str) -> Any:
    """``kitti_eval_server.main.app``: the application configured from the environment, built once on first use."""
    global _app
    if name == "app":
        if _app is None:
            _app = create_app()
        return _app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def serve(argv: Sequence[str] | None = None) -> int:
    """``kitti-eval serve``: run the service with uvicorn. Options override ``KITTI_EVAL_*`` variables."""
    import uvicorn

    parser = argparse.ArgumentParser(prog="kitti-eval serve", description="Run the kitti-eval HTTP service.")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    parser.add_argument(
        "--data-dir",
        help="KITTI_EVAL_DATA_DIR: database, ground truths, admin token, scratch space "
        f"(default {default_data_dir_text()})",
    )
    parser.add_argument("--database-url", help="KITTI_EVAL_DATABASE_URL, e.g. postgresql://user:pw@host/db")
    parser.add_argument(
        "--auth",
        choices=["open", "accounts"],
        help="KITTI_EVAL_AUTH: open (default: no accounts, everyone sees everything) or accounts (every request "
        "needs a token; users, projects and tokens come from kitti-eval admin)",
    )
    parser.add_argument(
        "--upgrade",
        action="store_true",
        help="KITTI_EVAL_DB_UPGRADE: upgrade an older database's schema at start (under a lock) instead of refusing",
    )
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    try:
        args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    except SystemExit as e:
        return int(e.code) if isinstance(e.code, int) else 2
    overrides = serve_overrides(args.data_dir, args.database_url, args.auth, args.upgrade, os.environ)
    try:
        settings = Settings(**overrides)
    except ValueError as e:  # pydantic's ValidationError, or no data folder (NoDataFolder)
        print(f"kitti-eval serve: {settings_error(e)}", file=sys.stderr)  # noqa: T201
        return 2
    app = create_app(settings)
    log.setLevel(args.log_level.upper())
    route_uvicorn_logs(wants_json(settings.log_format))  # uvicorn's own lines in the service's format
    # the service writes its own access log (one line a request, with its id): uvicorn's would repeat it. Which
    # proxy's X-Forwarded-For is believed is KITTI_EVAL_TRUSTED_PROXIES' alone: uvicorn's own proxy headers
    # (on by default, trusting 127.0.0.1 or FORWARDED_ALLOW_IPS) would rewrite the client's address before it
    try:
        with private_files():  # the database and the unpacked ground truths are not readable by other users
            uvicorn.run(
                app,
                host=args.host,
                port=args.port,
                log_level=args.log_level,
                access_log=False,
                log_config=None,  # its loggers keep the service's handler (route_uvicorn_logs)
                proxy_headers=False,
                timeout_graceful_shutdown=10,
            )
    except SystemExit:  # uvicorn's exit when the startup failed
        if app.state.startup_refused:  # the settings do not fit the database: the log line says which to change
            return 2
        raise
    return 0


if __name__ == "__main__":
    sys.exit(serve())
