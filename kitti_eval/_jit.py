"""Whether numba's on-disk cache already holds the evaluation kernels (so the CLI can say when it compiles)."""

from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
#: the kernels every evaluation calls; if their cache index is there, the others are too
_MARKERS = ("matching._pr_counts_many-*.nbi", "geometry._frame_overlaps_kernel-*.nbi")


def _cache_places() -> list[tuple[Path, bool]]:
    """Where numba keeps this package's cache, as (folder, search below it) pairs, in numba's order."""
    custom = os.environ.get("NUMBA_CACHE_DIR")
    if custom:
        return [(Path(custom), True)]
    user = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "numba"
    return [(_PACKAGE / "__pycache__", False), (user, True)]


def kernels_cached() -> bool:
    """True when numba's cache index files for the main kernels exist."""
    for marker in _MARKERS:
        if not any(place.is_dir() and any(place.glob(f"**/{marker}" if deep else marker))
                   for place, deep in _cache_places()):
            return False
    return True
