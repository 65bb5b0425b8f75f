"""The data folder must be one this process may write: checked once at start, before anything is put there."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import StartupRefused

__all__ = ["check_writable"]


#: the folders under the data folder the service writes to (scratch space, its locks, unpacked ground truths):
#: a volume another uid used before may hold them with that uid's permissions
SUBFOLDERS = ("tmp", "run", "ground-truths")


def check_writable(folder: Path, setting: str = "KITTI_EVAL_DATA_DIR") -> None:
    """Create ``folder`` and its :data:`SUBFOLDERS` if needed and write a file in each; where that fails (a volume
    owned by another uid, a read-only mount, a subfolder an earlier uid made), raise :class:`StartupRefused` with
    one sentence naming the folder, this process's uid and gid, and the fix, instead of the ``PermissionError`` of
    whichever part first wrote there."""
    for place in (folder, *(folder / name for name in SUBFOLDERS)):
        _check(place, folder, setting)


def _check(place: Path, folder: Path, setting: str) -> None:
    try:
        place.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=place, prefix=".write-check-"):
            pass
    except OSError as e:
        uid, gid = os.getuid(), os.getgid()
        reason = e.strerror or type(e).__name__
        what = f"the data folder {folder}" if place == folder else f"{place} in the data folder"
        raise StartupRefused(
            f"{what} cannot be written by uid {uid} (gid {gid}): {reason}; give the service a "
            f"folder or volume this uid may write (chown {uid}:{gid} it, or in Kubernetes set the pod's "
            f"securityContext.fsGroup to {gid}), or point {setting} at one"
        ) from None
