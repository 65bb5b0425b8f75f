"""The client's own files (the tokens ``kitti-eval login`` saves, the keys of submissions not yet shown scored):
written whole or not at all, readable by their owner only, whatever was left or planted beside them.

A file is written to a temporary file that :func:`tempfile.mkstemp` makes (``O_CREAT | O_EXCL``, mode 0600: a
name that exists, a symlink included, is never opened), made 0600 again with ``fchmod`` before anything is
written (a umask or an ACL cannot widen it), flushed, then renamed over the file."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["private_folder", "write_private_json"]


def private_folder(folder: Path) -> Path:
    """``folder``, made when missing (readable by its owner only when made here)."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    return folder


def write_private_json(path: Path, data: Any) -> Path:
    """Writes ``data`` as JSON to ``path``, readable and writable by its owner only; returns ``path``."""
    private_folder(path.parent)
    fd, partial = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            json.dump(data, out, indent=2)
            out.flush()
            os.fsync(out.fileno())
        os.replace(partial, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise
    return path
