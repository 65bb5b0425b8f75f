"""Measure the round trip of uploading a KITTI-val-sized result.pkl to a warm, real uvicorn.

    python tests/helpers/server_roundtrip.py --gt /work/shared/golden/cases/kitti_val_scale/kitti_infos_val.pkl.gz \\
        --pred /tmp/vs/result.pkl [--runs 5]

Starts ``uvicorn kitti_eval_server.main:app`` on 127.0.0.1 (a free port, a temp data folder), registers the ground
truth, uploads once to warm the ground-truth cache, then times ``--runs`` uploads (client clock, request sent to
response parsed) and prints them with the server's own ``duration_ms``. Not a test: run it by hand.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from server_helpers import ADMIN, LiveServer  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--pred", type=Path, required=True)
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args(argv)
    pred = args.pred.read_bytes()
    with (
        tempfile.TemporaryDirectory() as tmp,
        LiveServer(Path(tmp) / "data", max_upload_mb=256, max_unpacked_mb=1024) as server,
    ):
        with server.client(timeout=300) as c:
            t0 = time.perf_counter()
            r = c.post(
                "/v1/ground-truths",
                data={"name": "kitti-val"},
                headers=ADMIN,
                files={"file": (args.gt.name, args.gt.read_bytes())},
            )
            r.raise_for_status()
            print(f"register ground truth: {time.perf_counter() - t0:.2f} s, {r.json()['frames']} frames")  # noqa: T201

            def once() -> tuple[float, float]:
                t = time.perf_counter()
                resp = c.post(
                    "/v1/evaluations",
                    data={"gt": "kitti-val"},
                    files={"predictions": (args.pred.name, pred, "application/octet-stream")},
                )
                elapsed = time.perf_counter() - t
                resp.raise_for_status()
                return elapsed, resp.json()["evaluation"]["duration_ms"] / 1000

            first = once()
            print(f"first upload: {first[0]:.2f} s (server {first[1]:.2f} s)")  # noqa: T201
            runs = [once() for _ in range(args.runs)]
    walls = [w for w, _ in runs]
    servers = [s for _, s in runs]
    print(
        f"{args.pred.name}: {len(pred) / 1e6:.1f} MB, {args.runs} warm uploads: round trip "  # noqa: T201
        f"median {statistics.median(walls):.2f} s (min {min(walls):.2f}, max {max(walls):.2f}); "
        f"server-side median {statistics.median(servers):.2f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
