"""Every entry point shares one compiled version of each kernel: once warm, nothing compiles again."""

from __future__ import annotations

import gzip
import importlib
import io
import pkgutil
from pathlib import Path

import numba
import pytest
from numba.core import event

import kitti_eval
from kitti_eval import _jit
from kitti_eval.demo import demo_paths
from kitti_eval.io.safe_pickle import load_pickle


class _Compiles(event.Listener):
    """The kernels numba compiles (a cache hit is not a compile)."""

    def __init__(self) -> None:
        self.names: list[str] = []

    def on_start(self, ev: event.Event) -> None:
        self.names.append(ev.data["dispatcher"].py_func.__qualname__)

    def on_end(self, ev: event.Event) -> None:
        pass


def _entry_points(tmp_path: Path) -> None:
    """Each public entry point once, on the bundled demo (the first ten frames where the work is heavy)."""
    from kitti_eval import cli, evaluate, get_official_eval_result, load_detections, load_ground_truth
    from kitti_eval.analysis.batch import evaluate_many
    from kitti_eval.analysis.bootstrap import paired_bootstrap
    from kitti_eval.analysis.diagnostics import frame_stats
    from kitti_eval.analysis.inspection import inspect_frame
    from kitti_eval.io.describe import describe

    gt_path, pred_path = demo_paths()
    gt, dt = load_ground_truth(gt_path), load_detections(pred_path)
    evaluate(gt, dt)
    infos = load_pickle(gt_path, source="infos")
    results = load_pickle(pred_path, source="results")
    get_official_eval_result([i["annos"] for i in infos[:10]], results[:10], ["Car", "Pedestrian", "Cyclist"])
    evaluate_many(gt, [pred_path, pred_path])
    paired_bootstrap(gt, dt, dt, resamples=3)
    frame_stats(gt, dt)
    inspect_frame(gt, [("a", dt), ("b", dt)], gt.frame_ids[3])
    describe(pred_path, gt=gt_path)
    assert (
        cli.main(
            [
                "--gt",
                str(gt_path),
                "--pred",
                str(pred_path),
                "--format",
                "json",
                "--output",
                str(tmp_path / "out.json"),
                "--quiet",
            ]
        )
        == 0
    )
    with gzip.open(pred_path) as fh:
        load_pickle(io.BytesIO(fh.read()), source="upload")  # the service's path: a file object
    _jit.warm_up()  # the service's warm-up


def _dispatchers() -> list[numba.core.registry.CPUDispatcher]:
    found = []
    for info in pkgutil.walk_packages(kitti_eval.__path__, "kitti_eval."):
        module = importlib.import_module(info.name)
        found += [
            v
            for v in vars(module).values()
            if isinstance(v, numba.core.registry.CPUDispatcher) and v.py_func.__module__ == info.name
        ]
    return found


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_entry_points_compile_nothing_once_warm(tmp_path: Path) -> None:
    _jit.warm_up()
    compiles = _Compiles()
    with event.install_listener("numba:compile", compiles):
        _entry_points(tmp_path)
    assert compiles.names == []
    kernels = _dispatchers()
    assert len(kernels) > 20
    several = {d.py_func.__qualname__: [str(s) for s in d.signatures] for d in kernels if len(d.signatures) > 1}
    assert several == {}  # one compiled version of every kernel


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_the_listener_sees_a_compile() -> None:
    """The check above can fail: a kernel that is not in the cache is compiled and counted."""

    @numba.njit
    def twice(x):  # noqa: ANN001, ANN202
        return 2 * x

    compiles = _Compiles()
    with event.install_listener("numba:compile", compiles):
        assert twice(21) == 42
        assert twice(21) == 42  # compiled once, then reused
    assert compiles.names == [twice.py_func.__qualname__]


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: no dispatchers")
@pytest.mark.parametrize("marker", ["eval", "load"])
def test_cache_markers_name_existing_kernels(marker: str) -> None:
    """The files the CLI looks for to decide whether it compiles are written for kernels that exist."""
    markers = _jit._EVAL_MARKERS if marker == "eval" else _jit._LOAD_MARKERS
    names = {f"{d.py_func.__module__.split('.')[-1]}.{d.py_func.__name__}" for d in _dispatchers()}
    for m in markers:
        assert m.split("-")[0] in names
