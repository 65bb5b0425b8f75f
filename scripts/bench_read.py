"""Reading a KITTI-val-sized pair, measured against plain ``pickle.load``: this checkout and an older commit,
alternated in one run (the load of a shared machine varies from minute to minute; a pair of runs shares it).

* the whole ``kitti-eval --gt infos.pkl --pred result.pkl --format json`` process of each commit, beside a
  prototype that does the same work with ``pickle.load`` (both files read with it, the same arrays built with
  one concatenation per field and no check, evaluated and written the same way): the measured limit. Its
  AP table is checked to be the command's;
* where a process's time goes, for each commit: importing the command line, reading both files
  (``read_pair``), evaluating and writing the JSON (a driver that makes those calls and times them);
* a job in a worker, for each commit: a long-lived process that has imported everything and holds the
  ground truth, reading an uploaded result.pkl from its bytes as that commit's service does (the restricted
  unpickler and the annotations with the boxes kept and the frames checked against the ground truth's: one
  call, ``annotations_from_pickle``, where the commit has it) and evaluating it;
* reading the 22 MB result.pkl in such a process: ``pickle.load`` of the file, the restricted unpickler
  alone (``load_pickle``) and the whole read into arrays (``load_detections``).

``python scripts/bench_read.py [--old REV] [--pairs 9] [--case DIR]``: REV defaults to ``main``; the case to
the golden ``kitti_val_scale`` (its ``kitti_infos_val.pkl.gz`` and ``result.pkl.gz``, unpacked first, as users
send them). The old commit is unpacked (``git archive``) into a temporary folder and run with the same
interpreter; each side's kernels are compiled (or loaded) once before anything is timed. Prints medians and
the ratios (of the medians, and the median of each pair's ratio); exits 0, or 1 when the AP tables differ.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT.parent / "shared" / "golden" / "cases" / "kitti_val_scale"

#: the console script kitti-eval, as installed (its entry skips the interpreter's teardown)
ENTRY = "import sys; sys.argv[0] = 'kitti-eval'; from kitti_eval.cli import entry; entry()"

#: the prototype: the same work with pickle.load and no checks (argv: gt, pred, output)
PROTOTYPE = r"""
import pickle, sys
import numpy as np
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.report.render import OutputFormat, render

FIELDS = {"truncated": (), "occluded": (), "alpha": (), "bbox": (4,), "dimensions": (3,), "location": (3,),
          "rotation_y": (), "score": ()}

def build(kind, pairs):
    ids = [f"{int(f):06d}" if str(f).isdigit() else str(f) for f, _ in pairs]
    annos = [a for _, a in pairs]
    counts = [len(a["name"]) for a in annos]
    offsets = np.zeros(len(annos) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    cols = {}
    for f, trailing in FIELDS.items():
        if f in annos[0]:
            cols[f] = np.concatenate([a[f] for a, n in zip(annos, counts) if n], dtype=np.float64)
        else:
            cols[f] = np.full((int(offsets[-1]), *trailing), -1.0 if f == "score" else 0.0)
    names = np.concatenate([a["name"] for a, n in zip(annos, counts) if n])
    return Annotations(kind=kind, source=kind, frame_ids=tuple(ids), offsets=offsets, name=names, **cols)

with open(sys.argv[1], "rb") as fh:
    infos = pickle.load(fh)
with open(sys.argv[2], "rb") as fh:
    results = pickle.load(fh)
gt = build("ground_truth", [(i["image"]["image_idx"], i["annos"]) for i in infos])
dt = build("detections", [(r["frame_id"], r) for r in results])
with open(sys.argv[3], "w", encoding="utf-8") as out:
    out.write(render(evaluate(gt, dt, EvalConfig()), OutputFormat.JSON))
sys.stdout.flush()
import os
os._exit(0)
"""

#: a process's steps, timed (argv: gt, pred, output); prints one JSON line
STEPS = r"""
import json, sys, time
t0 = time.perf_counter()
import kitti_eval.cli
t1 = time.perf_counter()
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.io.reading import read_pair
from kitti_eval.report.render import OutputFormat, render
t2 = time.perf_counter()
pair = read_pair(sys.argv[1], sys.argv[2])
t3 = time.perf_counter()
with open(sys.argv[3], "w", encoding="utf-8") as out:
    out.write(render(evaluate(pair.gt, pair.dt, EvalConfig()), OutputFormat.JSON))
t4 = time.perf_counter()
print(json.dumps({"import": t1 - t0, "import more": t2 - t1, "read": t3 - t2, "evaluate": t4 - t3}), flush=True)
import os
os._exit(0)
"""

#: a worker: imports once, holds the ground truth, then one job (or one read) per line of stdin. A job reads
#: the upload as that commit's service does: one call where the commit has it, else the pickle then its frames
WORKER = r"""
import io, json, pickle, sys, time
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.io import loaders
from kitti_eval.io.loaders import annotations_from_object, load_detections, load_ground_truth
from kitti_eval.io.safe_pickle import load_pickle
gt_path, pred_path = sys.argv[1], sys.argv[2]
gt = load_ground_truth(gt_path)
known = gt.frame_index()
content = open(pred_path, "rb").read()
one_call = getattr(loaders, "annotations_from_pickle", None)

def job():
    t0 = time.perf_counter()
    if one_call is not None:
        dt = one_call(io.BytesIO(content), "detections", source="result.pkl", keep_lidar=True, known_frames=known)
    else:
        obj = load_pickle(io.BytesIO(content), source="result.pkl")
        dt = annotations_from_object(obj, "detections", source="result.pkl", keep_lidar=True, known_frames=known)
    t1 = time.perf_counter()
    evaluate(gt, dt, EvalConfig()).to_dict()
    t2 = time.perf_counter()
    return {"job read": t1 - t0, "job evaluate": t2 - t1}

def reads():
    out = {}
    t0 = time.perf_counter()
    with open(pred_path, "rb") as fh:
        pickle.load(fh)
    t1 = time.perf_counter()
    load_pickle(pred_path, source=pred_path)
    t2 = time.perf_counter()
    load_detections(pred_path)
    t3 = time.perf_counter()
    return {"pickle.load": t1 - t0, "load_pickle": t2 - t1, "load_detections": t3 - t2}

job(); reads()
print("ready", flush=True)
for line in sys.stdin:
    print(json.dumps(job() if line.strip() == "job" else reads()), flush=True)
"""


def unpack(case: Path, into: Path) -> tuple[Path, Path]:
    """The case's infos and result pickles, decompressed (as users send them)."""
    out = []
    for name in ("kitti_infos_val.pkl", "result.pkl"):
        target = into / name
        with gzip.open(case / f"{name}.gz", "rb") as src, open(target, "wb") as dst:
            shutil.copyfileobj(src, dst)
        out.append(target)
    return out[0], out[1]


def checkout(rev: str, into: Path) -> Path:
    """The package of commit ``rev``, unpacked into ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "kitti_eval"], check=True, capture_output=True)
    into.mkdir()
    tar_path = into / "src.tar"
    tar_path.write_bytes(archive.stdout)
    with tarfile.open(tar_path) as tar:
        tar.extractall(into, filter="data")
    tar_path.unlink()
    return into


def env_for(tree: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPATH")}
    env["PYTHONPATH"] = str(tree)  # this tree's kitti_eval before the installed one
    return env


def timed(cmd: list[str], tree: Path) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, cwd=tree, env=env_for(tree), check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def steps(tree: Path, gt: Path, pred: Path, out: Path) -> dict[str, float]:
    done = subprocess.run(
        [sys.executable, "-c", STEPS, str(gt), str(pred), str(out)],
        cwd=tree,
        env=env_for(tree),
        check=True,
        capture_output=True,
        text=True,
    )
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


class Worker:
    """A long-lived process of one tree that runs a job or a read per request."""

    def __init__(self, tree: Path, gt: Path, pred: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", WORKER, str(gt), str(pred)],
            cwd=tree,
            env=env_for(tree),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the worker of {tree} did not start")

    def ask(self, what: str) -> dict[str, float]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(what + "\n")
        self.proc.stdin.flush()
        return dict(json.loads(self.proc.stdout.readline()))

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


def median_ms(values: list[float]) -> str:
    return f"{statistics.median(values) * 1e3:7.0f} ms"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old", default="main", help="the commit to compare with (default: main)")
    p.add_argument("--pairs", type=int, default=9, help="alternated pairs of runs (default: 9)")
    p.add_argument("--case", type=Path, default=GOLDEN, help="a folder with kitti_infos_val.pkl.gz and result.pkl.gz")
    args = p.parse_args()
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.old], check=True, capture_output=True, text=True
    ).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="bench-read-") as tmp_name:
        tmp = Path(tmp_name)
        gt, pred = unpack(args.case, tmp)
        trees = {"old": checkout(rev, tmp / "old"), "new": ROOT}
        outs = {side: tmp / f"{side}.json" for side in ("old", "new", "prototype")}
        cli = {
            side: [sys.executable, "-c", ENTRY, "--gt", str(gt), "--pred", str(pred), "--format", "json"]
            for side in trees
        }
        print(
            f"case {args.case.name}: {gt.stat().st_size / 1e6:.1f} MB infos, {pred.stat().st_size / 1e6:.1f} MB "
            f"result.pkl; old = {rev}, new = this checkout; {args.pairs} alternated pairs"
        )
        for side, tree in trees.items():  # compiles (or loads) the kernels the command needs, once
            subprocess.run([*cli[side], "--output", str(outs[side])], cwd=tree, env=env_for(tree), check=True)
        subprocess.run(
            [sys.executable, "-c", PROTOTYPE, str(gt), str(pred), str(outs["prototype"])],
            cwd=ROOT,
            env=env_for(ROOT),
            check=True,
        )
        tables = {side: json.loads(outs[side].read_text())["ap"] for side in outs}
        if not tables["old"] == tables["new"] == tables["prototype"]:
            print("the AP tables differ between old, new and the prototype")
            return 1

        whole: dict[str, list[float]] = {side: [] for side in outs}
        parts: dict[str, dict[str, list[float]]] = {side: {} for side in trees}
        runs = {
            **{side: ([*cli[side], "--output", str(outs[side])], tree) for side, tree in trees.items()},
            "prototype": ([sys.executable, "-c", PROTOTYPE, str(gt), str(pred), str(outs["prototype"])], ROOT),
        }
        for i in range(args.pairs):
            order = list(runs) if i % 2 == 0 else list(reversed(runs))  # neither side always first
            for side in order:
                whole[side].append(timed(*runs[side]))
            for side in order:
                if side in trees:
                    for key, value in steps(trees[side], gt, pred, outs[side]).items():
                        parts[side].setdefault(key, []).append(value)

        workers = {side: Worker(tree, gt, pred) for side, tree in trees.items()}
        try:
            for i in range(args.pairs):
                for side in ("old", "new") if i % 2 == 0 else ("new", "old"):
                    worker = workers[side]
                    for what in ("job", "reads"):
                        for key, value in worker.ask(what).items():
                            parts[side].setdefault(key, []).append(value)
        finally:
            for worker in workers.values():
                worker.close()

    proto = statistics.median(whole["prototype"])
    print("\nwhole kitti-eval --format json process (wall, medians; then the median of each pair's ratio)")
    for side in ("old", "new", "prototype"):
        ratio = statistics.median(whole[side]) / proto
        paired = statistics.median(a / b for a, b in zip(whole[side], whole["prototype"]))
        print(f"  {side:<10} {median_ms(whole[side])}   {ratio:.2f}x the prototype ({paired:.2f}x paired)")
    print("\nwhere the time goes (medians)      old        new")
    for key in parts["new"]:
        print(f"  {key:<26} {median_ms(parts['old'][key])} {median_ms(parts['new'][key])}")
    for side in ("old", "new"):
        base = parts[side]["pickle.load"]
        for key in ("load_pickle", "load_detections"):
            ratio = statistics.median(parts[side][key]) / statistics.median(base)
            paired = statistics.median(a / b for a, b in zip(parts[side][key], base))
            print(f"  {side}: {key} of result.pkl is {ratio:.2f}x pickle.load ({paired:.2f}x paired)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
