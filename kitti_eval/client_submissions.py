"""The submission flow of :meth:`Client.submit <kitti_eval.client.Client.submit>`: the file checked here first
with ``kitti-eval validate``'s checks against the phase's test frames (a refused file costs no quota and no
upload), its idempotency key (given, else the one saved for the same file sent to the same phase by a run that
has not shown it scored, else a new one saved first: :mod:`kitti_eval.client_state`), sent through the client's
HTTP and followed until it is scored."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Protocol

from .client_config import config_dir
from .client_http import Transport, tar_of_txt
from .client_records import _POST_WAIT_S, Job, Submission, _at, _id
from .errors import ConfigError, SubmissionRefused

__all__ = ["check_submission", "submit", "upload_sha256"]


class Client(Protocol):
    """What the flow asks of :class:`kitti_eval.client.Client` (named here so the client's module imports this one,
    not the other way round)."""

    http: Transport
    service: str

    def frames(self, benchmark: str, *, phase: str | None = None) -> list[str]: ...

    def check_submission(
        self, predictions: str | os.PathLike[str], benchmark: str, *, phase: str | None = None
    ) -> None: ...

    def wait_job(self, job_id: str, *, timeout_s: float = 3600.0, poll_s: float = 1.0) -> Job: ...

    def submission(self, benchmark: str, submission_id: str) -> Submission: ...


def check_submission(
    client: Client, predictions: str | os.PathLike[str], benchmark: str, *, phase: str | None = None
) -> None:
    """The checks of ``kitti-eval validate`` against the test frames of the benchmark's phase (None: its
    current one): raises :class:`~kitti_eval.errors.SubmissionRefused` with the validator's sentences."""
    from .io.submission import SubmissionRules, validate_submission

    frames = tuple(client.frames(benchmark, phase=phase))
    outcome = validate_submission(Path(predictions), SubmissionRules(frames=frames))
    if not outcome.ok:
        lines = outcome.lines()
        raise SubmissionRefused(
            f"{predictions}: not a valid submission to {benchmark} ({len(lines)} problems); nothing was sent",
            lines,
            code="invalid_submission",
        )


def submit(
    client: Client,
    predictions: str | os.PathLike[str],
    benchmark: str,
    *,
    wait: bool,
    wait_s: float,
    check: bool,
    idempotency_key: str | None,
    phase: str | None,
    new: bool,
) -> Submission:
    """:meth:`Client.submit <kitti_eval.client.Client.submit>` (which says what each argument does)."""
    path = Path(predictions)
    if not path.exists():
        raise ConfigError(f"{path}: no such file (a result.pkl, a zip/tar of txt files, or a folder of them)")
    if check:
        client.check_submission(path, benchmark, phase=phase)
    if idempotency_key is not None:
        return _send(client, path, benchmark, phase, idempotency_key, wait=wait, wait_s=wait_s)
    from .client_state import PendingKeys

    pending = PendingKeys(config_dir())
    with pending.held(client.service, benchmark, phase, upload_sha256(path), new=new) as held:
        submission = _send(client, path, benchmark, phase, held.key, wait=wait, wait_s=wait_s)
        held.keep = not wait
    return dataclasses.replace(submission, reused=held.reused)


def _send(
    client: Client, path: Path, benchmark: str, phase: str | None, key: str, *, wait: bool, wait_s: float
) -> Submission:
    """The file sent with ``key``; with ``wait``, followed until its job ends."""
    response = client.http.request(
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
    client.wait_job(job.id, timeout_s=wait_s)
    return client.submission(benchmark, submission_id)


def upload_sha256(path: Path) -> str:
    """The sha256 of the bytes a submission of ``path`` sends (a folder: the tar.gz it is packed as)."""
    from .client_state import sha256_of

    if path.is_dir():
        with tar_of_txt(path) as raw:
            return sha256_of(raw)
    with open(path, "rb") as raw:
        return sha256_of(raw)
