"""The jobs as admins see them: every owner's, listed by state, cancelled, run again. No HTTP in here: the
routes (``/v1/admin/jobs``) and ``kitti-eval admin jobs`` call the same methods, and each change is audited
here (``job.cancel``, ``job.rerun``), whatever the door."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from ..access.audit import Audit
from ..access.policy import Caller, Policy
from ..errors import Conflict, NotFound, echo
from .queue import ENDED_STATES, JobQueue, JobRecord

__all__ = ["JobAdmin", "RunAgainCheck"]

#: why a kind's ended job cannot run again (None: it can), e.g. its inputs are gone
RunAgainCheck = Callable[[JobRecord], "str | None"]


class JobAdmin:
    def __init__(
        self,
        queue: JobQueue,
        policy: Policy,
        audit: Audit,
        *,
        run_again: Mapping[str, RunAgainCheck],
        wake: Callable[[], None],
    ) -> None:
        """``run_again``: by kind, what says whether an ended job can run again; ``wake``: the idle workers of
        this process look at the queue."""
        self.queue = queue
        self.policy = policy
        self.audit = audit
        self.run_again = dict(run_again)
        self.wake = wake

    def _job(self, job_id: str) -> JobRecord:
        job = self.queue.get(job_id)
        if job is None:
            raise NotFound(f"no job with id {echo(job_id)}")
        return job

    def listed(self, caller: Caller, *, state: str | None = None, limit: int = 100, offset: int = 0) -> list[JobRecord]:
        """Every owner's jobs, newest first (of ``state`` when given)."""
        self.policy.require_admin(caller)
        return self.queue.list(state=state, limit=limit, offset=offset)

    def counts(self, caller: Caller) -> dict[str, int]:
        """Jobs by state."""
        self.policy.require_admin(caller)
        return self.queue.counts()

    def cancel(self, job_id: str, caller: Caller) -> JobRecord:
        """A queued or running job is cancelled (a running one's result, when its worker ends it, is not
        stored); 409 for a job that has ended."""
        self.policy.require_admin(caller)
        before = self._job(job_id)
        if before.state in ENDED_STATES:
            raise Conflict(f"job {job_id} has ended ({before.state}): there is nothing to cancel")
        job = self.queue.cancel(job_id)
        if job is None or job.state != "cancelled":  # it ended meanwhile
            state = job.state if job is not None else "gone"
            raise Conflict(f"job {job_id} ended ({state}) before it could be cancelled")
        self.audit.record(caller, "job.cancel", job_id, detail=f"{job.kind} of {job.owner}, was {before.state}")
        return job

    def rerun(self, job_id: str, caller: Caller) -> JobRecord:
        """An ended job is queued again, as new (no attempt used); 409 for one still queued or running, and for
        one its kind says cannot run again (an evaluation that is done, or whose inputs are gone)."""
        self.policy.require_admin(caller)
        before = self._job(job_id)
        if before.state not in ENDED_STATES:
            raise Conflict(f"job {job_id} is {before.state}: it runs without being told to")
        check = self.run_again.get(before.kind)
        refusal = check(before) if check is not None else None
        if refusal:
            raise Conflict(refusal)
        job = self.queue.rerun(job_id)
        if job is None or job.state != "queued":  # another admin ran it again meanwhile
            raise Conflict(f"job {job_id} is already queued again")
        self.audit.record(caller, "job.rerun", job_id, detail=f"{job.kind} of {job.owner}, was {before.state}")
        self.wake()
        return job
