"""The speed benchmark: time and peak memory per stage and for the whole CLI, against the project's targets.

    python -m kitti_eval.speed                        # golden KITTI-val-sized set if found, generated 1x and 10x
    python -m kitti_eval.speed --scales 1 --repeat 3  # quicker

Every measurement runs in a fresh child process, so peak RSS belongs to one input. Figures printed:

* stages of one evaluation in a warm process: load (ground truth, predictions), overlaps, matching, AP,
  output; the warm evaluation on all cores and on one;
* the whole ``kitti-eval --format json`` process with numba's cache warm (median of ``--repeat``) and
  once with an empty cache (a fresh install: wall and CPU seconds, the CPU of the process that compiles
  the evaluation kernels beside it included), with its peak RSS; the same for ``kitti-eval demo``; and
  what each group of kernels costs to compile on its own (the pickle loader's scan, the evaluation kernels);
* the cost of 10x the frames relative to 1x.

Exit status 0 when every target below is met, 3 when one is not (the lines marked NOT MET).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]

#: (what, limit, unit) -- the targets this benchmark checks
TARGETS = {
    "warm_eval_s": 0.15,
    "cli_warm_s": 1.2,
    "cli_cold_s": 8.0,
    "cli_cold_cpu_s": 15.0,
    "peak_rss_mib": 350.0,
    "scale_ratio": 11.0,
}
VAL_FRAMES = 3769
GOLDEN_DEFAULT = Path("..") / "shared" / "golden" / "cases" / "kitti_val_scale"


def _peak_rss_mib() -> float:
    """This process's peak resident set (VmHWM; unlike ru_maxrss it is not inherited from a parent)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # pragma: no cover - not Linux
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cli_child(gt_path: str, pred_path: str) -> int:
    """Run the CLI in this process as the console script does (``kitti_eval.cli.entry``: main, then exit
    without interpreter teardown), reporting its peak RSS on stderr just before leaving."""
    from .cli import main as cli_main

    code = cli_main(["--gt", gt_path, "--pred", pred_path, "--format", "json", "--output", os.devnull, "--quiet"])
    sys.stderr.write(f"\nPEAK_RSS_MIB {_peak_rss_mib():.1f}\n")
    sys.stderr.flush()
    os._exit(code)


def _child(gt_path: str, pred_path: str, repeat: int) -> dict[str, float]:
    """Measure the stages in this process; returns seconds and MiB."""
    out: dict[str, float] = {}
    clock = time.perf_counter
    t = clock()
    from .core.evaluation import evaluate
    from .io.loaders import load_detections, load_ground_truth
    from .report.render import render_json

    out["import_s"] = clock() - t
    t = clock()
    gt = load_ground_truth(gt_path)
    out["load_gt_s"] = clock() - t
    t = clock()
    dt = load_detections(pred_path)
    out["load_pred_s"] = clock() - t
    out["rss_after_load_mib"] = _peak_rss_mib()
    t = clock()
    result = evaluate(gt, dt)
    out["first_eval_s"] = clock() - t  # includes loading the cached kernels
    runs = []
    for _ in range(repeat):
        t = clock()
        result = evaluate(gt, dt)
        runs.append((clock() - t, result.timings))
    best = min(runs, key=lambda r: r[0])
    out["warm_eval_s"] = best[0]
    for stage, seconds in best[1].items():
        out[f"stage_{stage}_s"] = seconds
    t = clock()
    render_json(result)
    out["output_s"] = clock() - t
    out["rss_after_eval_mib"] = _peak_rss_mib()
    from .core.cpus import default_workers

    out["warm_eval_1core_s"] = min(_timed(lambda: evaluate(gt, dt, workers=1)) for _ in range(repeat))
    out["threads"] = default_workers()
    out["frames"] = gt.num_frames
    out["gt_boxes"] = gt.num_boxes
    out["pred_boxes"] = dt.num_boxes
    out["peak_rss_mib"] = _peak_rss_mib()
    return out


def _timed(fn) -> float:  # noqa: ANN001
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def _run_child(gt: Path, pred: Path, repeat: int) -> dict[str, float]:
    proc = subprocess.run(
        [sys.executable, "-m", "kitti_eval.speed", "--child", str(gt), str(pred), "--repeat", str(repeat)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark child failed: {proc.stderr.strip()[-2000:]}")
    return json.loads(proc.stdout)


def _timed_child(argv: list[str], env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """Wall seconds, CPU seconds (user + system, its own children included) and stderr of one process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True, check=False)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[:4])} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, proc.stderr


def _cli_once(gt: Path, pred: Path, env: dict[str, str] | None = None) -> tuple[float, float, float]:
    """Wall seconds, peak RSS (MiB) and CPU seconds of one ``kitti-eval --format json`` process."""
    wall, cpu, err = _timed_child([sys.executable, "-m", "kitti_eval.speed", "--cli-child", str(gt), str(pred)], env)
    peak = [float(line.split()[1]) for line in err.splitlines() if line.startswith("PEAK_RSS_MIB")]
    return wall, peak[0], cpu


def _cold(tmp: Path, gt: Path, pred: Path) -> dict[str, tuple[float, float]]:
    """(wall, CPU seconds) of first runs, each with an empty numba cache."""
    out = {}
    runs = {
        "kitti-eval --format json": None,
        "kitti-eval demo": [sys.executable, "-m", "kitti_eval.cli", "demo", "--format", "json"],
        "compile the pickle loader only": [
            sys.executable,
            "-c",
            f"from kitti_eval.io.safe_pickle import load_pickle; load_pickle({str(pred)!r}, source='bench')",
        ],
        "compile the evaluation kernels only": [sys.executable, "-m", "kitti_eval._jit"],
    }
    for k, (what, argv) in enumerate(runs.items()):
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / f"empty_numba_cache_{k}"))
        if argv is None:
            wall, _, cpu = _cli_once(gt, pred, env)
        else:
            wall, cpu, _ = _timed_child(argv, env)
        out[what] = (wall, cpu)
    return out


def _generate(directory: Path, frames: int, seed: int) -> tuple[Path, Path]:
    """A KITTI-val-like set (~8 ground-truth boxes and ~40 detections a frame), written by a child process."""
    subprocess.run(
        [
            sys.executable,
            "-m",
            "kitti_eval.synth",
            "--frames",
            str(frames),
            "--seed",
            str(seed),
            "--dets-per-frame",
            "40",
            "--gt-per-frame",
            "8",
            "--out",
            str(directory),
        ],
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return directory / "kitti_infos_val.pkl", directory / "result.pkl"


def _golden_inputs(case: Path, tmp: Path) -> tuple[Path, Path] | None:
    """The golden set's pickles, uncompressed into ``tmp`` if they are stored gzipped."""
    import gzip
    import shutil

    paths = []
    for base in ("kitti_infos_val.pkl", "result.pkl"):
        plain, packed = case / base, case / f"{base}.gz"
        if plain.exists():
            paths.append(plain)
        elif packed.exists():
            out = tmp / f"golden_{base}"
            with gzip.open(packed, "rb") as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst)
            paths.append(out)
        else:
            return None
    return paths[0], paths[1]


def _fmt_row(name: str, m: dict[str, float]) -> str:
    return (
        f"{name:<18} {m['frames']:>7.0f} {m['pred_boxes']:>9.0f} {m['load_gt_s'] + m['load_pred_s']:>7.3f} "
        f"{m['stage_overlaps_s']:>8.3f} {m['stage_matching_s']:>8.3f} {m['stage_ap_s']:>6.3f} "
        f"{m['output_s']:>6.3f} {m['warm_eval_s']:>8.3f} {m['warm_eval_1core_s']:>8.3f} "
        f"{m['peak_rss_mib']:>8.1f}"
    )


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT MET"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m kitti_eval.speed", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--golden",
        type=Path,
        default=GOLDEN_DEFAULT,
        help=f"a golden case folder to include (default {GOLDEN_DEFAULT}, skipped if absent)",
    )
    p.add_argument("--scales", default="1,10", help="generated sets, in multiples of KITTI val's 3769 frames")
    p.add_argument("--repeat", type=int, default=5, help="repetitions of each warm measurement (best/median)")
    p.add_argument("--no-cold", action="store_true", help="skip the empty-cache (first run) measurement")
    p.add_argument(
        "--sharded",
        action="store_true",
        help="instead: kitti-eval --sharded on sets of K val-sized shards (python -m kitti_eval.speed_sharded)",
    )
    p.add_argument("--cluster", help="with --sharded: also on this Dask cluster, e.g. local:2")
    p.add_argument("--child", nargs=2, metavar=("GT", "PRED"), help=argparse.SUPPRESS)
    p.add_argument("--cli-child", nargs=2, metavar=("GT", "PRED"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.sharded:
        from .speed_sharded import main as sharded_main

        return sharded_main(["--scales", args.scales] + (["--cluster", args.cluster] if args.cluster else []))
    if args.cli_child:
        return _cli_child(*args.cli_child)
    if args.child:
        print(json.dumps(_child(args.child[0], args.child[1], args.repeat)))
        return 0

    scales = [int(s) for s in args.scales.split(",") if s.strip()]
    report: dict[str, dict[str, float]] = {}
    cli: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory(prefix="kitti_eval_bench_") as tmp_name:
        tmp = Path(tmp_name)
        inputs: list[tuple[str, Path, Path]] = []
        golden = _golden_inputs(args.golden, tmp) if args.golden.is_dir() else None
        if golden:
            inputs.append(("golden val-sized", *golden))
        for k in scales:
            d = tmp / f"x{k}"
            d.mkdir()
            t = time.perf_counter()
            inputs.append((f"generated {k}x", *_generate(d, VAL_FRAMES * k, seed=k)))
            print(f"generated {VAL_FRAMES * k} frames in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        _cli_once(*inputs[0][1:])  # make sure numba's cache is warm
        for name, gt, pred in inputs:
            report[name] = _run_child(gt, pred, args.repeat)
            runs = [_cli_once(gt, pred) for _ in range(max(1, args.repeat))]
            cli[name] = (statistics.median(r[0] for r in runs), max(r[1] for r in runs))
        cold = None if args.no_cold else _cold(tmp, inputs[0][1], inputs[0][2])

    print(
        "Stages of one evaluation (seconds; the load and stages in a warm process, best of "
        f"{args.repeat}; RSS = peak of the process, MiB)"
    )
    print(
        f"{'input':<18} {'frames':>7} {'pred box':>9} {'load':>7} {'overlaps':>8} {'matching':>8} {'AP':>6} "
        f"{'output':>6} {'eval':>8} {'eval 1c':>8} {'peak RSS':>8}"
    )
    for name, m in report.items():
        print(_fmt_row(name, m))
    print()
    print(f"Whole 'kitti-eval --format json' process, numba cache warm (median of {max(1, args.repeat)}):")
    for name, (wall, rss) in cli.items():
        print(f"  {name:<18} {wall:6.2f} s   peak RSS {rss:7.1f} MiB")
    if cold:
        print(f"First runs with an empty numba cache ({inputs[0][0]}; CPU includes the compiling helper process):")
        for what, (wall, cpu) in cold.items():
            print(f"  {what:<36} {wall:6.2f} s wall {cpu:6.2f} s CPU")
    print()

    ref_name = inputs[0][0]
    ref = report[ref_name]
    threads = int(ref["threads"])
    print(f"Targets (on {ref_name}; {threads} threads):")
    checks = [
        (
            f"warm evaluation <= {TARGETS['warm_eval_s']} s",
            ref["warm_eval_s"] <= TARGETS["warm_eval_s"],
            f"{ref['warm_eval_s']:.3f} s on {threads} cores, {ref['warm_eval_1core_s']:.3f} s on 1",
        ),
        (
            f"whole CLI process <= {TARGETS['cli_warm_s']} s (cache warm)",
            cli[ref_name][0] <= TARGETS["cli_warm_s"],
            f"{cli[ref_name][0]:.2f} s",
        ),
        (
            f"peak memory <= {TARGETS['peak_rss_mib']:.0f} MiB",
            cli[ref_name][1] <= TARGETS["peak_rss_mib"],
            f"{cli[ref_name][1]:.1f} MiB",
        ),
    ]
    if cold:
        for what in ("kitti-eval --format json", "kitti-eval demo"):
            wall, cpu = cold[what]
            checks.append(
                (
                    f"first {what} <= {TARGETS['cli_cold_s']:.0f} s wall, {TARGETS['cli_cold_cpu_s']:.0f} s CPU",
                    wall <= TARGETS["cli_cold_s"] and cpu <= TARGETS["cli_cold_cpu_s"],
                    f"{wall:.1f} s, {cpu:.1f} s CPU",
                )
            )
    if 1 in scales and 10 in scales:
        one, ten = report["generated 1x"], report["generated 10x"]
        t_ratio = ten["warm_eval_s"] / one["warm_eval_s"]
        m_ratio = cli["generated 10x"][1] / cli["generated 1x"][1]
        c_ratio = cli["generated 10x"][0] / cli["generated 1x"][0]
        checks.append(
            (
                f"10x frames: evaluation time <= {TARGETS['scale_ratio']:.0f}x",
                t_ratio <= TARGETS["scale_ratio"],
                f"{t_ratio:.2f}x",
            )
        )
        checks.append(
            (
                f"10x frames: whole process time <= {TARGETS['scale_ratio']:.0f}x",
                c_ratio <= TARGETS["scale_ratio"],
                f"{c_ratio:.2f}x",
            )
        )
        checks.append(
            (
                f"10x frames: peak memory <= {TARGETS['scale_ratio']:.0f}x",
                m_ratio <= TARGETS["scale_ratio"],
                f"{m_ratio:.2f}x",
            )
        )
    for what, ok, figure in checks:
        print(f"  {_verdict(ok):<8} {what:<52} {figure}")
    print(
        "References on this machine type (KITTI val size, R40, one threshold set): official C++ devkit 37.4 s; "
        "OpenPCDet's evaluator with its IoU on the CPU 186 s, 678 MiB."
    )
    if not all(ok for _, ok, _ in checks):
        print("Exit status 3: a target is not met on this machine (the targets are for two quiet cores).")
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
