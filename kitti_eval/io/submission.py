"""Checks of a benchmark submission before it is evaluated, as KITTI's submission server makes them.

A submission is a result for every frame of a test set: a zip or tar of KITTI result txt files (one
``<frame>.txt`` a frame, 16 fields a line; KITTI's server wants them at the zip's root), a folder of them, or
a result pickle (any layout :func:`kitti_eval.io.loaders.load_detections` reads). :func:`validate_submission`
lists every problem it finds, one sentence each, so that a participant can fix them all at once; the command
line (``kitti-eval validate``) and the service say exactly these sentences.

What is checked: every test frame present exactly once (the missing and the extra ones named), every line of
16 fields whose numbers parse and are finite, every class name one of KITTI's, at most a bounded number of
boxes a frame. Not checked: sizes, since the devkit reads any (:func:`kitti_eval.core.frames.unsized_boxes`).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..errors import InputError, InvalidSubmissionError
from .archives import ArchiveLimits
from .submission_rules import (
    KITTI_RESULT_CLASSES,
    SubmissionRules,
    Validation,
    validate_annotations,
    validate_txt_folder,
)
from .upload import UploadLimits, read_upload

__all__ = [
    "KITTI_RESULT_CLASSES",
    "SubmissionRules",
    "Validation",
    "validate_submission",
    "validate_annotations",
    "validate_txt_folder",
]


def validate_submission(
    path: str | os.PathLike[str],
    rules: SubmissionRules,
    *,
    limits: ArchiveLimits | None = None,
) -> Validation:
    """Every problem of the submission at ``path`` (a zip or tar of KITTI result txt files, a folder of them,
    or a result pickle) against ``rules``: a file is read and checked as the service reads and checks an upload
    (:func:`kitti_eval.io.upload.read_upload`).

    Unsafe or unreadable input (an unsafe pickle, an archive over the limits, a file of another format) is
    not a problem to list: it raises :class:`~kitti_eval.errors.InputError` as every loader does.
    """
    p = Path(path)
    if p.is_dir():
        return validate_txt_folder(p, rules)
    upload_limits = UploadLimits()
    if limits is not None:
        upload_limits = UploadLimits(
            max_bytes=limits.max_unpacked_bytes,
            max_members=limits.max_members,
            bytes_setting=limits.bytes_setting,
            members_setting=limits.members_setting,
        )
    try:
        fh = open(p, "rb")
    except OSError as e:
        raise InputError(f"cannot read {path}: {e.strerror or e}") from None
    with fh, tempfile.TemporaryDirectory(prefix="kitti-eval-submission-") as tmp:
        try:
            read = read_upload(fh, "detections", source=str(path), scratch=Path(tmp), limits=upload_limits, rules=rules)
        except InvalidSubmissionError as e:
            return Validation(problems=e.problems, more=e.more)
    assert read.validation is not None
    return read.validation
