"""What the platform wheel's kernels buy, measured: first use after ``pip install`` and warm speed, against a
plain wheel whose first run compiles the kernels for this machine's CPU (kitti-eval before platform wheels).

    python scripts/bench_wheel.py                 # about 4 minutes on two cores
    python scripts/bench_wheel.py --rounds 9      # more alternations of the warm measurements

It builds both wheels from this checkout (the platform one with ``scripts/build_wheel.py``, the plain one
with ``pip wheel``), installs each with ``pip install`` into a fresh virtual environment (numba, numpy and
the rest from the package index) and prints:

* the size of each wheel;
* the first run of ``kitti-eval demo`` in each environment (the console script's own entry, under a
  listener of numba's compile events): wall and CPU seconds, and how many kernels numba compiled;
* warm speed, the two environments alternated in one run: the whole ``kitti-eval demo`` process, and one
  evaluation of a generated KITTI-val-sized set (3769 frames, ~40 detections a frame) in a warm process,
  medians of the rounds and their ratio (generic kernels / this CPU's).

Exit status 0 when the targets are met (first use under 1.5 s with nothing compiled, warm speed within 3 %),
3 when one is not.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_USE_LIMIT_S = 1.5
WARM_RATIO_LIMIT = 0.03
#: the warm figures: title, and whether the 3 % target is judged on it (CPU seconds: the machine is shared,
#: and a busy neighbour stretches wall time, not the work the kernels do)
_WARM = {
    "demo_wall": ("`kitti-eval demo` process, wall", False),
    "demo_cpu": ("`kitti-eval demo` process, CPU", True),
    "eval_wall": ("one evaluation of 3769 frames, 1 thread, wall", False),
    "eval_cpu": ("one evaluation of 3769 frames, 1 thread, CPU", True),
}

# what the console script runs (kitti_eval.cli:entry: main, then os._exit), with numba's compile events counted
_FIRST_USE = """
import json, os, sys
from kitti_eval._jit import compilations

with compilations() as compiled:
    from kitti_eval.cli import main

    code = main(["demo"])
from numba.core.registry import cpu_target

cpu = cpu_target.target_context.codegen().magic_tuple()[1]
print(json.dumps({"code": code, "compiled": len(compiled), "cpu": cpu}), file=sys.stderr)
sys.stdout.flush()
sys.stderr.flush()
os._exit(code)
"""

# warm evaluations of the generated set on one thread (the kernels' speed, whatever the other core does):
# loaded once, evaluated once to warm, then timed; the medians of wall and CPU seconds
_WARM_EVAL = """
import json, statistics, sys, time
from kitti_eval import evaluate, load_detections, load_ground_truth

gt, dt = load_ground_truth(sys.argv[1]), load_detections(sys.argv[2])
evaluate(gt, dt, workers=1)
walls, cpus = [], []
for _ in range(int(sys.argv[3])):
    wall, cpu = time.perf_counter(), time.process_time()
    evaluate(gt, dt, workers=1)
    walls.append(time.perf_counter() - wall)
    cpus.append(time.process_time() - cpu)
print(json.dumps([statistics.median(walls), statistics.median(cpus)]))
"""


def _env() -> dict[str, str]:
    """This environment, less what would change what numba compiles or where it caches."""
    drop = ("NUMBA_", "PYTHONPATH", "VIRTUAL_ENV")
    return {k: v for k, v in os.environ.items() if not k.startswith(drop)}


def _run(argv: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(argv, capture_output=True, text=True, check=False, env=_env(), **kwargs)  # type: ignore[call-overload]
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, argv[:6]))} failed ({done.returncode}):\n{done.stderr[-4000:]}")
    return done


def _timed(argv: list[str], cwd: Path) -> tuple[float, float, str]:
    """Wall and CPU seconds (its children included) and stderr of one process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = _run(argv, cwd=cwd)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), done.stderr


def _wheels(work: Path) -> tuple[Path, Path]:
    """The platform wheel (kernels inside) and the plain wheel (sources only) of this checkout."""
    _run([sys.executable, str(ROOT / "scripts" / "build_wheel.py"), "--out", str(work / "platform")])
    src = work / "src"
    src.mkdir()
    skip = shutil.ignore_patterns("__pycache__", "*.py[cod]", "*.nbi", "*.nbc", "_kernels", "*.egg-info")
    for name in ("pyproject.toml", "README.md", "kitti_eval", "server"):
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=skip)
        else:
            shutil.copy2(ROOT / name, src / name)
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "--disable-pip-version-check",
            "-q",
            "wheel",
            "--no-deps",
            str(src),
            "-w",
            str(work / "plain"),
        ]
    )
    (platform,) = (work / "platform").glob("*.whl")
    (plain,) = (work / "plain").glob("*.whl")
    return platform, plain


def _venv(where: Path, wheel: Path) -> tuple[Path, float]:
    """A fresh virtual environment with ``wheel`` installed by pip (its requirements from the index); its bin
    folder and the install's seconds."""
    _run([sys.executable, "-m", "venv", str(where)])
    bin_dir = where / "bin"
    started = time.perf_counter()
    _run([str(bin_dir / "python"), "-m", "pip", "--disable-pip-version-check", "-q", "install", str(wheel)])
    return bin_dir, time.perf_counter() - started


def _generate(where: Path) -> tuple[Path, Path]:
    argv = [sys.executable, "-m", "kitti_eval.synth", "--frames", "3769", "--seed", "0"]
    _run([*argv, "--dets-per-frame", "40", "--gt-per-frame", "8", "--out", str(where)])
    return where / "kitti_infos_val.pkl", where / "result.pkl"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=10, help="alternations of the warm measurements (default 10)")
    parser.add_argument("--repeat", type=int, default=5, help="timed evaluations in each warm process (default 5)")
    args = parser.parse_args(argv)
    met = True
    with tempfile.TemporaryDirectory(prefix="kitti-eval-bench-wheel-") as tmp:
        work = Path(tmp)
        platform, plain = _wheels(work)
        print("wheel sizes")
        for label, wheel in (("plain (sources only)", plain), ("platform (kernels inside)", platform)):
            print(f"  {label:<28} {wheel.stat().st_size / 2**20:6.2f} MiB  {wheel.name}")

        envs = {}
        print("\npip install into a fresh virtual environment, then the first `kitti-eval demo`")
        for label, wheel in (("platform wheel", platform), ("plain wheel", plain)):
            bin_dir, install_s = _venv(work / label.replace(" ", "-"), wheel)
            envs[label] = bin_dir
            wall, cpu, err = _timed([str(bin_dir / "python"), "-c", _FIRST_USE], cwd=work)
            first = json.loads(err.strip().splitlines()[-1])
            assert first["code"] == 0, err
            saved = len(list(bin_dir.parent.rglob("__pycache__/*.nbi")))  # by the CLI and its background compile
            print(
                f"  {label:<16} install {install_s:5.1f} s   first run {wall:5.2f} s wall, {cpu:5.2f} s CPU   "
                f"compiled: {first['compiled']} in the CLI's process, {saved} kernels saved to numba's cache "
                f"(the process compiles for CPU {first['cpu']!r})"
            )
            if label == "platform wheel":
                ok = wall < FIRST_USE_LIMIT_S and first["compiled"] == 0 and saved == 0
                met &= ok
                verdict = "met" if ok else "NOT MET"
                print(f"  {'':<16} target: under {FIRST_USE_LIMIT_S} s with nothing compiled: {verdict}")

        # every kernel of every entry point in both: compiled for this CPU (plain) or loaded (platform)
        for bin_dir in envs.values():
            _run([str(bin_dir / "python"), "-m", "kitti_eval._jit", "--all"], cwd=work)
        gt, pred = _generate(work / "set")
        runs: dict[str, dict[str, list[float]]] = {what: {label: [] for label in envs} for what in _WARM}
        for round_ in range(args.rounds):
            order = list(envs.items()) if round_ % 2 == 0 else list(envs.items())[::-1]
            for label, bin_dir in order:
                wall, cpu, _ = _timed([str(bin_dir / "kitti-eval"), "demo"], cwd=work)
                runs["demo_wall"][label].append(wall)
                runs["demo_cpu"][label].append(cpu)
                out = _run([str(bin_dir / "python"), "-c", _WARM_EVAL, str(gt), str(pred), str(args.repeat)], cwd=work)
                wall, cpu = json.loads(out.stdout.strip().splitlines()[-1])
                runs["eval_wall"][label].append(wall)
                runs["eval_cpu"][label].append(cpu)

        print(f"\nwarm, the two alternated ({args.rounds} rounds; medians; ratio = generic / this CPU's)")
        for what, (title, judged) in _WARM.items():
            generic, host = (statistics.median(runs[what][label]) for label in ("platform wheel", "plain wheel"))
            ratio = generic / host
            verdict = ""
            if judged:
                ok = ratio <= 1 + WARM_RATIO_LIMIT  # generic code no more than 3 % slower
                met &= ok
                verdict = f"  (at most {WARM_RATIO_LIMIT:.0%} slower: {'met' if ok else 'NOT MET'})"
            print(f"  {title:<44} generic {generic:6.3f} s   this CPU's {host:6.3f} s   {ratio:5.3f}x{verdict}")
        print("\nevery round (generic / this CPU's):")
        for what, (title, _) in _WARM.items():
            pairs = zip(runs[what]["platform wheel"], runs[what]["plain wheel"])
            print(f"  {title:<44} " + " ".join(f"{g:.3f}/{h:.3f}" for g, h in pairs))
    return 0 if met else 3


if __name__ == "__main__":
    sys.exit(main())
