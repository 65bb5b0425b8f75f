"""Ground truths as callers see them: which they may list, read and evaluate against (the policy decides), and
the admins' registering and deleting (audited). The files, their storage and the loaded sets are
:class:`~kitti_eval_server.ground_truths.cache.GroundTruths`'."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

from ..access.audit import Audit
from ..access.policy import Caller, Policy
from ..errors import NotFound
from ..scoring.uploads import FileIn, receive_upload
from ..store import GroundTruthRecord, GroundTruthStore
from .cache import GroundTruths

__all__ = ["GroundTruthCatalog"]


class GroundTruthCatalog:
    def __init__(
        self,
        files: GroundTruths,
        ground_truth_store: GroundTruthStore,
        policy: Policy,
        audit: Audit,
        scratch: Callable[[], AbstractContextManager[Path]],
        check_project: Callable[[str], str],
    ) -> None:
        self.files = files
        self.ground_truth_store = ground_truth_store
        self.policy = policy
        self.audit = audit
        self.scratch = scratch
        #: the accounts' check that a project exists (404 otherwise)
        self.check_project = check_project

    def get(self, name: str, caller: Caller) -> GroundTruthRecord:
        """The registered ground truth, if the caller may use it; another project's is as absent as a missing
        one."""
        try:
            record: GroundTruthRecord | None = self.files.record(name)
        except NotFound:
            record = None
        self.policy.require_ground_truth(caller, record, name)
        assert record is not None
        return record

    def listed(self, caller: Caller) -> list[GroundTruthRecord]:
        if not self.policy.is_signed_in(caller):
            return []
        return self.ground_truth_store.list_ground_truths(projects=self.policy.project_filter(caller))

    def to_evaluate(self, caller: Caller) -> list[GroundTruthRecord]:
        """The ground truths the caller may evaluate against (what the upload form offers): those they see,
        less the benchmarks' test sets unless they are an admin."""
        hidden = set(self.policy.hidden_ground_truths(caller))  # one look at the benchmarks, not one a record
        return [r for r in self.listed(caller) if r.name not in hidden]

    def add(
        self, name: str, file: FileIn, *, caller: Caller, project: str | None = None, sealed: bool = False
    ) -> GroundTruthRecord:
        """Register a named ground truth (admins); ``project``: only its members see and use it (None:
        everyone); ``sealed``: no per-frame view of it ever leaves the service."""
        self.policy.require_admin(caller)
        if project is not None:
            self.check_project(project)
        with self.scratch() as scratch:
            upload = receive_upload(file.file, file.filename, "file")
            record = self.files.register(name, upload, scratch, project=project, sealed=sealed)
        detail = f"project {record.project or '-'}{', sealed' if record.sealed else ''}"
        self.audit.record(caller, "ground_truth.add", record.name, detail=detail)
        return record

    def remove(self, name: str, *, caller: Caller) -> GroundTruthRecord:
        """Delete a registered ground truth (admins); evaluations made with it stay."""
        self.policy.require_admin(caller)
        record = self.files.delete(name)
        self.audit.record(caller, "ground_truth.delete", name)
        return record
