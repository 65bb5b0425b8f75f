"""The client's HTTP: one service's connections, with the token, each request sent again while the service is
away (:class:`Retries`), a refusal turned into an error of the one tree
(:class:`~kitti_eval.errors.ServiceError` and its kinds), a file's upload opened afresh for each try (a folder of
txt files packed the same way each time) with its progress. :class:`~kitti_eval.client.Client` sends through one
:class:`Transport`; so do its benchmark commands (:mod:`kitti_eval.client_benchmarks`)."""

from __future__ import annotations

import contextlib
import math
import os
import random
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from .client_config import TOKEN_ENV, refuse_plain_http, service_key, token_for
from .errors import ConfigError, QuotaExceeded, ServiceError, ServiceUnreachable, SubmissionRefused

if TYPE_CHECKING:
    import httpx

__all__ = ["Retries", "Transport", "Files", "shown", "refusal", "tar_of_txt"]

#: statuses answered while a service is away or too busy for now: sent again
_AWAY = frozenset({408, 502, 503, 504})
_USER_AGENT = "kitti-eval-client"


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


def shown(text: object) -> str:
    """A service's text as it may be printed: control characters replaced, its length bounded."""
    out = _CONTROL.sub("?", str(text))
    return out if len(out) <= _MAX_SHOWN else out[:_MAX_SHOWN] + "..."


def refusal(response: httpx.Response) -> ServiceError:
    """The error of the one tree a refusal is."""
    error = _error_of(response)
    code = shown(error.get("code") or "")
    message = shown(error.get("message") or response.reason_phrase or f"HTTP {response.status_code}")
    details = {k: v for k, v in error.items() if k not in ("code", "message")}
    kw: dict[str, Any] = {"status": response.status_code, "code": code or None, "details": details}
    if code == "quota_exceeded":
        return QuotaExceeded(message, **kw)
    if code == "invalid_submission":
        problems = details.get("problems")
        return SubmissionRefused(message, [shown(p) for p in problems] if isinstance(problems, list) else [], **kw)
    return ServiceError(message, **kw)


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


@contextlib.contextmanager
def tar_of_txt(folder: Path) -> Iterator[BinaryIO]:
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
Files = Mapping[str, tuple[str, Path]]


class Transport:
    """The service at ``service`` (``http(s)://HOST[:PORT]``) over HTTP, as the caller the token is (``token``,
    else ``$KITTI_EVAL_TOKEN``, else the one saved for it): the arguments are :class:`~kitti_eval.client.Client`'s.
    A token goes over plain ``http://`` to a loopback host only, unless ``allow_http`` says the network is
    trusted (:func:`~kitti_eval.client_config.refuse_plain_http`)."""

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
        service = service_key(service)
        if not service.startswith(("http://", "https://")):
            raise ConfigError(f"--service: expected http(s)://HOST[:PORT], got {service!r}")
        self.service = service
        self.retries = retries or Retries()
        self.progress = progress
        self.on_retry = on_retry
        headers = {"User-Agent": _USER_AGENT, "Accept": "application/json"}
        token = token_for(service, token)
        if token:
            refuse_plain_http(service, allow_http)
            headers["Authorization"] = f"Bearer {token}"
        self.sends_token = bool(token)
        self._httpx = httpx
        self._http = httpx.Client(base_url=service, headers=headers, timeout=timeout_s, transport=transport)

    def close(self) -> None:
        """Closes the connections."""
        self._http.close()

    def request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        data: Mapping[str, Any] | None = None,
        json_body: Any = None,
        files: Files | None = None,
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
                    raise self.refused(response)
                reason = f"{response.status_code} {shown(error.get('code') or response.reason_phrase)}"
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

    def refused(self, response: httpx.Response) -> ServiceError:
        """The refusal's error; one for want of a token says how to give one."""
        error = refusal(response)
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
    def _opened(self, files: Files | None) -> Iterator[dict[str, Any] | None]:
        """The files of one try, opened afresh (a try that failed half-way leaves its file read half-way)."""
        if not files:
            yield None
            return
        with contextlib.ExitStack() as stack:
            out: dict[str, Any] = {}
            for name, (filename, path) in files.items():
                if path.is_dir():
                    raw, filename = stack.enter_context(tar_of_txt(path)), f"{path.name}.tar.gz"
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

    def get(self, path: str, **params: Any) -> Any:
        """GET ``path`` (``params`` None are left out): the answer's JSON."""
        return self.request("GET", path, params={k: v for k, v in params.items() if v is not None}).json()

    def follow(self, location: object) -> Any:
        """GET a place the service named (a job's ``result_location``): a path on this service only, so the token
        is never sent to another host whatever an answer says."""
        if not isinstance(location, str) or not location.startswith("/") or location.startswith("//"):
            raise ServiceError(f"{self.service}: the answer names {location!r} as the result, not a path of its own")
        return self.get(location)
