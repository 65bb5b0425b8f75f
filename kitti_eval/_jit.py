"""Whether numba's on-disk cache already holds the evaluation kernels (so the CLI can say when it compiles)."""

from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
#: the kernels every evaluation calls; if their cache index is there, the others are too
_MARKERS = ("matching._pr_counts-*.nbi", "geometry._frame_overlaps*-*.nbi")


def kernels_cached() -> bool:
    """True when numba's cache index files for the main kernels exist (in-tree or under NUMBA_CACHE_DIR)."""
    places = [_PACKAGE / "__pycache__"]
    custom = os.environ.get("NUMBA_CACHE_DIR")
    if custom:
        places.insert(0, Path(custom))
    for marker in _MARKERS:
        found = False
        for place in places:
            if not place.is_dir():
                continue
            if any(place.glob(marker)) or (place != places[-1] and any(place.glob(f"**/{marker}"))):
                found = True
                break
        if not found:
            return False
    return True
