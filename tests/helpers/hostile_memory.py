"""Peak memory of the CLI and the live service on hostile inputs, with default limits (prints a table).

    python tests/helpers/hostile_memory.py [--only WORD]    (WORD: only the payloads whose label holds it)

Each payload is refused; the figures are the CLI process's peak RSS, and the service's peak RSS during
the upload (its high-water mark is reset before each one) and its RSS a moment after the answer, next to
its idle RSS. Target: no single bad input above 1 GiB, and the service back near idle afterwards.
"""

from __future__ import annotations

import gzip
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from server_helpers import LiveServer  # noqa: E402

from kitti_eval.demo import demo_paths  # noqa: E402

GIB = 1 << 30


def _bomb_pickle() -> bytes:
    """A pickle of one 1 GiB bytes object, gzipped to ~1 MB."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", compresslevel=9) as gz:
        gz.write(b"\x80\x04]\x94\x8e" + GIB.to_bytes(8, "little"))
        zeros = b"\0" * (16 << 20)
        for _ in range(GIB // len(zeros)):
            gz.write(zeros)
        gz.write(b"a.")
    return out.getvalue()


def _million_frames() -> bytes:
    empty = {k: np.zeros(0) for k in ("name", "truncated", "occluded", "alpha", "rotation_y", "score")}
    empty.update(bbox=np.zeros((0, 4)), dimensions=np.zeros((0, 3)), location=np.zeros((0, 3)))
    return pickle.dumps([dict(empty, frame_id=f"{i:07d}") for i in range(1_000_000)], protocol=4)


def _many_unknown_frames(n: int) -> bytes:
    frame = {
        "name": np.array(["Car"]),
        "score": np.float32([0.5]),
        "bbox": np.zeros((1, 4), np.float32),
        "dimensions": np.ones((1, 3), np.float32),
        "location": np.zeros((1, 3), np.float32),
        "rotation_y": np.zeros(1, np.float32),
        "alpha": np.zeros(1, np.float32),
    }
    return pickle.dumps([dict(frame, frame_id=f"9{i:06d}") for i in range(n)], protocol=4)


def _shared_arrays(frames: int, boxes: int) -> bytes:
    """Frames that all use the same arrays (pickle writes them once, then reads them from its memo): a small
    file that reads into frames x boxes boxes."""
    rng = np.random.default_rng(0)
    arrays = {f: rng.random(boxes, np.float32) for f in ("truncated", "alpha", "rotation_y", "score")}
    arrays.update(name=np.array(["Car"] * boxes), occluded=np.zeros(boxes, np.int8))
    arrays.update({f: rng.random((boxes, w), np.float32) for f, w in (("bbox", 4), ("dimensions", 3), ("location", 3))})
    return pickle.dumps([dict(arrays, frame_id=f"{i:06d}") for i in range(frames)], protocol=4)


def _archive(kind: str) -> bytes:
    out = io.BytesIO()
    if kind == "zip":
        with (
            zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf,
            zf.open("pred/000000.txt", "w", force_zip64=True) as f,
        ):
            zeros = b"0" * (16 << 20)
            for _ in range(GIB // len(zeros)):
                f.write(zeros)
        return out.getvalue()

    class Zeros(io.RawIOBase):
        left = GIB

        def readable(self) -> bool:
            return True

        def readinto(self, b: bytearray) -> int:  # type: ignore[override]
            n = min(len(b), self.left)
            b[:n] = b"0" * n
            self.left -= n
            return n

    with tarfile.open(fileobj=out, mode="w:gz") as tf:
        info = tarfile.TarInfo("pred/000000.txt")
        info.size = GIB
        tf.addfile(info, io.BufferedReader(Zeros()))
    return out.getvalue()


PAYLOADS = {
    "gzip bomb (1 GiB pickle, 1 MB gz)": ("result.pkl.gz", _bomb_pickle),
    "a million empty frames (56 MB)": ("result.pkl", _million_frames),
    "150k frames not in the ground truth": ("result.pkl", lambda: _many_unknown_frames(150_000)),
    "3M empty dicts (3 MB)": ("result.pkl", lambda: b"\x80\x04" + b"}" * 3_000_000 + b"."),
    "tar bomb (1 GiB txt member)": ("pred.tar.gz", lambda: _archive("tar")),
    "zip bomb (1 GiB txt member)": ("pred.zip", lambda: _archive("zip")),
    "200 frames sharing 10k-box arrays (0.7 MB)": ("result.pkl", lambda: _shared_arrays(200, 10_000)),
    "200 frames sharing 20k-box arrays (1.4 MB)": ("result.pkl", lambda: _shared_arrays(200, 20_000)),
}


def _status(pid: int, key: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def _cli_peak(gt: Path, pred: Path) -> tuple[int, float, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "kitti_eval.cli", "--gt", str(gt), "--pred", str(pred), "--format", "json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    assert proc.stderr is not None
    err = proc.stderr.read().decode()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_maxrss / 1024, err.strip().splitlines()[-1][:90] if err.strip() else ""


def main(only: str = "") -> int:
    gt, _ = demo_paths()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        # made in a child: a child forked from a big process starts with its peak RSS
        subprocess.run([sys.executable, __file__, "--make", str(tmp), only], check=True)
        files = {label: tmp / f"{k}-{name}" for k, (label, (name, _)) in enumerate(PAYLOADS.items()) if only in label}
        print("CLI (kitti-eval --gt <demo infos> --pred PAYLOAD), default limits")
        print(f"{'payload':40s} {'exit':>4s} {'peak MiB':>9s}  message")
        for label, path in files.items():
            code, peak, msg = _cli_peak(gt, path)
            print(f"{label:40s} {code:4d} {peak:9.0f}  {msg}")
        server = LiveServer(tmp / "data").start()
        try:
            pid = server.proc.pid  # type: ignore[union-attr]
            time.sleep(1.0)
            idle = _status(pid, "VmRSS")
            print(f"\nservice (uvicorn, default settings): idle {idle:.0f} MiB")
            print(f"{'payload':40s} {'HTTP':>4s} {'peak MiB':>9s} {'after':>7s}  error code")
            with httpx.Client(base_url=server.url, timeout=600) as client:
                for label, path in files.items():
                    Path(f"/proc/{pid}/clear_refs").write_text("5")  # reset the high-water mark
                    with open(path, "rb") as fh:
                        r = client.post("/v1/evaluations", data={"gt": "demo"}, files={"predictions": (path.name, fh)})
                    peak = _status(pid, "VmHWM")
                    time.sleep(2.0)
                    after = _status(pid, "VmRSS")
                    code = r.json().get("error", {}).get("code", "") if r.status_code >= 400 else ""
                    print(f"{label:40s} {r.status_code:4d} {peak:9.0f} {after:7.0f}  {code}")
        finally:
            server.stop()
    return 0


def make(directory: Path, only: str = "") -> None:
    for k, (label, (name, build)) in enumerate(PAYLOADS.items()):
        if only in label:
            (directory / f"{k}-{name}").write_bytes(build())


if __name__ == "__main__":
    if sys.argv[1:2] == ["--make"]:
        make(Path(sys.argv[2]), sys.argv[3])
        sys.exit(0)
    sys.exit(main(sys.argv[2] if sys.argv[1:2] == ["--only"] else ""))
