"""The data folder must be one this process may write: checked once at start, before anything is put there."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import StartupRefused

__all__ = ["check_writable"]


def check_writable(folder: Path, setting: str = "KITTI_EVAL_DATA_DIR") -> None:
    """Create ``folder`` if needed and write a file in it; where that fails (a volume owned by another uid, a
    read-only mount), raise :class:`StartupRefused` with one sentence naming the folder, this process's uid
    and gid, and the fix, instead of the ``PermissionError`` of whichever part first wrote there."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-check-"):
            pass
    except OSError as e:
        uid, gid = os.getuid(), os.getgid()
        reason = e.strerror or type(e).__name__
        raise StartupRefused(
            f"the data folder {folder} cannot be written by uid {uid} (gid {gid}): {reason}; give the service a "
            f"folder or volume this uid may write (chown {uid}:{gid} it, or in Kubernetes set the pod's "
            f"securityContext.fsGroup to {gid}), or point {setting} at one"
        ) from None
