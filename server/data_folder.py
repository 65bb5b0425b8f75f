"""The data folder must be one this process may write: checked once at start, before anything is put there."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["check_writable", "private_files"]


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
        from .errors import StartupRefused  # here: ``kitti-eval serve`` imports this module before FastAPI

        uid, gid = os.getuid(), os.getgid()
        reason = e.strerror or type(e).__name__
        what = f"the data folder {folder}" if place == folder else f"{place} in the data folder"
        # the folder to give the uid: this one, or, where it could not be made, the nearest that exists (os.path's
        # exists: a folder the uid may not even look into is not one it could be told to fix, and raises no error)
        target = next((p for p in (place, *place.parents) if os.path.exists(p)), place)
        mine = "it" if target == place else str(target)
        raise StartupRefused(
            f"{what} cannot be written by uid {uid} (gid {gid}): {reason}; give the service a "
            f"folder or volume this uid may write (chown {uid}:{gid} {mine}, or in Kubernetes set the pod's "
            f"securityContext.fsGroup to {gid}), or point {setting} at one"
        ) from None


@contextlib.contextmanager
def private_files() -> Iterator[None]:
    """While it lasts, what this process makes (the database, the unpacked ground truths, sealed ones among them,
    backups, scratch files) is not readable by other users: the umask gains ``007``, whatever it was (a umask of
    022 made them 0644 in 0755 folders, so any local user of a shared host read the sealed labels). The group's
    permissions stay as the umask gives them: the image's ``/data`` is the root group's, which OpenShift's random
    uids belong to. ``kitti-eval serve``, ``worker`` and ``admin`` run in it; the umask is given back after."""
    before = os.umask(0o077)
    os.umask(before | 0o007)
    try:
        yield
    finally:
        os.umask(before)
