"""Idempotency keys, as the IETF draft "The Idempotency-Key HTTP Header Field" describes them: a client sends
``Idempotency-Key: <a unique value>`` with ``POST /v1/evaluations`` or ``POST /v1/benchmarks/NAME/submissions``
(the web forms send one of their own, drawn when the form is shown), and when it sends the same request again
with the same key (a retry after a 503, a timeout, a dropped connection, a service killed between committing and
answering) it gets the first request's job again, as it is now: the same id, never a second record, never a second
count against a quota.

A key is the caller's (another caller's same key is another key) and the place's it was sent to; it is recorded
with its request's fingerprint (the sha256 of its files and fields) in the transaction that records the job, so
concurrent copies of one request are recorded one after another and all but the first get the first's job. The
same key with another request (another file, other fields) is refused, 422 ``idempotency_key_reused``, naming the
key. A key is kept for ``KITTI_EVAL_IDEMPOTENCY_KEY_HOURS`` (a day); a request refused before its job was
recorded (a 4xx, a full queue) records nothing, so it may be sent again with its key.
"""

from __future__ import annotations

import hashlib
import json
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from .errors import ApiError, echo
from .jobs.queue import JobQueue, JobRecord, now_utc
from .store import IdempotencyRecord, IdempotencyStore, KeyTaken

__all__ = [
    "HEADER",
    "IDEMPOTENCY_DESCRIPTION",
    "FORM_FIELD",
    "EVALUATIONS",
    "GATE_EVALUATIONS",
    "Idempotency",
    "RequestKey",
    "KeyReused",
    "InvalidKey",
    "KeyTaken",
    "parse_key",
    "fingerprint",
    "new_form_key",
    "submissions_scope",
]

HEADER = "Idempotency-Key"
#: the web forms' hidden field holding their key
FORM_FIELD = "idempotency_key"
#: the scope of the evaluations' keys (the API's and the upload form's)
EVALUATIONS = "POST /v1/evaluations"
#: the scope of the keys of the evaluations a gate asks for without keeping them
GATE_EVALUATIONS = "POST /v1/gates/evaluations"
#: what the API's documentation says of the header
IDEMPOTENCY_DESCRIPTION = (
    "a unique value of yours (a UUID, say): sending the same request again with the same key (a retry) answers "
    "the first request's job, as it is now, and records nothing new; the same key with another request is "
    "refused (422 idempotency_key_reused). Kept for KITTI_EVAL_IDEMPOTENCY_KEY_HOURS (24)"
)
#: the longest key kept
MAX_KEY_CHARS = 255


def submissions_scope(benchmark: str) -> str:
    return f"POST /v1/benchmarks/{benchmark}/submissions"


class InvalidKey(ApiError):
    status_code = 400
    code = "invalid_idempotency_key"


class KeyReused(ApiError):
    """The key was sent before with another request."""

    status_code = 422
    code = "idempotency_key_reused"

    def __init__(self, key: str, job_id: str) -> None:
        super().__init__(
            f"the Idempotency-Key {echo(key)} was sent before with another request (another file or other fields; "
            f"it made job {job_id}): send a new key with a new request"
        )
        self.details = {"idempotency_key": key, "job_id": job_id}


def parse_key(value: str | None) -> str | None:
    """A request's key from its header or form field (None: it sent none): 1-255 visible ASCII characters; a
    structured-field string (``"..."``, as the draft writes it) is taken without its quotes."""
    if value is None:
        return None
    text = value.strip()
    if len(text) >= 2 and text[0] == text[-1] == '"':
        text = text[1:-1]
    if not 1 <= len(text) <= MAX_KEY_CHARS or not all(33 <= ord(c) <= 126 for c in text):
        raise InvalidKey(f"an {HEADER} is 1-{MAX_KEY_CHARS} visible ASCII characters (a UUID, say), got {echo(value)}")
    return text


def new_form_key() -> str:
    """A web form's key, drawn when the form is shown (sent again by the browser, it makes one job)."""
    return secrets.token_urlsafe(24)


def fingerprint(**parts: Any) -> str:
    """The sha256 of a request's files (by their sha256) and fields."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


@dataclass(frozen=True)
class RequestKey:
    """A request's key: who sent it, where, and the fingerprint of what it sent."""

    owner: str
    scope: str
    key: str
    fingerprint: str


class Idempotency:
    """The keys of one database."""

    def __init__(
        self,
        idempotency_store: IdempotencyStore,
        jobs: JobQueue,
        hours: float = 24.0,
        clock: Callable[[], datetime] = now_utc,
    ) -> None:
        self.idempotency_store = idempotency_store
        self.jobs = jobs
        self.keep = timedelta(hours=hours)
        self.clock = clock

    def known(self, owner: str, scope: str, key: str | None) -> bool:
        """Whether the key was recorded and has not expired (before a request's body: a retry is answered by its
        route, whatever a quota says now)."""
        return key is not None and self.idempotency_store.idempotency_key(owner, scope, key, self.clock()) is not None

    def earlier(self, key: RequestKey | None) -> JobRecord | None:
        """The job the key's first request made (None: no key, or not recorded); :class:`KeyReused` when the
        key was sent with another request."""
        if key is None:
            return None
        found = self.idempotency_store.idempotency_key(key.owner, key.scope, key.key, self.clock())
        return None if found is None else self._job(key, found)

    def record(self, key: RequestKey, job_id: str) -> IdempotencyRecord:
        """The row that records the key with its job (written in the job's transaction)."""
        now = self.clock()
        return IdempotencyRecord(key.owner, key.scope, key.key, key.fingerprint, job_id, now, now + self.keep)

    def taken(self, key: RequestKey, e: KeyTaken) -> JobRecord:
        """The first request's job, when a copy of it recorded the key first (:class:`KeyReused` when that was
        another request)."""
        return self._job(key, e.record)

    def _job(self, key: RequestKey, found: IdempotencyRecord) -> JobRecord:
        if found.fingerprint != key.fingerprint:
            raise KeyReused(key.key, found.job_id)
        job = self.jobs.get(found.job_id)
        if job is None:  # a database changed by hand: the job went, its key with it
            raise KeyReused(key.key, found.job_id)
        return job
