"""numba's on-disk cache: whether it holds the kernels (so the CLI can say when it compiles), and warming it.

Every entry point (the CLI, ``evaluate``, the OpenPCDet drop-in, batch, compare/bootstrap, frames,
inspect, the service) calls the same kernels with the same argument types: the wrappers cast every input
to one dtype and layout before a kernel sees it (:func:`kitti_eval.core.arrays.kernel_input`), so each
kernel is compiled once and cached once. :func:`warm_up` compiles (or loads) all of them.

This module sits above everything it warms: it imports the layers (``core``, ``io``, ``analysis``) and
none of them imports it; the CLI and the service call it. ``python -m kitti_eval._jit [--all]`` warms from
the command line.

numba keeps a compiled kernel for one source file's folder (by its absolute path), one numba and Python
version and one CPU (model and features), and stamps it with the content of the kernel's module and of every
module it imports (:mod:`kitti_eval.core.kernel_cache`). :func:`cache_key` names exactly that, so a CI
job can keep ``NUMBA_CACHE_DIR`` between runs and restore it only where every kernel in it is valid
(``python -m kitti_eval._jit --cache-key``).

A platform wheel (``scripts/build_wheel.py``) carries the kernels compiled for a generic CPU, which
:mod:`kitti_eval.core.kernel_cache` loads where numba's own cache has none: such an installation compiles
nothing on first use, and :func:`kernels_cached` counts them.

A first run compiles two groups: the restricted unpickler's scan (needed to load the inputs) and the
evaluation kernels. On two or more cores :func:`warm_in_background` compiles the second group in another
process while this one compiles the first, so a fresh install pays roughly the larger of the two.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import pickle
import platform
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
#: kernels every evaluation calls; if their cache index is there, the others of their group are too
_EVAL_MARKERS = ("matching._pass2-*.nbi", "geometry._frame_overlaps_kernel-*.nbi")
_LOAD_MARKERS = ("_pickle_scan.scan-*.nbi",)
_DECOMPOSITION_MARKERS = ("decomposition._tp_error_events-*.nbi",)


def _cache_places() -> list[tuple[Path, str]]:
    """Where this package's kernels are kept, as (folder, glob pattern of a marker below it) pairs: numba's
    places in numba's order, then the kernels a platform wheel ships when this process can use them."""
    custom = os.environ.get("NUMBA_CACHE_DIR")
    if custom:
        places = [(Path(custom), "**/{}")]
    else:
        # the package and its sub-packages keep their own __pycache__
        places = [(_PACKAGE, "**/__pycache__/{}")]
        user = _user_cache()
        if user is not None:
            places.append((user, "**/{}"))
    from .core.kernel_cache import shipped_kernels

    shipped = shipped_kernels()
    if shipped is not None:
        from numba.core.registry import cpu_target

        if shipped.usable_on(cpu_target.target_context.codegen().magic_tuple()):
            places.append((shipped.root, "**/{}"))
    return places


def _user_cache() -> Path | None:
    """numba's user-wide cache (``$XDG_CACHE_HOME/numba``, else ``~/.cache/numba``), or None where there is no
    home to find it in (``env -i``, a uid without an entry in /etc/passwd): nothing is kept there then."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and os.path.isabs(xdg):
        return Path(xdg) / "numba"
    home = os.path.expanduser("~")
    return Path(home) / ".cache" / "numba" if os.path.isabs(home) else None


def _cached(markers: tuple[str, ...]) -> bool:
    places = _cache_places()
    for marker in markers:
        if not any(place.is_dir() and any(place.glob(pattern.format(marker))) for place, pattern in places):
            return False
    return True


def kernels_cached() -> bool:
    """True when numba's cache index files for the evaluation kernels exist."""
    return _cached(_EVAL_MARKERS)


def loader_cached() -> bool:
    """True when the restricted unpickler's scan is in numba's cache."""
    return _cached(_LOAD_MARKERS)


def decomposition_cached() -> bool:
    """True when the error decomposition's kernels (kitti-eval errors) are in numba's cache."""
    return _cached(_DECOMPOSITION_MARKERS)


def cache_key() -> str:
    """A name for numba's cache of this installation's kernels that changes whenever a cached kernel would
    not be used: ``kitti-eval-<version>-numba-<version>-py<version>-<digest>``, the digest over the package's
    sources (their content and where they are installed: numba's cache folders are named after the source
    folder's path) and the CPU numba compiles for (target, model, features; ``NUMBA_CPU_NAME`` counts)."""
    import numba
    from numba.core.registry import cpu_target

    from . import __version__

    digest = hashlib.sha256()
    digest.update(repr(cpu_target.target_context.codegen().magic_tuple()).encode())
    digest.update(str(_PACKAGE).encode())
    for source in sorted(_PACKAGE.rglob("*.py")):
        digest.update(b"\0" + source.relative_to(_PACKAGE).as_posix().encode() + b"\0" + source.read_bytes())
    return f"kitti-eval-{__version__}-numba-{numba.__version__}-py{platform.python_version()}-{digest.hexdigest()[:16]}"


@contextlib.contextmanager
def compilations() -> Iterator[list[str]]:
    """The qualified names of the kernels numba compiles while the block runs (numba's compile events): what
    the tests and the wheel's scripts count to show that a cache was used."""
    from numba.core import event

    compiled: list[str] = []

    class _Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            compiled.append(ev.data["dispatcher"].py_func.__qualname__)

        def on_end(self, ev: event.Event) -> None:
            pass

    with event.install_listener("numba:compile", _Listener()):
        yield compiled


def warm_in_background(*, loader: bool = False) -> subprocess.Popen[bytes] | None:
    """Start compiling the evaluation kernels in a child process (``loader``: the pickle scan too, which a run
    reading only txt files never compiles itself); None on a single core."""
    if (os.cpu_count() or 1) < 2:
        return None
    try:
        return subprocess.Popen(
            [sys.executable, "-m", "kitti_eval._jit", *(["--loader"] if loader else [])],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError:
        return None


def warm_up(everything: bool = True, *, loader: bool = False) -> None:
    """Compile (or load from the cache) the kernels: those an evaluation calls, and with ``everything``
    those of every other entry point too (the pickle scan, per-frame events and the bootstrap, the frame
    labels, the IoU functions). A tiny generated scene has the array types of every real input."""
    from .core.evaluation import evaluate
    from .core.frames import Annotations
    from .synth import generate

    infos, results = generate(4, seed=0)
    gt = Annotations.from_frames("ground_truth", "warm-up", [(i["image"]["image_idx"], i["annos"]) for i in infos])
    dt = Annotations.from_frames("detections", "warm-up", [(r["frame_id"], r) for r in results])
    evaluate(gt, dt)
    if loader and not everything:
        from .io.safe_pickle import load_pickle

        load_pickle(io.BytesIO(pickle.dumps(results, protocol=4)), source="warm-up")
    if not everything:
        return
    from .analysis.bootstrap import paired_bootstrap
    from .analysis.decomposition import decompose
    from .analysis.diagnostics import frame_stats
    from .analysis.inspection import inspect_frame
    from .core.geometry import iou_2d, iou_3d, iou_bev
    from .io.safe_pickle import load_pickle

    load_pickle(io.BytesIO(pickle.dumps(results, protocol=4)), source="warm-up")
    paired_bootstrap(gt, dt, dt, resamples=2)
    frame_stats(gt, dt)
    decompose(gt, dt)
    inspect_frame(gt, [("warm-up", dt)], gt.frame_ids[0])
    boxes = gt.boxes_camera[:2]
    iou_2d(gt.bbox[:2], gt.bbox[:2])
    iou_bev(boxes, boxes)
    iou_3d(boxes, boxes)


if __name__ == "__main__":
    if "--cache-key" in sys.argv[1:]:
        print(cache_key())  # noqa: T201
    else:
        warm_up(everything="--all" in sys.argv[1:], loader="--loader" in sys.argv[1:])
