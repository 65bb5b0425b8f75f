"""The sharded evaluation's speed benchmark: time and peak memory of ``kitti-eval --sharded`` per scale.

    python -m kitti_eval.speed_sharded                          # 1x and 10x KITTI val, in process
    python -m kitti_eval.speed_sharded --scales 1,10,100 --cluster local:2

Each scale is a generated set of ``k`` shards of KITTI val's size (3769 frames, ~8 ground-truth boxes
and ~40 detections a frame each; frame ids continue across shards), written by a child process as
OpenPCDet infos/result pickles. The whole CLI runs in a fresh child; its peak RSS is the largest of that
process and (with a local cluster) its workers. Time is checked against linear in frames: the 10x and
100x runs take at most 1.2x their share of the 1x time. Exit status 3 when a target is not met.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]

VAL_FRAMES = 3769
#: peak RSS of the process (and of each worker) for the largest scale, MiB; time against linear
TARGETS = {"rss_in_process_mib": 3072.0, "rss_cluster_mib": 2048.0, "linear_ratio": 1.2}


def _write_shards(directory: Path, shards: int) -> None:
    """``shards`` KITTI-val-sized shards: ``gt-K.pkl`` and ``pred-K.pkl``, frame ids continuing."""
    from .synth import generate, write_infos, write_results

    for k in range(shards):
        infos, results = generate(VAL_FRAMES, seed=1000 + k, dets_per_frame=40.0, gt_per_frame=8.0)
        first = k * VAL_FRAMES
        for i, info in enumerate(infos):
            idx = f"{first + i:06d}"
            info["image"]["image_idx"] = idx
            info["point_cloud"]["lidar_idx"] = idx
        for i, r in enumerate(results):
            r["frame_id"] = f"{first + i:06d}"
        write_infos(directory / f"gt-{k:03d}.pkl", infos)
        write_results(directory / f"pred-{k:03d}.pkl", results)


def _run(directory: Path, cluster: str | None) -> tuple[float, float]:
    argv = [sys.executable, "-m", "kitti_eval.cli", "--gt", str(directory / "gt-*.pkl")]
    argv += ["--pred", str(directory / "pred-*.pkl"), "--sharded", "--format", "json", "--quiet"]
    if cluster:
        argv += ["--cluster", cluster]
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"kitti-eval failed on {directory}")
    return wall, usage.ru_maxrss / 1024


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m kitti_eval.speed_sharded",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scales", default="1,10", help="sets of K val-sized shards, e.g. 1,10,100")
    p.add_argument("--cluster", help="also run on this Dask cluster, e.g. local:2")
    p.add_argument("--write", nargs=2, metavar=("DIR", "K"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.write:
        _write_shards(Path(args.write[0]), int(args.write[1]))
        return 0
    scales = [int(s) for s in args.scales.split(",") if s.strip()]
    modes: list[str | None] = [None] + ([args.cluster] if args.cluster else [])
    rows: dict[tuple[int, str | None], tuple[float, float]] = {}
    with tempfile.TemporaryDirectory(prefix="kitti_eval_speed_sharded_") as tmp_name:
        for k in scales:
            d = Path(tmp_name) / f"x{k}"
            d.mkdir()
            t = time.perf_counter()
            # written by a child: a child forked from a big process starts with its peak RSS
            subprocess.run([sys.executable, "-m", "kitti_eval.speed_sharded", "--write", str(d), str(k)], check=True)
            print(f"generated {k} shards ({k * VAL_FRAMES} frames) in {time.perf_counter() - t:.1f} s", file=sys.stderr)
            for mode in modes:
                rows[(k, mode)] = _run(d, mode)
            for f in d.iterdir():
                f.unlink()
    print(f"{'frames':>8} {'shards':>6} {'where':<12} {'wall s':>8} {'s / 1k frames':>13} {'peak RSS MiB':>12}")
    for (k, mode), (wall, rss) in rows.items():
        where = mode or "in process"
        print(
            f"{k * VAL_FRAMES:>8} {k:>6} {where:<12} {wall:>8.1f} {1000 * wall / (k * VAL_FRAMES):>13.3f} {rss:>12.0f}"
        )
    ok = True
    base = min(scales)
    for mode in modes:
        for k in scales:
            if k == base:
                continue
            ratio = rows[(k, mode)][0] / (rows[(base, mode)][0] * k / base)
            good = ratio <= TARGETS["linear_ratio"]
            ok &= good
            print(f"  {'met' if good else 'NOT MET':<8} {k}x {mode or 'in process'}: time / linear = {ratio:.2f}")
    top = max(scales)
    limits: list[tuple[str | None, float]] = [(None, TARGETS["rss_in_process_mib"])]
    if args.cluster:
        limits.append((args.cluster, TARGETS["rss_cluster_mib"]))
    for mode, limit in limits:
        if (top, mode) in rows:
            good = rows[(top, mode)][1] <= limit
            ok &= good
            print(f"  {'met' if good else 'NOT MET':<8} {top}x {mode or 'in process'}: peak RSS <= {limit:.0f} MiB")
    return 0 if ok else 3


if __name__ == "__main__":
    sys.exit(main())
