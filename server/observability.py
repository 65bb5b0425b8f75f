"""What an operator sees: Prometheus metrics (``GET /metrics``) and one log line per request.

:class:`RequestMiddleware` (the outermost layer) gives every request an id (the client's ``X-Request-ID`` when
it is a sane one, else a new one), returns it in the ``X-Request-ID`` response header and in every JSON error
body (``error.request_id``), times the request, counts the bytes it brought, and when the response is done
writes one access-log line and updates the metrics. The log line names the method, the route (its template,
e.g. ``/v1/evaluations/{evaluation_id}``), the status, the duration, the bytes and the evaluation's id where
there is one; never a header value (so never a token), a query string or any file content.

Metrics (prometheus-client): requests by route, method and status; request latency; bytes received;
evaluations by outcome (``ok``; ``refused``: the client's input or a full service, 4xx and 503; ``failed``:
any other 5xx) and their duration; admission (evaluations in progress, bodies being received, 503s given);
ground-truth cache hits, misses, entries and bytes; whether the kernels are warm. With several worker
processes (``PROMETHEUS_MULTIPROC_DIR`` set, as prometheus-client's multiprocess mode requires) the counters
and histograms are summed over the processes; the gauges of the process state (cache, admission, warm) are
those of the process that answers the scrape, labelled with its ``pid``.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import re
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from kitti_eval.core.kernel_cache import route_warnings

from .errors import INTERNAL_ERROR_MESSAGE, error_body

__all__ = [
    "Metrics",
    "RequestMiddleware",
    "REQUEST_ID_HEADER",
    "configure_logging",
    "route_uvicorn_logs",
    "CONTENT_TYPE",
    "JsonFormatter",
    "TextFormatter",
    "escape_text",
]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
REQUEST_ID_HEADER = "x-request-id"
#: a client's request id is taken when it is this (anything else is replaced: it is written to the log)
_SANE_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")
#: the paths whose POST runs an evaluation
EVALUATION_PATHS = frozenset({"/v1/evaluations", "/ui/evaluations"})
#: the routes probes and scrapers ask every few seconds: their access lines are written at DEBUG, not INFO
#: (a readiness probe every 5 s is 17,000 lines a day), and counted in the metrics as every request is
PROBE_ROUTES = frozenset({"/healthz", "/readyz", "/metrics"})
#: uvicorn's loggers, whose lines (the start, the stop, a failed startup) go through the service's formatter
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")
_ATTEMPT_BUCKETS = (1, 2, 3, 5, 10)
_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)

access_log = logging.getLogger("kitti_eval.server.access")
errors_log = logging.getLogger("kitti_eval.server")


class _Cache(Protocol):
    @property
    def nbytes(self) -> int: ...

    def __len__(self) -> int: ...


class _GroundTruths(Protocol):
    @property
    def cache(self) -> _Cache: ...


class _Warm(Protocol):
    def is_set(self) -> bool: ...


class _Jobs(Protocol):
    def counts(self) -> dict[str, int]: ...

    def oldest_queued_age_s(self) -> float | None: ...

    def workers_seen(self, within_s: float) -> Sequence[_SeenWorker]: ...


class _SeenWorker(Protocol):
    @property
    def threads(self) -> int: ...


class _Alive(Protocol):
    @property
    def alive(self) -> int: ...


class ServiceState(Protocol):
    """What the metrics read of the service (:class:`kitti_eval_server.service.Service` has it)."""

    @property
    def jobs(self) -> _Jobs: ...

    @property
    def workers(self) -> _Alive: ...

    @property
    def pool(self) -> _Alive | None: ...

    @property
    def admission(self) -> AdmissionState: ...

    @property
    def ground_truths(self) -> _GroundTruths: ...

    @property
    def warm(self) -> _Warm: ...


class Metrics:
    """The service's metrics, on a registry of its own (one per application, so that tests can build many)."""

    def __init__(self, service: ServiceState | None = None) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.multiprocess_dir = os.environ.get("PROMETHEUS_MULTIPROC_DIR") or os.environ.get("prometheus_multiproc_dir")
        r = self.registry
        self.requests = Counter(
            "kitti_eval_http_requests", "HTTP requests answered", ["route", "method", "status"], registry=r
        )
        self.latency = Histogram(
            "kitti_eval_http_request_duration_seconds",
            "Time from a request's arrival to the end of its response",
            ["route", "method"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.received = Counter("kitti_eval_http_received_bytes", "Request body bytes received", registry=r)
        self.evaluations = Counter("kitti_eval_evaluations", "Evaluation requests by outcome", ["outcome"], registry=r)
        self.errors = Counter(
            "kitti_eval_http_errors", "Error responses by their code (database_unavailable, ...)", ["code"], registry=r
        )
        self.evaluation_seconds = Histogram(
            "kitti_eval_evaluation_duration_seconds",
            "Time an evaluation request took, by outcome",
            ["outcome"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.rejected = Counter(
            "kitti_eval_admission_rejected", "Requests answered 503 as the service was full", ["reason"], registry=r
        )
        self.cache_lookups = Counter(
            "kitti_eval_ground_truth_cache_lookups", "Ground-truth cache lookups", ["result"], registry=r
        )
        self.job_seconds = Histogram(
            "kitti_eval_job_duration_seconds",
            "Time a run of a job took on a worker of this process, by kind and outcome (done, refused, retried, "
            "failed, lost, released, timed_out)",
            ["kind", "outcome"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.job_attempts = Histogram(
            "kitti_eval_job_attempts",
            "Which attempt a run of a job was (1: its first), by kind and outcome",
            ["kind", "outcome"],
            buckets=_ATTEMPT_BUCKETS,
            registry=r,
        )
        self.state = None if service is None else _StateCollector(service, with_pid=self.multiprocess_dir is not None)
        if self.state is not None:
            r.register(self.state)

    def render(self) -> bytes:
        """The text exposition: this process's registry, or every process's in multiprocess mode."""
        if self.multiprocess_dir is None:
            return generate_latest(self.registry)
        merged = CollectorRegistry()
        MultiProcessCollector(merged, path=self.multiprocess_dir)
        if self.state is not None:
            merged.register(self.state)
        return generate_latest(merged)

    def cache_hit(self, hit: bool) -> None:
        self.cache_lookups.labels("hit" if hit else "miss").inc()

    def job_ended(self, kind: str, outcome: str, seconds: float, attempt: int) -> None:
        """A worker's run of a job ended (:attr:`kitti_eval_server.jobs.workers.Workers.on_ended`)."""
        self.job_seconds.labels(kind, outcome).observe(seconds)
        self.job_attempts.labels(kind, outcome).observe(attempt)


class _StateCollector(Collector):
    """Gauges read from the service when scraped: admission, the ground-truth cache, the kernels, the queue of
    jobs and the workers (the last two read from the database: left out of a scrape that cannot read it)."""

    #: a worker process seen on the database within this long counts among ``job_workers_seen``
    SEEN_S = 60.0

    def __init__(self, service: ServiceState, *, with_pid: bool) -> None:
        self.service = service
        self.labels = {"pid": str(os.getpid())} if with_pid else {}

    def _gauge(self, name: str, doc: str, value: float) -> GaugeMetricFamily:
        g = GaugeMetricFamily(name, doc, labels=list(self.labels))
        g.add_metric(list(self.labels.values()), value)
        return g

    def collect(self) -> Iterable[GaugeMetricFamily]:
        s = self.service
        cache = s.ground_truths.cache
        gauges = (
            ("evaluations_in_progress", "Evaluation requests admitted (running or waiting)", s.admission.in_flight),
            ("evaluations_running", "Evaluations running on worker threads", s.admission.running),
            ("requests_waiting", "Requests waiting for their job to end (wait)", s.admission.waiting),
            ("bodies_receiving", "Request bodies being received", s.admission.receiving),
            ("bodies_waiting", "Requests waiting for their turn to send their body", s.admission.body_waiting),
            ("ground_truth_cache_entries", "Ground-truth sets held in memory", len(cache)),
            ("ground_truth_cache_bytes", "Bytes of the ground-truth sets held in memory", cache.nbytes),
            ("kernels_warm", "1 once every kernel is compiled or loaded", float(s.warm.is_set())),
        )
        for name, doc, value in gauges:
            yield self._gauge(f"kitti_eval_{name}", doc, value)
        yield from self._jobs()

    def _jobs(self) -> Iterable[GaugeMetricFamily]:
        s = self.service
        yield self._gauge("kitti_eval_job_workers_alive", "Worker threads alive in this process", s.workers.alive)
        pool = s.pool
        yield self._gauge(
            "kitti_eval_job_worker_processes_alive",
            "Worker processes of this service's own (KITTI_EVAL_WORKER_PROCESSES) running",
            pool.alive if pool is not None else 0,
        )
        try:
            counts = s.jobs.counts()
            oldest = s.jobs.oldest_queued_age_s()
            seen = s.jobs.workers_seen(self.SEEN_S)
        except Exception:  # noqa: BLE001 - the database is away: the rest of the scrape still answers
            errors_log.debug("could not read the jobs for the metrics", exc_info=True)
            return
        by_state = GaugeMetricFamily("kitti_eval_jobs", "Jobs in the database by state", labels=[*self.labels, "state"])
        for state, n in counts.items():
            by_state.add_metric([*self.labels.values(), state], n)
        yield by_state
        yield self._gauge(
            "kitti_eval_jobs_oldest_queued_age_seconds",
            "Seconds since the oldest queued job was accepted (0: none is queued)",
            oldest or 0.0,
        )
        yield self._gauge(
            "kitti_eval_job_workers_seen",
            "Worker threads of the processes seen on the database within the last minute (this one's included)",
            sum(w.threads for w in seen),
        )


@dataclass
class AdmissionState:
    """What the middlewares and the worker threads count, for the metrics (the event loop writes most of it)."""

    in_flight: int = 0
    running: int = 0
    receiving: int = 0
    #: requests waiting for their turn to send their body (past ``max_receiving_bodies``)
    body_waiting: int = 0
    #: requests waiting for their job's outcome
    waiting: int = 0


# ------------------------------------------------------------------------------------------- requests


def _client_request_id(scope: Scope) -> str | None:
    for key, value in scope.get("headers", ()):
        if key == b"x-request-id":
            text = bytes(value).decode("latin-1")
            return text if _SANE_ID.fullmatch(text) else None
    return None


#: the methods a metric names; any other token a client sends is ``other`` (it would be a series of its own)
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS"})


def _method_label(method: str) -> str:
    return method if method in _METHODS else "other"


def _route_of(scope: Scope, template: Callable[[Scope], str | None] | None = None) -> str:
    """The matched route's template (``/v1/evaluations/{evaluation_id}``), a mount's prefix, or ``unmatched``:
    never the path as sent, so that clients cannot make new series. A request answered before the router ran (a
    408, 413 or 503 ``busy`` about its body) is matched by ``template`` (the door's table of the app's routes),
    so that it counts under its route: ``unmatched`` is a path no route serves."""
    route = scope.get("route")
    path = getattr(route, "path_format", None) or getattr(route, "path", None)
    if isinstance(path, str):
        return path
    if str(scope.get("path", "")).startswith("/static/"):
        return "/static"
    found = template(scope) if template is not None else None
    return found or "unmatched"


class RequestMiddleware:
    """Request ids, the access log and the request metrics (see the module's docstring)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        metrics: Metrics | None,
        log_json: Callable[[], bool],
        route_template: Callable[[Scope], str | None] | None = None,
    ) -> None:
        self.app = app
        self.metrics = metrics
        self.log_json = log_json
        #: the template of the route serving a request the router did not see (answered before it)
        self.route_template = route_template

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        rid = _client_request_id(scope) or uuid.uuid4().hex
        state = scope.setdefault("state", {})
        state["request_id"] = rid
        seen = {"status": 0, "received": 0, "sent": 0}
        error_parts: list[bytes] | None = None
        error_start: Message | None = None

        async def counting_receive() -> Message:
            message = await receive()
            if message["type"] == "http.request":
                seen["received"] += len(message.get("body", b""))
            return message

        async def tagging_send(message: Message) -> None:
            nonlocal error_parts, error_start
            if message["type"] == "http.response.start":
                seen["status"] = int(message["status"])
                headers = [(k, v) for k, v in message.get("headers", ()) if k.lower() != b"x-request-id"]
                headers.append((b"x-request-id", rid.encode()))
                seen_evaluation = _evaluation_of(headers)
                if seen_evaluation:
                    state["evaluation_id"] = seen_evaluation
                message = {**message, "headers": headers}
                if seen["status"] >= 400 and _is_json(headers):
                    error_start, error_parts = message, []  # held until the body is complete
                    return
            elif message["type"] == "http.response.body":
                seen["sent"] += len(message.get("body", b""))
                if error_parts is not None and error_start is not None:
                    error_parts.append(message.get("body", b""))
                    if message.get("more_body", False):
                        return
                    body, code = _with_request_id(b"".join(error_parts), rid)
                    if code is not None:
                        state["error_code"] = code[:64]
                    headers = [(k, v) for k, v in error_start["headers"] if k.lower() != b"content-length"]
                    headers.append((b"content-length", str(len(body)).encode()))
                    await send({**error_start, "headers": headers})
                    error_parts = error_start = None
                    await send({"type": "http.response.body", "body": body})
                    return
            await send(message)

        try:
            await self.app(scope, counting_receive, tagging_send)
        except Exception:
            # an unexpected failure: answered here, inside this layer, so the 500 carries the request id and is
            # counted and logged like any other answer (the server's own last-resort handler sits outside)
            if seen["status"]:  # the response had begun: nothing more can be said on this connection
                raise
            errors_log.error("unhandled error on %s %s", scope.get("method"), scope.get("path"), exc_info=True)
            raw = json.dumps(error_body("internal_error", INTERNAL_ERROR_MESSAGE)).encode()
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(raw)).encode())]
            await tagging_send({"type": "http.response.start", "status": 500, "headers": headers})
            await tagging_send({"type": "http.response.body", "body": raw})
        finally:
            self._done(scope, rid, seen, time.perf_counter() - started)

    def _done(self, scope: Scope, rid: str, seen: dict[str, int], seconds: float) -> None:
        route, method, status = _route_of(scope, self.route_template), str(scope.get("method", "")), seen["status"]
        evaluation = scope.get("state", {}).get("evaluation_id")
        if self.metrics is not None:
            m = self.metrics
            m.requests.labels(route, _method_label(method), str(status)).inc()
            m.latency.labels(route, _method_label(method)).observe(seconds)
            m.received.inc(seen["received"])
            code = scope.get("state", {}).get("error_code")
            if code is not None:
                m.errors.labels(str(code)).inc()
            if method == "POST" and str(scope.get("path", "")).rstrip("/") in EVALUATION_PATHS and status:
                outcome = "ok" if status < 400 else "refused" if status < 500 or status == 503 else "failed"
                m.evaluations.labels(outcome).inc()
                m.evaluation_seconds.labels(outcome).observe(seconds)
            if status == 503 and code == "busy":  # every turn to send a body taken, whichever the route
                m.rejected.labels("bodies").inc()
            elif status == 503 and method == "POST" and str(scope.get("path", "")).rstrip("/") in EVALUATION_PATHS:
                m.rejected.labels("evaluations").inc()
        record = {
            "request_id": rid,
            "method": method,
            "route": route,
            "status": status,
            "duration_ms": round(seconds * 1000, 3),
            "bytes_in": seen["received"],
            "bytes_out": seen["sent"],
        }
        if evaluation:
            record["evaluation_id"] = str(evaluation)
        level = logging.DEBUG if route in PROBE_ROUTES else logging.INFO
        if not access_log.isEnabledFor(level):
            return
        if self.log_json():
            access_log.log(level, json.dumps(record), extra={"access": record})
        else:  # the values as arguments, so that the text format escapes them (TextFormatter)
            access_log.log(
                level,
                "%s %s %s %.0f ms in=%s B out=%s B id=%s%s",
                method,
                route,
                status,
                record["duration_ms"],
                seen["received"],
                seen["sent"],
                rid,
                f" evaluation={evaluation}" if evaluation else "",
                extra={"access": record},
            )


_EVALUATION_LOCATION = re.compile(rb"/(?:v1|ui)/evaluations/([A-Za-z0-9_-]{1,64})")


def _evaluation_of(headers: list[tuple[bytes, bytes]]) -> str | None:
    """The evaluation a response made or names: its ``X-Evaluation-Id``, or the one its Location points to."""
    for k, v in headers:
        if k.lower() == b"x-evaluation-id":
            return v.decode("latin-1")[:64]
    for k, v in headers:
        if k.lower() == b"location":
            found = _EVALUATION_LOCATION.search(v)
            if found:
                return found.group(1).decode()
    return None


def _is_json(headers: list[tuple[bytes, bytes]]) -> bool:
    return any(k.lower() == b"content-type" and v.startswith(b"application/json") for k, v in headers)


def _with_request_id(body: bytes, rid: str) -> tuple[bytes, str | None]:
    """An error body with ``error.request_id`` added (any other body as it was), and the error's code."""
    try:
        doc = json.loads(body)
    except ValueError:
        return body, None
    if isinstance(doc, dict) and isinstance(doc.get("error"), dict):
        doc["error"]["request_id"] = rid
        code = doc["error"].get("code")
        return json.dumps(doc).encode(), code if isinstance(code, str) else None
    return body, None


# -------------------------------------------------------------------------------------------- logging


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time, level, logger, message, and the access record's fields when it is one."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
        }
        access = getattr(record, "access", None)
        if isinstance(access, dict):
            doc.update(access)
        else:
            doc["message"] = record.getMessage()
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc)


#: what would break a text line or fake an escape: control characters (C0, DEL, C1), the Unicode line and
#: paragraph separators, and the backslash
_UNSAFE = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\\]")
_UNSAFE_IN_TEMPLATE = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def _escaped(match: re.Match[str]) -> str:
    return match.group().encode("unicode_escape").decode("ascii")  # \n, \r, \x85, \u2028, \\


def escape_text(value: str) -> str:
    """``value`` with control characters and backslashes written as Python escapes: one line, unambiguous."""
    return _UNSAFE.sub(_escaped, value)


class TextFormatter(logging.Formatter):
    """The text format, one line a record: every string value of a message (its ``%s`` arguments, where request
    paths, methods and client addresses go) is escaped (:func:`escape_text`), so a ``%0A`` in a URL cannot
    start a line of its own; a control character in the message itself is escaped too. A traceback, when there
    is one, follows on lines of its own as usual."""

    def format(self, record: logging.LogRecord) -> str:
        safe = copy.copy(record)
        if isinstance(record.args, Mapping):
            safe.args = {k: escape_text(v) if isinstance(v, str) else v for k, v in record.args.items()}
        elif record.args:
            safe.args = tuple(escape_text(v) if isinstance(v, str) else v for v in record.args)
        safe.msg, safe.args = _UNSAFE_IN_TEMPLATE.sub(_escaped, safe.getMessage()), None
        return super().format(safe)


def wants_json(log_format: str, stream: Any = None) -> bool:
    """``json``, ``text``, or ``auto``: JSON unless the log goes to a terminal."""
    if log_format == "auto":
        stream = sys.stderr if stream is None else stream
        return not (hasattr(stream, "isatty") and stream.isatty())
    return log_format == "json"


def configure_logging(log_format: str) -> bool:
    """The service's loggers (``kitti_eval.server`` and its access log) to stderr, as JSON lines or as text,
    unless the embedding application configured logging itself. Returns whether the lines are JSON."""
    as_json = wants_json(log_format)
    logger = logging.getLogger("kitti_eval.server")
    # kernels compiled in memory for want of a writable numba cache: said once, in the service's log
    route_warnings(lambda message: logger.warning("%s", message))
    if logging.getLogger().handlers or any(not getattr(h, "_kitti_eval", False) for h in logger.handlers):
        return as_json
    for h in list(logger.handlers):
        logger.removeHandler(h)
    handler = logging.StreamHandler()
    handler._kitti_eval = True  # type: ignore[attr-defined]
    handler.setFormatter(JsonFormatter() if as_json else TextFormatter("%(levelname)s:     kitti-eval: %(message)s"))
    logger.addHandler(handler)
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.INFO)
    logger.propagate = False
    return as_json


def route_uvicorn_logs(as_json: bool) -> None:
    """uvicorn's own lines (``Started server process``, ``Application startup complete``, a failed startup, the
    shutdown) through the service's formatter, so that a JSON log holds nothing but JSON lines. For
    ``kitti-eval serve``, which runs uvicorn with ``log_config=None`` (uvicorn then leaves these loggers alone
    but for their level)."""
    handler = logging.StreamHandler()
    handler._kitti_eval = True  # type: ignore[attr-defined]
    handler.setFormatter(JsonFormatter() if as_json else TextFormatter("%(levelname)s:     %(message)s"))
    for name in UVICORN_LOGGERS:
        logger = logging.getLogger(name)
        for old in [h for h in logger.handlers if getattr(h, "_kitti_eval", False)]:
            logger.removeHandler(old)
        logger.addHandler(handler)
        logger.propagate = False
