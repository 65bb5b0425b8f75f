"""Reading KITTI txt folders: this checkout against an older commit, alternated in one run (a shared
machine's load varies from minute to minute; a pair of runs shares it).

For each commit, in a fresh process per run, over the golden ``kitti_val_scale`` label and result folders
(3769 files each, unpacked once from ``label_2.tar.gz`` and ``pred.tar.gz``):

* ``parse``: each file's content read and parsed as the loader does, file by file (``read_bytes`` and
  ``parse_kitti_txt`` where the commit has ``read_bytes``, else ``read_text`` and ``parse_kitti_txt``);
* ``load``: the whole ``load_kitti_txt_dir`` (listing, reading, parsing, the checked annotations).

Each run takes the best of 3 calls of each (the first call warms the file cache and imports); the script
prints the median over the pairs and the median of each pair's ratio.

``python scripts/bench_txt.py [--old REV] [--pairs 7] [--case DIR]``: REV defaults to ``main``. The old
commit is unpacked (``git archive``) into a temporary folder and run with the same interpreter.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT.parent / "shared" / "golden" / "cases" / "kitti_val_scale"

#: argv: gt folder, pred folder; prints a JSON dict of seconds
DRIVER = r"""
import json, sys, time
from pathlib import Path
from kitti_eval.io.formats import kitti_txt as k
from kitti_eval.io.formats.kitti_txt import load_kitti_txt_dir, parse_kitti_txt, txt_files
read = getattr(k, "read_bytes", None) or k.read_text
out = {}
for kind, folder in (("ground_truth", sys.argv[1]), ("detections", sys.argv[2])):
    files = sorted(txt_files(Path(folder)), key=lambda f: f.name)
    best_parse = best_load = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for f in files:
            parse_kitti_txt(read(f), kind, frame=f.stem, source=str(f))
        best_parse = min(best_parse, time.perf_counter() - t)
        t = time.perf_counter()
        load_kitti_txt_dir(folder, kind)
        best_load = min(best_load, time.perf_counter() - t)
    out[f"{kind} parse"] = best_parse
    out[f"{kind} load"] = best_load
print(json.dumps(out))
"""


def _unpack(archive: Path, dest: Path) -> Path:
    with tarfile.open(archive) as tf:
        tf.extractall(dest, filter="data")
    dirs = {p.parent for p in dest.rglob("*.txt")}
    if len(dirs) != 1:
        raise SystemExit(f"{archive}: expected one folder of txt files, found {len(dirs)}")
    return dirs.pop()


def _run(tree: Path, gt: Path, pred: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(
        [sys.executable, "-c", DRIVER, str(gt), str(pred)], env=env, cwd=tree, capture_output=True, text=True
    )
    if done.returncode:
        raise SystemExit(f"{tree}: {done.stderr.strip()}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old", default="main", help="the commit to compare with (default: main)")
    p.add_argument("--pairs", type=int, default=7, help="alternated pairs of runs (default: 7)")
    p.add_argument("--case", type=Path, default=GOLDEN, help="a folder with label_2.tar.gz and pred.tar.gz")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-txt-") as tmp:
        t = Path(tmp)
        gt = _unpack(args.case / "label_2.tar.gz", t / "gt")
        pred = _unpack(args.case / "pred.tar.gz", t / "pred")
        old = t / "old"
        old.mkdir()
        archive = subprocess.run(["git", "archive", args.old], cwd=ROOT, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive, check=True)
        print(f"{len(list(gt.glob('*.txt')))} label files, {len(list(pred.glob('*.txt')))} result files")
        for tree in (old, ROOT):  # compile (or load) each side's kernels before timing anything
            _run(tree, gt, pred)
        runs: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
        for i in range(args.pairs):
            order = [("old", old), ("new", ROOT)] if i % 2 == 0 else [("new", ROOT), ("old", old)]
            for side, tree in order:
                runs[side].append(_run(tree, gt, pred))
    print(f"{'seconds (median of ' + str(args.pairs) + ' pairs)':<34} {args.old:>10} {'this':>10} {'ratio':>8}")
    for key in runs["old"][0]:
        o = statistics.median(r[key] for r in runs["old"])
        n = statistics.median(r[key] for r in runs["new"])
        pair = statistics.median(b[key] / a[key] for a, b in zip(runs["old"], runs["new"], strict=True))
        print(f"{key:<34} {o:>10.4f} {n:>10.4f} {pair:>7.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
