"""A client of the service (``kitti-eval serve``): evaluate, submit to a benchmark, follow jobs, read boards.

What the service answers comes back as the library's own types: an evaluation's document is the JSON document
``kitti-eval --format json`` prints (:class:`~kitti_eval.core.result.EvalResult` by
:meth:`Evaluation.result`), a submission, a job and a quota are small dataclasses, and a refusal is an error of
the one tree (:class:`~kitti_eval.errors.ServiceError` and its kinds).

Every request is sent again when the service is away: no connection, a connection dropped, 502/503/504 (after
its ``Retry-After`` when it sends one), 408, 429 ``too_many_queued``; with exponential backoff and full jitter,
for at most :attr:`Retries.within_s` seconds, then :class:`~kitti_eval.errors.ServiceUnreachable`. The two
requests that record something (an evaluation, a submission) carry an ``Idempotency-Key`` drawn once per call
and sent again with every retry, so a retry never makes a second evaluation nor counts a submission twice.

Needs httpx (``pip install 'kitti-eval[client]'``); the rest of the library imports without it.

The token is the ``token`` argument, else ``$KITTI_EVAL_TOKEN``, else the one ``kitti-eval login`` saved for
that service (:func:`saved_token`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import random
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, TypeVar

from .client_state import new_key
from .errors import (
    ConfigError,
    QuotaExceeded,
    ServiceError,
    ServiceUnreachable,
    SubmissionRefused,
)

if TYPE_CHECKING:
    import httpx

    from .core.result import EvalResult

__all__ = [
    "Client",
    "Retries",
    "Evaluation",
    "Submission",
    "Job",
    "Quota",
    "TOKEN_ENV",
    "CONFIG_ENV",
    "ALLOW_HTTP_ENV",
    "saved_token",
    "saved_services",
    "save_token",
    "token_for",
    "new_key",
]

#: the environment variable holding the token
TOKEN_ENV = "KITTI_EVAL_TOKEN"
#: the folder of the client's configuration instead of the user's config folder
CONFIG_ENV = "KITTI_EVAL_CONFIG_DIR"
#: ``1``: a token may be sent over plain http to a host other than loopback
ALLOW_HTTP_ENV = "KITTI_EVAL_ALLOW_HTTP"
_TOKENS_FILE = "services.json"
#: statuses answered while a service is away or too busy for now: sent again
_AWAY = frozenset({408, 502, 503, 504})
#: how long one POST asks the service to wait for its result before answering 202 with the job
_POST_WAIT_S = 20.0
_USER_AGENT = "kitti-eval-client"
_T = TypeVar("_T")


# ------------------------------------------------------------------------------------------ results

_ID = re.compile(r"^[A-Za-z0-9_-]{1,128}$")


def _id(value: object) -> str:
    """An id the service gave, as it may go into a path and a sentence (else the answer is not the service's)."""
    text = str(value)
    if not _ID.match(text):
        raise ValueError(f"not an id: {_shown(text)[:80]!r}")
    return text


@dataclass(frozen=True)
class Evaluation:
    """One stored evaluation: its id, the labels and inputs the service recorded (``meta``), and ``document``,
    the JSON document ``kitti-eval --format json`` prints for the same files."""

    id: str
    document: dict[str, Any]
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Evaluation:
        doc = {k: v for k, v in body.items() if k not in ("id", "evaluation")}
        return cls(id=_id(body["id"]), document=doc, meta=dict(body.get("evaluation") or {}))

    def result(self) -> EvalResult:
        """The document as the library's result (without curves)."""
        from .core.result import EvalResult

        return EvalResult.from_dict(self.document)

    def render(self, fmt: str = "json") -> str:
        """What ``kitti-eval --format FMT`` prints for the same files: the document as it came for ``json``
        (with its curves and error decomposition when they were asked for), else rendered from :meth:`result`."""
        from .report.render import OutputFormat, render

        if OutputFormat(fmt) is OutputFormat.JSON:
            return json.dumps(self.document, indent=2, allow_nan=False) + "\n"
        return render(self.result(), fmt)


@dataclass(frozen=True)
class Job:
    """An accepted evaluation's or submission's job, as ``GET /v1/jobs/{id}`` says it is."""

    id: str
    kind: str
    state: str
    position: int | None = None
    attempts: int = 0
    result_location: str | None = None
    error: dict[str, Any] | None = None

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Job:
        return cls(
            id=_id(body["id"]),
            kind=_shown(body.get("kind", "")),
            state=_shown(body["state"]),
            position=body.get("position"),
            attempts=int(body.get("attempts") or 0),
            result_location=body.get("result_location"),
            error=body.get("error"),
        )

    @property
    def ended(self) -> bool:
        return self.state in ("done", "failed", "cancelled")


@dataclass(frozen=True)
class Submission:
    """One of your submissions as the service shows it to you: ``status`` (``queued``, ``scored``, ``failed``),
    ``scores`` (the board's columns, on the part of the test set the board shows: ``scored_on``), and ``view``,
    everything the service answered. ``reused``: :meth:`Client.submit` sent the key an earlier call saved for
    the same file (the answer is the submission that call made, counted once)."""

    id: str
    benchmark: str
    status: str
    scores: dict[str, float | None] | None
    scored_on: str | None
    view: dict[str, Any]
    reused: bool = False

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Submission:
        return cls(
            id=_id(body["id"]),
            benchmark=_shown(body.get("benchmark", "")),
            status=_shown(body.get("status", "")),
            scores=body.get("scores"),
            scored_on=body.get("scored_on"),
            view=dict(body),
        )

    def result(self) -> EvalResult | None:
        """The scored document on the part shown, as the library's result (None before it is scored)."""
        from .core.result import EvalResult

        doc = self.view.get("result")
        return EvalResult.from_dict(doc) if doc else None


@dataclass(frozen=True)
class Quota:
    """A benchmark's quota as it stands for you: ``submissions`` in any ``days``, ``used`` and ``left``, and
    ``next_at`` (ISO 8601) when none is left: when the next submission is accepted."""

    submissions: int
    days: float
    used: int
    left: int
    next_at: str | None = None


# ------------------------------------------------------------------------------------------ retries


@dataclass(frozen=True)
class Retries:
    """How requests are sent again while a service is away: after ``first_s``, doubling up to ``max_s``, each
    wait drawn uniformly below that (full jitter), or the service's ``Retry-After`` plus up to a tenth of it;
    for at most ``within_s`` seconds from a request's first try."""

    within_s: float = 300.0
    first_s: float = 0.5
    max_s: float = 15.0
    rng: random.Random = field(default_factory=random.Random, compare=False, repr=False)

    def delay(self, attempt: int, retry_after: float | None) -> float:
        if retry_after is not None:
            return retry_after + self.rng.uniform(0.0, retry_after / 10)
        return self.rng.uniform(0.1 * self.first_s, min(self.max_s, self.first_s * 2**attempt))


def _retry_after(response: httpx.Response) -> float | None:
    value = response.headers.get("Retry-After", "").strip()
    try:
        seconds = float(value)
    except ValueError:
        return None
    return seconds if math.isfinite(seconds) and seconds >= 0 else None


def _error_of(response: httpx.Response) -> dict[str, Any]:
    try:
        body = response.json()
    except ValueError:
        return {}
    error = body.get("error") if isinstance(body, dict) else None
    return error if isinstance(error, dict) else {}


#: what a service's text may not hold when it is shown: control characters (a terminal's escape sequences)
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")
_MAX_SHOWN = 2000


def _shown(text: object) -> str:
    """A service's text as it may be printed: control characters replaced, its length bounded."""
    out = _CONTROL.sub("?", str(text))
    return out if len(out) <= _MAX_SHOWN else out[:_MAX_SHOWN] + "..."


def _refusal(response: httpx.Response) -> ServiceError:
    """The error of the one tree a refusal is."""
    error = _error_of(response)
    code = _shown(error.get("code") or "")
    message = _shown(error.get("message") or response.reason_phrase or f"HTTP {response.status_code}")
    details = {k: v for k, v in error.items() if k not in ("code", "message")}
    kw: dict[str, Any] = {"status": response.status_code, "code": code or None, "details": details}
    if code == "quota_exceeded":
        return QuotaExceeded(message, **kw)
    if code == "invalid_submission":
        problems = details.get("problems")
        return SubmissionRefused(message, [_shown(p) for p in problems] if isinstance(problems, list) else [], **kw)
    return ServiceError(message, **kw)


# ------------------------------------------------------------------------------------------ the token


def config_dir() -> Path:
    """The client's folder: ``$KITTI_EVAL_CONFIG_DIR``, else the user's config folder's ``kitti-eval``
    (``$XDG_CONFIG_HOME/kitti-eval``, else ``~/.config/kitti-eval``); a :class:`~kitti_eval.errors.ConfigError`
    naming the settings where there is neither (no ``HOME``, as under ``env -i``, and no home for the uid)."""
    env = os.environ.get(CONFIG_ENV, "").strip()
    if env:
        return Path(env)
    try:
        from platformdirs import user_config_dir
    except ImportError:
        raise ConfigError("the client needs platformdirs: pip install 'kitti-eval[client]'") from None
    try:
        found = Path(user_config_dir("kitti-eval", appauthor=False))
    except RuntimeError:  # platformdirs, where ~ cannot be expanded
        found = None
    if found is None or not found.is_absolute():
        raise ConfigError(
            f"the client has no folder for its saved tokens: HOME is not set and the user has no home folder; "
            f"set {CONFIG_ENV} to a folder it may write (or XDG_CONFIG_HOME, or HOME)"
        )
    return found


def _service_key(service: str) -> str:
    return service.strip().rstrip("/")


def _saved() -> dict[str, str]:
    path = config_dir() / _TOKENS_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: not the tokens kitti-eval login writes: {e}") from None
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise ConfigError(f"{path}: not the tokens kitti-eval login writes")
    return data


def saved_token(service: str) -> str | None:
    """The token ``kitti-eval login`` saved for ``service``, if any."""
    return _saved().get(_service_key(service))


def save_token(service: str, token: str) -> Path:
    """Saves ``token`` for ``service`` in the client's folder (readable by its owner only, written through a
    temporary file of its own: :mod:`kitti_eval.client_state`); returns the file."""
    from .client_state import write_private_json

    tokens = {**_saved(), _service_key(service): token}
    return write_private_json(config_dir() / _TOKENS_FILE, tokens)


def saved_services() -> list[str]:
    """The services ``kitti-eval login`` saved a token for."""
    return sorted(_saved())


def token_for(service: str, token: str | None = None) -> str | None:
    """The token to send: ``token``, else ``$KITTI_EVAL_TOKEN``, else the one saved for ``service``."""
    return token or os.environ.get(TOKEN_ENV, "").strip() or saved_token(service)


def _loopback(host: str) -> bool:
    import ipaddress

    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _refuse_plain_http(service: str, allow_http: bool | None) -> None:
    """The token goes over plain http to a loopback host only, unless the caller says the network is trusted."""
    from urllib.parse import urlsplit

    if allow_http is None:
        allow_http = os.environ.get(ALLOW_HTTP_ENV, "").strip() == "1"
    parts = urlsplit(service)
    if parts.scheme != "http" or allow_http or _loopback(parts.hostname or ""):
        return
    raise ConfigError(
        f"--service {service}: the token would be sent unencrypted (plain http to a host other than this "
        f"machine); use https://, or say the network is trusted with --allow-http (or {ALLOW_HTTP_ENV}=1)"
    )


# ------------------------------------------------------------------------------------------ the client


class _Counted:
    """A file handed to httpx's multipart encoder that reports the bytes read (the upload's progress)."""

    def __init__(self, raw: BinaryIO, on_read: Callable[[int], None]) -> None:
        self.raw = raw
        self.on_read = on_read

    def read(self, n: int = -1) -> bytes:
        chunk = self.raw.read(n)
        self.on_read(len(chunk))
        return chunk

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        return self.raw.tell()

    def fileno(self) -> int:
        return self.raw.fileno()


def _answered(method: Callable[..., _T]) -> Callable[..., _T]:
    """A public method of :class:`Client` whose reading of an answer that is not the service's (not JSON, a field
    missing, another document) raises :class:`~kitti_eval.errors.ServiceError` rather than a Python error."""

    @functools.wraps(method)
    def wrapper(self: Client, *args: Any, **kwargs: Any) -> _T:
        try:
            return method(self, *args, **kwargs)
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise ServiceError(
                f"{self.service}: an answer this client cannot read ({type(e).__name__}: {e}); is it a kitti-eval "
                "service of this version?",
                code="unexpected_answer",
            ) from None

    return wrapper


@contextlib.contextmanager
def _tar_of_txt(folder: Path) -> Iterator[BinaryIO]:
    """A folder of KITTI txt files (the local reader's layout) as the service takes it: a tar.gz of its txt
    files, in a temporary file. The same files give the same bytes each time it is packed (gzip's header says
    no time): each try of a request packs it again, and a try after one whose answer was lost must send the
    file the idempotency key was first recorded with, or the service refuses the key as reused."""
    import gzip
    import tarfile
    import tempfile

    with tempfile.TemporaryFile() as raw:
        with gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=1, mtime=0) as packed:
            with tarfile.open(fileobj=packed, mode="w") as tar:
                for path in sorted(folder.glob("*.txt")):
                    tar.add(path, arcname=path.name, recursive=False)
        raw.seek(0)
        yield raw


#: a request's multipart files: field -> (file name, path)
_Files = Mapping[str, tuple[str, Path]]


class Client:
    """The service at ``service`` (``http(s)://HOST[:PORT]``), as the caller the token is.

    ``retries``: how long and how often a request is sent again while the service is away; ``timeout_s``: the
    longest silence on one connection; ``progress``: a bar (on stderr) while a file is sent; ``on_retry``: told
    a sentence each time a request is sent again (the CLI prints it); ``transport``: httpx's, for tests.

    A token is sent over plain ``http://`` to a loopback host only (``localhost``, ``127.0.0.1``, ``::1``);
    to any other host :class:`~kitti_eval.errors.ConfigError`, unless ``allow_http`` (None: whether
    ``$KITTI_EVAL_ALLOW_HTTP`` is ``1``) says that the network between is trusted."""

    def __init__(
        self,
        service: str,
        token: str | None = None,
        *,
        retries: Retries | None = None,
        timeout_s: float = 120.0,
        progress: bool = False,
        on_retry: Callable[[str], None] | None = None,
        transport: Any = None,
        allow_http: bool | None = None,
    ) -> None:
        try:
            import httpx
        except ImportError:
            raise ConfigError("the client needs httpx: pip install 'kitti-eval[client]'") from None
        service = _service_key(service)
        if not service.startswith(("http://", "https://")):
            raise ConfigError(f"--service: expected http(s)://HOST[:PORT], got {service!r}")
        self.service = service
        self.retries = retries or Retries()
        self.progress = progress
        self.on_retry = on_retry
        headers = {"User-Agent": _USER_AGENT, "Accept": "application/json"}
        token = token_for(service, token)
        if token:
            _refuse_plain_http(service, allow_http)
            headers["Authorization"] = f"Bearer {token}"
        self.sends_token = bool(token)
        self._httpx = httpx
        self._http = httpx.Client(base_url=service, headers=headers, timeout=timeout_s, transport=transport)

    def close(self) -> None:
        """Closes the connections (``with Client(...) as c:`` closes them on leaving)."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- sending ----------------------------------------------------------------------------------------
    def _request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        data: Mapping[str, Any] | None = None,
        json_body: Any = None,
        files: _Files | None = None,
        headers: Mapping[str, str] | None = None,
        ok: Sequence[int] = (200, 201, 202),
    ) -> httpx.Response:
        """One request, sent again while the service is away (see :class:`Retries`); a refusal raises."""
        httpx = self._httpx
        start = time.monotonic()
        attempt = 0
        while True:
            try:
                with self._opened(files) as opened:
                    response = self._http.request(
                        method, path, params=params, data=data, json=json_body, files=opened, headers=headers
                    )
            except httpx.TransportError as e:
                reason, wait = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__, None
            else:
                error = _error_of(response) if response.status_code >= 400 else {}
                away = response.status_code in _AWAY or (
                    response.status_code == 429 and error.get("code") == "too_many_queued"
                )
                if not away:
                    if response.status_code in ok:
                        return response
                    raise self._refused(response)
                reason = f"{response.status_code} {_shown(error.get('code') or response.reason_phrase)}"
                wait = _retry_after(response)
            delay = self.retries.delay(attempt, wait)
            waited = time.monotonic() - start
            if waited + delay > self.retries.within_s:
                raise ServiceUnreachable(
                    f"{self.service}: no answer to {method} {path} within {self.retries.within_s:g} s "
                    f"({attempt + 1} tries; the last: {reason})",
                    code="unreachable",
                )
            if self.on_retry is not None:
                self.on_retry(f"{self.service}: {reason}; trying again in {delay:.1f} s")
            time.sleep(delay)
            attempt += 1

    def _refused(self, response: httpx.Response) -> ServiceError:
        """The refusal's error; one for want of a token says how to give one."""
        error = _refusal(response)
        if response.status_code == 401 and not self.sends_token:
            return ServiceError(
                f"{self.service} needs a token: save yours once with 'kitti-eval login --service {self.service}' "
                f"(or set ${TOKEN_ENV})",
                status=401,
                code=error.code,
                details=error.details,
            )
        return error

    @contextlib.contextmanager
    def _opened(self, files: _Files | None) -> Iterator[dict[str, Any] | None]:
        """The files of one try, opened afresh (a try that failed half-way leaves its file read half-way)."""
        if not files:
            yield None
            return
        with contextlib.ExitStack() as stack:
            out: dict[str, Any] = {}
            for name, (filename, path) in files.items():
                if path.is_dir():
                    raw, filename = stack.enter_context(_tar_of_txt(path)), f"{path.name}.tar.gz"
                else:
                    raw = stack.enter_context(open(path, "rb"))  # noqa: SIM115 - closed by the stack
                out[name] = (filename, self._with_progress(raw, filename, stack), "application/octet-stream")
            yield out

    def _with_progress(self, raw: BinaryIO, filename: str, stack: Any) -> Any:
        if not self.progress:
            return raw
        from tqdm import tqdm

        size = os.fstat(raw.fileno()).st_size
        bar = stack.enter_context(
            tqdm(total=size, unit="B", unit_scale=True, unit_divisor=1024, desc=f"sending {filename}", leave=False)
        )
        return _Counted(raw, bar.update)

    def _get(self, path: str, **params: Any) -> Any:
        return self._request("GET", path, params={k: v for k, v in params.items() if v is not None}).json()

    def _follow(self, location: object) -> Any:
        """GET a place the service named (a job's ``result_location``): a path on this service only, so the token
        is never sent to another host whatever an answer says."""
        if not isinstance(location, str) or not location.startswith("/") or location.startswith("//"):
            raise ServiceError(f"{self.service}: the answer names {location!r} as the result, not a path of its own")
        return self._get(location)

    @_answered
    def whoami(self) -> dict[str, Any]:
        """Who the token is, as the service admitted it: ``user``, ``admin``, ``read_only``."""
        body = self._get("/v1/me")
        return {"user": _shown(body["user"]), "admin": bool(body.get("admin")), "read_only": bool(body["read_only"])}

    # -- jobs -------------------------------------------------------------------------------------------
    @_answered
    def job(self, job_id: str) -> Job:
        """An accepted evaluation's or submission's job as it is now."""
        return Job.from_body(self._get(f"/v1/jobs/{job_id}"))

    @_answered
    def wait_job(self, job_id: str, *, timeout_s: float = 3600.0, poll_s: float = 1.0) -> Job:
        """Polls the job until it is done, failed or cancelled; a job that failed raises its error."""
        deadline = time.monotonic() + timeout_s
        pause = poll_s
        while True:
            job = self.job(job_id)
            if job.ended:
                break
            if time.monotonic() + pause > deadline:
                raise ServiceError(
                    f"job {job_id} is still {job.state} after {timeout_s:g} s; ask again later "
                    f"({self.service}/v1/jobs/{job_id})",
                    code="still_pending",
                    details={"job_id": job_id},
                )
            time.sleep(pause)
            pause = min(5.0, pause * 1.5)
        if job.state == "failed":
            error = job.error or {}
            raise ServiceError(
                f"job {job_id} failed: {_shown(error.get('message', 'no reason given'))}",
                status=error.get("status"),
                code=error.get("code"),
                details={"job_id": job_id},
            )
        if job.state == "cancelled":
            raise ServiceError(f"job {job_id} was cancelled by an admin", code="cancelled", details={"job_id": job_id})
        return job

    def _accepted(self, response: httpx.Response, wait_s: float) -> str | None:
        """The result's place of an accepted request: at once (201), or once its job has ended (202)."""
        if response.status_code == 201:
            return None
        job = self.wait_job(_id(response.json()["id"]), timeout_s=wait_s)
        return job.result_location

    # -- evaluations ------------------------------------------------------------------------------------
    @_answered
    def evaluate(
        self,
        predictions: str | os.PathLike[str],
        gt: str,
        *,
        protocol: str | None = None,
        classes: str | Sequence[str] | None = None,
        threshold_sets: str | None = None,
        iou: Sequence[str] = (),
        ranges: str | None = None,
        coco: bool = False,
        lidar_only: bool = False,
        curves: bool = False,
        errors: bool = False,
        labels: Mapping[str, str] | None = None,
        project: str | None = None,
        wait_s: float = 3600.0,
        idempotency_key: str | None = None,
    ) -> Evaluation:
        """Evaluates ``predictions`` (a result.pkl, or a zip/tar of KITTI result txt files) against the ground
        truth registered as ``gt``, with the options of ``kitti-eval --gt --pred``; stored with ``labels``.
        ``idempotency_key``: the key sent with every try (default: a new UUID); the same key again (a CI job run
        again) is answered with the evaluation it made."""
        path = Path(predictions)
        if not path.exists():
            raise ConfigError(f"{path}: no such file (a result.pkl, a zip/tar of txt files, or a folder of them)")
        fields: dict[str, Any] = {"gt": gt, "coco": _flag(coco), "lidar_only": _flag(lidar_only)}
        fields.update(curves=_flag(curves), errors=_flag(errors))
        if protocol:
            fields["protocol"] = protocol
        if classes:
            fields["classes"] = classes if isinstance(classes, str) else ",".join(classes)
        if threshold_sets:
            fields["threshold_sets"] = threshold_sets
        if iou:
            fields["iou"] = list(iou)
        if ranges:
            fields["ranges"] = ranges
        if project:
            fields["project"] = project
        if labels:
            fields["label"] = [f"{k}={v}" for k, v in labels.items()]
        response = self._request(
            "POST",
            "/v1/evaluations",
            params={"wait": _POST_WAIT_S},
            data=fields,
            files={"predictions": (path.name, path)},
            headers={"Idempotency-Key": idempotency_key or new_key()},
        )
        location = self._accepted(response, wait_s)
        if location is None:
            return Evaluation.from_body(response.json())
        return Evaluation.from_body(self._follow(location))

    @_answered
    def evaluation(self, evaluation_id: str) -> Evaluation:
        """One stored evaluation (yours, or your projects')."""
        return Evaluation.from_body(self._get(f"/v1/evaluations/{evaluation_id}"))

    @_answered
    def evaluations(
        self, *, gt: str | None = None, labels: Mapping[str, str] | None = None, limit: int = 50
    ) -> list[dict[str, Any]]:
        """The history, newest first: each evaluation's record and its moderate AP per class and metric."""
        params: dict[str, Any] = {"gt": gt, "limit": limit}
        if labels:
            params["label"] = [f"{k}={v}" for k, v in labels.items()]
        return list(self._get("/v1/evaluations", **params)["items"])

    # -- benchmarks -------------------------------------------------------------------------------------
    @_answered
    def benchmarks(self) -> list[dict[str, Any]]:
        """The benchmarks you may see, each with its rules."""
        return list(self._get("/v1/benchmarks")["items"])

    @_answered
    def benchmark(self, name: str) -> dict[str, Any]:
        """One benchmark and its rules: key, columns, quota, whether it is open, its board's part."""
        return dict(self._get(f"/v1/benchmarks/{name}"))

    @_answered
    def frames(self, benchmark: str, *, phase: str | None = None) -> list[str]:
        """The test frame ids of the benchmark's phase (None: its current one): what a submission must hold."""
        from .core.frames import normalize_frame_id

        frames = self._get(f"{_at(benchmark, phase)}/frames").get("frames")
        if not isinstance(frames, list) or not frames:
            raise ServiceError(f"{self.service}: benchmark {benchmark} lists no test frames")
        return [normalize_frame_id(f) for f in frames]

    @_answered
    def leaderboard(
        self, benchmark: str, *, sort: str | None = None, order: str | None = None, phase: str | None = None
    ) -> dict[str, Any]:
        """The board of the benchmark's phase (None: its current one) as the service shows it to you (entries,
        columns, the key, intervals)."""
        return dict(self._get(f"{_at(benchmark, phase)}/leaderboard", sort=sort, order=order))

    @_answered
    def quota(self, benchmark: str, *, phase: str | None = None) -> Quota:
        """Your quota (your team's, in a team) on the benchmark's phase (None: its current one) as it stands."""
        q = self._get(f"{_at(benchmark, phase)}/submissions")["quota"]
        next_at = q.get("next_at")
        return Quota(
            int(q["submissions"]),
            float(q["days"]),
            int(q["used"]),
            int(q["left"]),
            _shown(next_at) if next_at else None,
        )

    @_answered
    def submissions(self, benchmark: str, *, phase: str | None = None) -> list[Submission]:
        """Your submissions to the benchmark's phase (None: its current one), newest first."""
        return [Submission.from_body(s) for s in self._get(f"{_at(benchmark, phase)}/submissions")["items"]]

    @_answered
    def submission(self, benchmark: str, submission_id: str) -> Submission:
        """One of your submissions, with its scores and aggregate result once scored."""
        return Submission.from_body(self._get(f"/v1/benchmarks/{benchmark}/submissions/{submission_id}"))

    @_answered
    def leaderboard_csv(self, benchmark: str, *, phase: str | None = None) -> str:
        """The board of the benchmark's phase (None: its current one) as the service's CSV."""
        from .client_benchmarks import board_csv

        return board_csv(self, f"{_at(benchmark, phase)}/leaderboard")

    @_answered
    def publish(
        self,
        benchmark: str,
        submission_id: str,
        *,
        method: str,
        anonymous: bool = False,
        affiliation: str | None = None,
        link: str | None = None,
    ) -> Submission:
        """Shows one of your scored submissions on the board under ``method`` (``anonymous``: without your name,
        affiliation or link); the submission as it is then."""
        from .client_benchmarks import publish

        return Submission.from_body(
            publish(
                self,
                benchmark,
                _id(submission_id),
                method=method,
                anonymous=anonymous,
                affiliation=affiliation,
                link=link,
            )
        )

    @_answered
    def withdraw(self, benchmark: str, submission_id: str) -> Submission:
        """Takes one of your entries off the board; the submission as it is then."""
        from .client_benchmarks import withdraw

        return Submission.from_body(withdraw(self, benchmark, _id(submission_id)))

    # -- teams ------------------------------------------------------------------------------------------
    @_answered
    def teams(self, benchmark: str) -> dict[str, Any]:
        """The benchmark's teams: ``items`` (each with its members), ``mine`` (yours, None when in none),
        ``invitations`` (the teams that invited you) and ``team_size``."""
        from .client_benchmarks import teams

        return teams(self, benchmark)

    @_answered
    def create_team(self, benchmark: str, name: str, *, invite: Sequence[str] = ()) -> dict[str, Any]:
        """Makes the team ``name`` in the benchmark (you are its first member) and invites ``invite``, who join
        when they accept (:meth:`join_team`); the team with its ``members`` and ``invited``."""
        from .client_benchmarks import create_team

        return create_team(self, benchmark, name, invite)

    @_answered
    def join_team(self, benchmark: str, name: str) -> dict[str, Any]:
        """Joins the team ``name``, which invited you: from then on each phase's quota is the team's."""
        from .client_benchmarks import join_team

        return join_team(self, benchmark, name)

    def check_submission(
        self, predictions: str | os.PathLike[str], benchmark: str, *, phase: str | None = None
    ) -> None:
        """The checks of ``kitti-eval validate`` against the test frames of the benchmark's phase (None: its
        current one), here, before anything is sent: raises :class:`~kitti_eval.errors.SubmissionRefused` with the
        validator's sentences."""
        from .io.submission import SubmissionRules, validate_submission

        frames = tuple(self.frames(benchmark, phase=phase))
        outcome = validate_submission(Path(predictions), SubmissionRules(frames=frames))
        if not outcome.ok:
            lines = outcome.lines()
            raise SubmissionRefused(
                f"{predictions}: not a valid submission to {benchmark} ({len(lines)} problems); nothing was sent",
                lines,
                code="invalid_submission",
            )

    @_answered
    def submit(
        self,
        predictions: str | os.PathLike[str],
        benchmark: str,
        *,
        wait: bool = True,
        wait_s: float = 3600.0,
        check: bool = True,
        idempotency_key: str | None = None,
        phase: str | None = None,
        new: bool = False,
    ) -> Submission:
        """Submits ``predictions`` to the benchmark: checked here first (``check``: a refused file costs no
        quota and no upload), sent with an idempotency key (sent again while the service is away, it counts
        once), and with ``wait``, followed until it is scored (:class:`Submission` with its scores).
        Over the quota: :class:`~kitti_eval.errors.QuotaExceeded` (with when the next one is accepted).
        ``phase``: the benchmark's phase to submit to (None: its current one).

        The key: ``idempotency_key`` when given (sent again in another call, it is answered with the submission
        it made, counted once); else the key saved in the client's folder for the same file (its sha256) sent
        to the same service, benchmark and phase by a call that has not shown it scored yet (a process killed
        after its file reached the service), so that the same file submitted again counts once; else a new
        one, saved before the file is sent (:mod:`kitti_eval.client_state`). ``new``: a new key
        whatever was saved: the same file submitted again on purpose, counted again."""
        path = Path(predictions)
        if not path.exists():
            raise ConfigError(f"{path}: no such file (a result.pkl, a zip/tar of txt files, or a folder of them)")
        if check:
            self.check_submission(path, benchmark, phase=phase)
        if idempotency_key is not None:
            return self._submit(path, benchmark, phase, idempotency_key, wait=wait, wait_s=wait_s)
        from .client_state import PendingKeys

        pending = PendingKeys(config_dir())
        with pending.held(self.service, benchmark, phase, _upload_sha256(path), new=new) as held:
            submission = self._submit(path, benchmark, phase, held.key, wait=wait, wait_s=wait_s)
            held.keep = not wait
        return dataclasses.replace(submission, reused=held.reused)

    def _submit(
        self, path: Path, benchmark: str, phase: str | None, key: str, *, wait: bool, wait_s: float
    ) -> Submission:
        response = self._request(
            "POST",
            f"{_at(benchmark, phase)}/submissions",
            params={"wait": _POST_WAIT_S if wait else 0},
            files={"predictions": (path.name, path)},
            headers={"Idempotency-Key": key},
        )
        body = response.json()
        if response.status_code == 201:
            return Submission.from_body(body)
        job = Job.from_body(body)
        submission_id = _id(body.get("submission") or job.id)
        if not wait:
            return Submission(submission_id, benchmark, job.state, None, None, {"id": submission_id, "job": body})
        self.wait_job(job.id, timeout_s=wait_s)
        return self.submission(benchmark, submission_id)


def _upload_sha256(path: Path) -> str:
    """The sha256 of the bytes a submission of ``path`` sends (a folder: the tar.gz it is packed as)."""
    from .client_state import sha256_of

    if path.is_dir():
        with _tar_of_txt(path) as raw:
            return sha256_of(raw)
    with open(path, "rb") as raw:
        return sha256_of(raw)


def _at(benchmark: str, phase: str | None) -> str:
    """The path of a benchmark's phase: its own routes address its current phase."""
    return f"/v1/benchmarks/{benchmark}" if phase is None else f"/v1/benchmarks/{benchmark}/phases/{phase}"


def _flag(value: bool) -> str:
    return "true" if value else "false"
