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

:class:`Client` is composed of parts, each a module: the token and configuration
(:mod:`kitti_eval.client_config`), the HTTP with its retries (:mod:`kitti_eval.client_http`, the client's
``http``), the saved submission keys (:mod:`kitti_eval.client_state`), the submission flow
(:mod:`kitti_eval.client_submissions`) and the benchmark commands beyond submitting
(:mod:`kitti_eval.client_benchmarks`); this module holds the answers' types, the jobs, the evaluations and the
reads of a benchmark.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from .client_config import (
    ALLOW_HTTP_ENV,
    CONFIG_ENV,
    TOKEN_ENV,
    save_token,
    saved_services,
    saved_token,
    token_for,
)
from .client_http import Retries, Transport
from .client_http import shown as _shown
from .client_records import _POST_WAIT_S, Evaluation, Job, Quota, Submission, _at, _id
from .client_state import new_key
from .errors import (
    ConfigError,
    ServiceError,
)

if TYPE_CHECKING:
    import httpx


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

_T = TypeVar("_T")


# ------------------------------------------------------------------------------------------ the client


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
        #: the HTTP every call goes through: the token, the retries, the refusals as errors
        self.http = Transport(
            service,
            token,
            retries=retries,
            timeout_s=timeout_s,
            progress=progress,
            on_retry=on_retry,
            transport=transport,
            allow_http=allow_http,
        )
        self.service = self.http.service

    def close(self) -> None:
        """Closes the connections (``with Client(...) as c:`` closes them on leaving)."""
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @_answered
    def whoami(self) -> dict[str, Any]:
        """Who the token is, as the service admitted it: ``user``, ``admin``, ``read_only``."""
        body = self.http.get("/v1/me")
        return {"user": _shown(body["user"]), "admin": bool(body.get("admin")), "read_only": bool(body["read_only"])}

    # -- jobs -------------------------------------------------------------------------------------------
    @_answered
    def job(self, job_id: str) -> Job:
        """An accepted evaluation's or submission's job as it is now."""
        return Job.from_body(self.http.get(f"/v1/jobs/{job_id}"))

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
        keep: bool = True,
    ) -> Evaluation:
        """Evaluates ``predictions`` (a result.pkl, or a zip/tar of KITTI result txt files) against the ground
        truth registered as ``gt``, with the options of ``kitti-eval --gt --pred``; stored with ``labels``.
        ``idempotency_key``: the key sent with every try (default: a new UUID); the same key again (a CI job run
        again) is answered with the evaluation it made.

        ``keep=False``: evaluated for a gate and kept nowhere (``POST /v1/gates/evaluations``; a read-only token
        will do): no evaluation is stored, so none shows in the history, and the document is given once (the
        :class:`Evaluation`'s ``id`` names no stored evaluation, its ``meta`` says ``"kept": false``); it takes
        no ``labels`` nor ``project``."""
        path = Path(predictions)
        if not path.exists():
            raise ConfigError(f"{path}: no such file (a result.pkl, a zip/tar of txt files, or a folder of them)")
        if not keep and (labels or project):
            raise ConfigError(
                "an evaluation that is not kept (keep=False) takes no labels nor project: nothing stores them"
            )
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
        response = self.http.request(
            "POST",
            "/v1/evaluations" if keep else "/v1/gates/evaluations",
            params={"wait": _POST_WAIT_S},
            data=fields,
            files={"predictions": (path.name, path)},
            headers={"Idempotency-Key": idempotency_key or new_key()},
        )
        location = self._accepted(response, wait_s)
        if location is None:
            return Evaluation.from_body(response.json())
        return Evaluation.from_body(self.http.follow(location))

    @_answered
    def evaluation(self, evaluation_id: str) -> Evaluation:
        """One stored evaluation (yours, or your projects')."""
        return Evaluation.from_body(self.http.get(f"/v1/evaluations/{evaluation_id}"))

    @_answered
    def evaluations(
        self, *, gt: str | None = None, labels: Mapping[str, str] | None = None, limit: int = 50
    ) -> list[dict[str, Any]]:
        """The history, newest first: each evaluation's record and its moderate AP per class and metric."""
        params: dict[str, Any] = {"gt": gt, "limit": limit}
        if labels:
            params["label"] = [f"{k}={v}" for k, v in labels.items()]
        return list(self.http.get("/v1/evaluations", **params)["items"])

    # -- benchmarks -------------------------------------------------------------------------------------
    @_answered
    def benchmarks(self) -> list[dict[str, Any]]:
        """The benchmarks you may see, each with its rules."""
        return list(self.http.get("/v1/benchmarks")["items"])

    @_answered
    def benchmark(self, name: str) -> dict[str, Any]:
        """One benchmark and its rules: key, columns, quota, whether it is open, its board's part."""
        return dict(self.http.get(f"/v1/benchmarks/{name}"))

    @_answered
    def frames(self, benchmark: str, *, phase: str | None = None) -> list[str]:
        """The test frame ids of the benchmark's phase (None: its current one): what a submission must hold."""
        from .core.frames import normalize_frame_id

        frames = self.http.get(f"{_at(benchmark, phase)}/frames").get("frames")
        if not isinstance(frames, list) or not frames:
            raise ServiceError(f"{self.service}: benchmark {benchmark} lists no test frames")
        return [normalize_frame_id(f) for f in frames]

    @_answered
    def leaderboard(
        self, benchmark: str, *, sort: str | None = None, order: str | None = None, phase: str | None = None
    ) -> dict[str, Any]:
        """The board of the benchmark's phase (None: its current one) as the service shows it to you (entries,
        columns, the key, intervals)."""
        return dict(self.http.get(f"{_at(benchmark, phase)}/leaderboard", sort=sort, order=order))

    @_answered
    def quota(self, benchmark: str, *, phase: str | None = None) -> Quota:
        """Your quota (your team's, in a team) on the benchmark's phase (None: its current one) as it stands."""
        q = self.http.get(f"{_at(benchmark, phase)}/submissions")["quota"]
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
        return [Submission.from_body(s) for s in self.http.get(f"{_at(benchmark, phase)}/submissions")["items"]]

    @_answered
    def submission(self, benchmark: str, submission_id: str) -> Submission:
        """One of your submissions, with its scores and aggregate result once scored."""
        return Submission.from_body(self.http.get(f"/v1/benchmarks/{benchmark}/submissions/{submission_id}"))

    @_answered
    def leaderboard_csv(self, benchmark: str, *, phase: str | None = None) -> str:
        """The board of the benchmark's phase (None: its current one) as the service's CSV."""
        from .client_benchmarks import board_csv

        return board_csv(self.http, f"{_at(benchmark, phase)}/leaderboard")

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
                self.http,
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

        return Submission.from_body(withdraw(self.http, benchmark, _id(submission_id)))

    # -- teams ------------------------------------------------------------------------------------------
    @_answered
    def teams(self, benchmark: str) -> dict[str, Any]:
        """The benchmark's teams: ``items`` (each with its members), ``mine`` (yours, None when in none),
        ``invitations`` (the teams that invited you) and ``team_size``."""
        from .client_benchmarks import teams

        return teams(self.http, benchmark)

    @_answered
    def create_team(self, benchmark: str, name: str, *, invite: Sequence[str] = ()) -> dict[str, Any]:
        """Makes the team ``name`` in the benchmark (you are its first member) and invites ``invite``, who join
        when they accept (:meth:`join_team`); the team with its ``members`` and ``invited``."""
        from .client_benchmarks import create_team

        return create_team(self.http, benchmark, name, invite)

    @_answered
    def join_team(self, benchmark: str, name: str) -> dict[str, Any]:
        """Joins the team ``name``, which invited you: from then on each phase's quota is the team's."""
        from .client_benchmarks import join_team

        return join_team(self.http, benchmark, name)

    @_answered
    def leave_team(self, benchmark: str) -> dict[str, Any]:
        """Leaves your team of the benchmark (until its last phase has closed): from then on your submissions count
        against your own quota; what you submitted for the team still counts against the team's and your own while
        it is in the quota's window, and the board keeps naming the team on its entries. The team left (``left``)
        and its ``members`` now."""
        from .client_benchmarks import leave_team

        return leave_team(self.http, benchmark)

    def check_submission(
        self, predictions: str | os.PathLike[str], benchmark: str, *, phase: str | None = None
    ) -> None:
        """The checks of ``kitti-eval validate`` against the test frames of the benchmark's phase (None: its
        current one), here, before anything is sent: raises :class:`~kitti_eval.errors.SubmissionRefused` with the
        validator's sentences."""
        from .client_submissions import check_submission

        check_submission(self, predictions, benchmark, phase=phase)

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
        from .client_submissions import submit

        return submit(
            self,
            predictions,
            benchmark,
            wait=wait,
            wait_s=wait_s,
            check=check,
            idempotency_key=idempotency_key,
            phase=phase,
            new=new,
        )


def _flag(value: bool) -> str:
    return "true" if value else "false"
