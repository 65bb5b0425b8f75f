"""numba's on-disk cache: whether it holds the kernels (so the CLI can say when it compiles), and warming it.

A first run compiles two groups of kernels: the restricted unpickler's scanner (needed to load the
inputs) and the evaluation kernels. On two or more cores :func:`warm_in_background` compiles the second
group in another process while this one compiles the first, so a fresh install pays roughly the larger
of the two instead of their sum.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
#: kernels every evaluation calls; if their cache index is there, the others of their group are too
_EVAL_MARKERS = ("matching._pass2-*.nbi", "geometry._frame_overlaps_kernel-*.nbi")
_LOAD_MARKERS = ("_pickle_scan.scan-*.nbi",)


def _cache_places() -> list[tuple[Path, bool]]:
    """Where numba keeps this package's cache, as (folder, search below it) pairs, in numba's order."""
    custom = os.environ.get("NUMBA_CACHE_DIR")
    if custom:
        return [(Path(custom), True)]
    user = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "numba"
    return [(_PACKAGE / "__pycache__", False), (user, True)]


def _cached(markers: tuple[str, ...]) -> bool:
    for marker in markers:
        if not any(place.is_dir() and any(place.glob(f"**/{marker}" if deep else marker))
                   for place, deep in _cache_places()):
            return False
    return True


def kernels_cached() -> bool:
    """True when numba's cache index files for the evaluation kernels exist."""
    return _cached(_EVAL_MARKERS)


def loader_cached() -> bool:
    """True when the restricted unpickler's scanner is in numba's cache."""
    return _cached(_LOAD_MARKERS)


def warm_in_background() -> subprocess.Popen[bytes] | None:
    """Start compiling the evaluation kernels in a child process; None on a single core."""
    if (os.cpu_count() or 1) < 2:
        return None
    try:
        return subprocess.Popen([sys.executable, "-m", "kitti_eval._jit"], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


def _warm() -> None:
    """Evaluate a tiny generated scene: it has the array types of every real input, so the kernels
    compiled here are the ones a real evaluation loads from the cache."""
    from .evaluation import evaluate
    from .frames import Annotations
    from .synth import generate

    infos, results = generate(4, seed=0)
    gt = Annotations.from_frames("ground_truth", "warm-up", [(i["image"]["image_idx"], i["annos"]) for i in infos])
    dt = Annotations.from_frames("detections", "warm-up", [(r["frame_id"], r) for r in results])
    evaluate(gt, dt)


if __name__ == "__main__":
    _warm()
