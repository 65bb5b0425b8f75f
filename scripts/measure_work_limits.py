"""The limits on work, measured: the two files that asked for more work than their bytes said, refused at the
defaults (by the command line, and by the service in one process: its web part and its worker threads), and
the memory a process needs at the defaults (the largest txt input accepted, and the overlaps per pair).

Each case runs in a fresh process (``python -c``), timed from its start to its end, its peak resident memory
read from the kernel (``wait4``'s ``ru_maxrss``). Prints one line a case: seconds, peak MB, and the outcome.

``python scripts/measure_work_limits.py [--skip-large] [--case DIR]``: ``--skip-large`` leaves out the cases
that measure the memory at the defaults (a few minutes on two cores); the case (the golden ``kitti_val_scale``
by default) gives the KITTI-val-sized labels and predictions.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import tarfile
import tempfile
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LABEL = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"


def tar_gz(path: Path, files: dict[str, bytes]) -> Path:
    with tarfile.open(path, "w:gz", compresslevel=9) as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def run(code: str, env: dict[str, str] | None = None) -> tuple[float, float, int, str]:
    """(seconds, peak MB, exit code, the last line of its output) of ``python -c code``."""
    started = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, **(env or {})},
        cwd=ROOT,
    )
    assert proc.stdout is not None
    out = proc.stdout.read().decode(errors="replace").strip().splitlines()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return time.monotonic() - started, usage.ru_maxrss / 1024, proc.returncode, (out[-1] if out else "")[:160]


def cli(gt: Path, pred: Path) -> str:
    return f"""
    import sys
    from kitti_eval.cli import main
    sys.exit(main(["--gt", {str(gt)!r}, "--pred", {str(pred)!r}, "--format", "json", "-o", "/dev/null"]))
    """


def service(pred: Path, gt_file: Path | None) -> str:
    """An in-process service (its web part and two worker threads in one process) given one upload."""
    return f"""
    import tempfile
    from pathlib import Path
    from fastapi.testclient import TestClient
    from kitti_eval_server.main import create_app
    from kitti_eval_server.settings import Settings
    with tempfile.TemporaryDirectory() as data:
        app = create_app(Settings(data_dir=Path(data), admin_token="measure-admin-token", warmup=False))
        with TestClient(app) as client:
            files = {{"predictions": ({pred.name!r}, open({str(pred)!r}, "rb"))}}
            form = {{"gt": "demo"}}
            if {gt_file is not None!r}:
                files["gt_file"] = ("label_2.tar.gz", open({str(gt_file)!r}, "rb"))
                form = {{}}
            r = client.post("/v1/evaluations", data=form, files=files)
            print(r.status_code, r.json().get("error", {{}}).get("message", "")[:110])
    """


def frames_view(pred: Path, data: Path, *, upload: bool) -> str:
    """A service on ``data`` that uploads ``pred`` against the demo (``upload``), or, in a fresh process, answers
    the frame listing of the evaluation stored there: the kept predictions read whole by the process."""
    return f"""
    from pathlib import Path
    from fastapi.testclient import TestClient
    from kitti_eval_server.main import create_app
    from kitti_eval_server.settings import Settings
    app = create_app(Settings(data_dir=Path({str(data)!r}), admin_token="measure-admin-token", warmup=False))
    with TestClient(app) as client:
        if {upload!r}:
            files = {{"predictions": ("pred.tar.gz", open({str(pred)!r}, "rb"))}}
            r = client.post("/v1/evaluations", data={{"gt": "demo"}}, files=files)
            print(r.status_code, "evaluated")
        else:
            (evaluation,) = [e["id"] for e in client.get("/v1/evaluations").json()["items"]]
            r = client.get(f"/v1/evaluations/{{evaluation}}/frames", params={{"worst": 5}})
            print(r.status_code, len(r.content), "bytes answered")
    """


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--skip-large", action="store_true")
    parser.add_argument("--only", help="run only the cases whose name holds this")
    parser.add_argument("--case", type=Path, default=ROOT.parent / "shared" / "golden" / "cases" / "kitti_val_scale")
    args = parser.parse_args()
    golden = args.case
    with tempfile.TemporaryDirectory(prefix="work-limits-") as tmp_:
        tmp = Path(tmp_)
        # 1. many boxes in few bytes: 32 frames of one line repeated, 509 MB of txt (inside the 512 MB unpacked)
        line = (LABEL + " 0.95\n").encode()
        crowded = line * (509_000_000 // 32 // len(line))
        many = tar_gz(tmp / "many.tar.gz", {f"pred/{i:06d}.txt": crowded for i in range(32)})
        boxes = 32 * crowded.count(b"\n")
        # 2. work that grows with the square: one frame of 8,000 identical boxes on each side
        gt_sq = tar_gz(tmp / "gt_square.tar.gz", {"label_2/000000.txt": (LABEL + "\n").encode() * 8000})
        pred_sq = tar_gz(tmp / "pred_square.tar.gz", {"pred/000000.txt": line * 8000})
        print(
            f"many boxes: {many.stat().st_size / 1e6:.1f} MB tar.gz, {32 * len(crowded) / 1e6:.0f} MB of txt, "
            f"{boxes:,} boxes"
        )
        print(f"square: {(gt_sq.stat().st_size + pred_sq.stat().st_size) / 1e3:.0f} KB in all, 8,000 x 8,000 boxes")
        cases = [
            ("CLI, many boxes (KITTI-val-sized labels)", cli(golden / "label_2.tar.gz", many), None),
            ("CLI, 8,000 x 8,000 in one frame", cli(gt_sq, pred_sq), None),
            ("service (one process), many boxes against the demo", service(many, None), None),
            ("service (one process), 8,000 x 8,000 with gt_file", service(pred_sq, gt_sq), None),
            ("CLI, KITTI-val-sized case (txt)", cli(golden / "label_2.tar.gz", golden / "pred.tar.gz"), None),
        ]
        if not args.skip_large:
            # the largest txt predictions the defaults accept: 500 frames of 10,000 boxes (5 million, ~450 MB)
            head = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64"
            frame = b"".join(f"{head} {k * 0.01:.2f} 1.71 46.70 -1.59 0.95\n".encode() for k in range(10_000))
            big = tmp / "big"
            (big / "pred").mkdir(parents=True)
            for i in range(500):
                (big / "pred" / f"{i:06d}.txt").write_bytes(frame)
            read_big = f"""
            from kitti_eval.io.loaders import load_detections
            print(load_detections({str(big / "pred")!r}).num_boxes, "boxes read")
            """
            cases.append(("read 5,000,000 boxes of txt (the defaults' most)", read_big, None))
            # the overlaps: 10 frames of 2,000 detections x 1,000 labels (20 million pairs), against 10 x 20 x 10
            pairs = """
            import numpy as np
            from kitti_eval.core.evaluation import evaluate
            from kitti_eval.core.frames import Annotations
            def frames(n, det):
                out = []
                for f in range(10):
                    k = np.arange(n, dtype=float)
                    d = {"name": np.full(n, "Car"), "truncated": np.zeros(n), "occluded": np.zeros(n),
                         "alpha": np.zeros(n), "bbox": np.tile([100.0, 100.0, 200.0, 160.0], (n, 1)),
                         "dimensions": np.tile([3.9, 1.5, 1.6], (n, 1)),
                         "location": np.stack([k % 50 * 5.0, np.full(n, 1.6), k // 50 * 5.0 + 5], 1),
                         "rotation_y": np.zeros(n)}
                    if det:
                        d["score"] = np.linspace(0.1, 0.9, n)
                    out.append((f"{f:06d}", d))
                return Annotations.from_frames("detections" if det else "ground_truth", "s", out)
            gt, dt = frames(N_GT, False), frames(N_DT, True)
            evaluate(gt, dt)
            print(10 * N_GT * N_DT, "pairs evaluated")
            """
            cases.append(("evaluate 200 pairs (baseline)", pairs.replace("N_GT", "10").replace("N_DT", "2"), None))
            cases.append(("evaluate 20,000,000 pairs", pairs.replace("N_GT", "1000").replace("N_DT", "2000"), None))
            # a frame view of kept predictions of 1,000,000 boxes (KITTI_EVAL_FRAMES_MAX_BOXES): 100 frames of 10,000
            kept = tar_gz(tmp / "kept.tar.gz", {f"pred/{i:06d}.txt": frame for i in range(100)})
            cases.append(
                ("service, evaluate 1,000,000 boxes of txt (kept)", frames_view(kept, tmp / "svc", upload=True), None)
            )
            cases.append(
                (
                    "service, a frame listing of them in a new process",
                    frames_view(kept, tmp / "svc", upload=False),
                    None,
                )
            )
        # compile (or load) the kernels once, outside the measured runs
        run("import kitti_eval._jit as j; j.warm_up()")
        for name, code, env in cases:
            if args.only and args.only not in name:
                continue
            seconds, peak, rc, last = run(code, env)
            print(f"{name:<55} {seconds:6.1f} s  {peak:7.0f} MB  exit {rc}  {last}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
