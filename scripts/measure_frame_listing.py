"""A frame listing and a frame view of a KITTI-val-sized evaluation, answered by a fresh web process: from the
frames the evaluation's job stored, and from the kept predictions read whole (the way of evaluations stored
before their jobs stored frames, the only way before), side by side.

The golden ``kitti_val_scale`` case (3769 frames, 151,276 detections as txt) is registered and evaluated once in
a temporary data folder (the evaluation's time and the size of its stored frames are printed). Then each run is
a fresh process (``python -c``) on that folder, the ways alternated, that answers one request:
``GET /v1/evaluations/ID/frames?worst=20`` or ``GET /v1/frames/FRAME?evaluation=ID`` (FRAME: the worst frame),
timed, and reports how far its resident memory grew while answering (its peak, from the kernel, less what it
held before the request). The old way is the same code with the stored frames ignored.

``python scripts/measure_frame_listing.py [--runs 3] [--case DIR]``. Prints the medians; exits 0.
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADMIN = "measure-admin-token"

SETUP = """
import json, time
from pathlib import Path
from fastapi.testclient import TestClient
from kitti_eval_server.main import create_app
from kitti_eval_server.settings import Settings
headers = {{"Authorization": "Bearer {admin}"}}
app = create_app(Settings(data_dir=Path({data!r}), admin_token="{admin}", warmup=False))
with TestClient(app) as client:
    files = {{"file": ("label_2.tar.gz", open({gt!r}, "rb"))}}
    r = client.post("/v1/ground-truths", data={{"name": "val"}}, files=files, headers=headers)
    assert r.status_code == 201, r.text
    started = time.monotonic()
    files = {{"predictions": ("pred.tar.gz", open({pred!r}, "rb"))}}
    r = client.post("/v1/evaluations", data={{"gt": "val"}}, files=files, headers=headers)
    assert r.status_code == 201, r.text
    evaluation = r.json()["id"]
    worst = client.get(f"/v1/evaluations/{{evaluation}}/frames", params={{"worst": 1}}, headers=headers).json()
    print(json.dumps({{"id": evaluation, "frame": worst["frames"][0]["frame"]}}))
"""

ANSWER = """
import json, resource, time
from pathlib import Path
from unittest import mock
from fastapi.testclient import TestClient
from kitti_eval_server.main import create_app
from kitti_eval_server.settings import Settings
from kitti_eval_server.evaluations.evaluations import EvaluationFrames
from kitti_eval_server.store import EvaluationStore

def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024

if {whole!r}:  # the old way: the stored frames ignored
    mock.patch.object(EvaluationStore, "has_frames", lambda self, evaluation_id: False).start()
    mock.patch.object(EvaluationFrames, "_stored_frame", lambda self, records, fid, cls: None).start()
headers = {{"Authorization": "Bearer {admin}"}}
app = create_app(Settings(data_dir=Path({data!r}), admin_token="{admin}", warmup=False))
with TestClient(app) as client:
    client.get("/healthz")
    before = rss_mb()
    t0 = time.perf_counter()
    if {listing!r}:
        r = client.get("/v1/evaluations/{evaluation}/frames", params={{"worst": 20}}, headers=headers)
    else:
        r = client.get("/v1/frames/{frame}", params={{"evaluation": "{evaluation}"}}, headers=headers)
    seconds = time.perf_counter() - t0
    assert r.status_code == 200, r.text
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({{"s": seconds, "grew_mb": peak - before, "peak_mb": peak, "bytes": len(r.content),
                      "answer": r.json()}}))
"""


def run(code: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=ROOT, env=os.environ.copy()
    )
    if out.returncode != 0:
        raise SystemExit(out.stderr[-2000:])
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs of each way (alternated)")
    parser.add_argument("--case", type=Path, default=ROOT.parent / "shared" / "golden" / "cases" / "kitti_val_scale")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="frame-listing-") as tmp:
        data = Path(tmp) / "data"
        started = time.monotonic()
        setup = run(
            SETUP.format(
                data=str(data), admin=ADMIN, gt=str(args.case / "label_2.tar.gz"), pred=str(args.case / "pred.tar.gz")
            )
        )
        print(f"registered, evaluated and listed once in a fresh process: {time.monotonic() - started:.1f} s")
        db = sqlite3.connect(data / "kitti-eval.db")
        rows, det_bytes, ev_bytes = db.execute(
            "SELECT count(*), sum(length(detections)), sum(length(events)) FROM evaluation_frames"
        ).fetchone()
        (duration,) = db.execute("SELECT duration_ms FROM evaluations").fetchone()
        (kept,) = db.execute("SELECT sum(length(content)) FROM prediction_files").fetchone()
        db.close()
        print(
            f"evaluation job: {duration / 1000:.1f} s; stored frames: {rows} rows, "
            f"detections {det_bytes / 1e6:.1f} MB, steps {ev_bytes / 1e6:.1f} MB (the kept file: {kept / 1e6:.1f} MB)"
        )
        cases = [
            (f"{what}, {way}", listing, whole)
            for what, listing in (("listing (worst=20)", True), (f"frame {setup['frame']}", False))
            for way, whole in (("stored frames", False), ("read whole", True))
        ]
        results: dict[str, list[dict]] = {name: [] for name, _, _ in cases}
        for _ in range(args.runs):
            for name, listing, whole in cases:
                code = ANSWER.format(
                    data=str(data),
                    admin=ADMIN,
                    evaluation=setup["id"],
                    frame=setup["frame"],
                    listing=listing,
                    whole=whole,
                )
                results[name].append(run(code))
        for listing in (True, False):
            answers = [r["answer"] for name, lst, _ in cases if lst == listing for r in results[name]]
            same = all(a == answers[0] for a in answers)
            print(f"{'listings' if listing else 'frame views'}: {'identical' if same else 'DIFFERENT'}")
        print(f"{'answer, way':<42} {'seconds':>8} {'grew MB':>8} {'peak MB':>8} {'bytes':>8}")
        for name, rs in results.items():
            med = {k: statistics.median(r[k] for r in rs) for k in ("s", "grew_mb", "peak_mb")}
            print(f"{name:<42} {med['s']:>8.3f} {med['grew_mb']:>8.0f} {med['peak_mb']:>8.0f} {rs[0]['bytes']:>8}")
        print(f"(medians of {args.runs} fresh processes each, alternated)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
