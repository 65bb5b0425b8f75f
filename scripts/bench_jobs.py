"""Evaluations as jobs, measured on this machine: a real ``kitti-eval serve`` on a KITTI-val-sized generated set
(3769 frames; a 22 MB result.pkl of about 151,000 detections, as a real detector's above OpenPCDet's 0.1 score
threshold, like the golden ``kitti_val_scale`` case), uploads from several clients at once, beside the library's
own rate measured in the same run.

* throughput: evaluations finished per second, from the first acceptance to the last result, of uploads
  (``POST /v1/evaluations``) and of benchmark submissions (accounts mode, a participant a client), for the default
  ``kitti-eval serve`` (a worker process of its own a CPU), for one whose web process runs the jobs on two
  threads, and for one with no worker of its own beside ``kitti-eval worker --processes N`` (``--processes``);
* acceptance: how long ``POST /v1/evaluations?wait=0`` takes to answer 202 while the workers are busy (median
  and 95th percentile): accepting never waits for a free evaluator;
* the in-process rate: one process a CPU, each with the ground truth loaded, loading the same result.pkl from
  disk and evaluating it again and again (what the library does for an upload), measured just before and just
  after each configuration (the machine's other load varies); each service figure is also given as a share of
  their mean, and the CPU the service's processes used an upload beside the library's CPU an evaluation (a
  figure others' load changes far less than the rates).

The clients stand for machines elsewhere, but run on the cores the service is measured on: each request's body
is encoded once, before the clock starts, and sent with the standard library's ``http.client``, which hands it to
the socket as it is; the CPU they use is printed beside the service's. The benchmark sends the same file each
time, which the service keeps once (``--distinct``: a file of its own each time, as at a deadline, each kept).

``python scripts/bench_jobs.py [--uploads 40] [--clients 4] [--processes 2] [--kind uploads|submissions|both]
[--dets-per-frame 40.1] [--distinct]`` (``--dets-per-frame 10``: the 6.6 MB file of earlier figures).
Prints the figures; exits 0.
Everything runs on loopback in a temporary folder and stops by itself.
"""

from __future__ import annotations

import argparse
import http.client
import os
import pickle
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from kitti_eval.synth import generate

ADMIN = "bench-admin-token"


def generated(dets_per_frame: float) -> tuple[bytes, bytes]:
    """The ground truth (infos) and result pickles of the generated 3769-frame set."""
    infos, results = generate(3769, seed=0, dets_per_frame=dets_per_frame)
    return pickle.dumps(infos, protocol=4), pickle.dumps(results, protocol=4)


def _library_evaluations(gt_path: str, pred_path: str, seconds: float) -> tuple[int, float, float]:
    """In one process: the ground truth loaded once (and the kernels warmed by a first evaluation), then the
    result.pkl loaded and evaluated again and again for ``seconds``: (evaluations, seconds taken, CPU seconds)."""
    from kitti_eval import evaluate, load_detections, load_ground_truth

    gt = load_ground_truth(gt_path)
    evaluate(gt, load_detections(pred_path))
    count, started, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - started < seconds:
        evaluate(gt, load_detections(pred_path))
        count += 1
    return count, time.perf_counter() - started, time.process_time() - cpu


def in_process(gt: bytes, pred: bytes, seconds: float = 20.0) -> tuple[float, float]:
    """The library itself, one process a CPU, each loading and evaluating the file: (evaluations a second, CPU
    seconds an evaluation)."""
    from concurrent.futures import ProcessPoolExecutor

    cpus = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        gt_path, pred_path = Path(tmp) / "kitti_infos_val.pkl", Path(tmp) / "result.pkl"
        gt_path.write_bytes(gt)
        pred_path.write_bytes(pred)
        with ProcessPoolExecutor(cpus) as pool:
            runs = list(
                pool.map(_library_evaluations, [str(gt_path)] * cpus, [str(pred_path)] * cpus, [seconds] * cpus)
            )
    return sum(n / took for n, took, _ in runs), sum(cpu for _, _, cpu in runs) / max(1, sum(n for n, _, _ in runs))


def in_process_rate(gt: bytes, pred: bytes, seconds: float = 20.0) -> float:
    """Evaluations a second of the library itself, one process a CPU (each loading and evaluating the file)."""
    return in_process(gt, pred, seconds)[0]


def _cpu_of(pids: list[int]) -> float | None:
    """CPU seconds used so far by the processes and all their descendants (Linux's /proc; None elsewhere)."""
    total, seen, todo = 0.0, set(), list(pids)
    try:
        while todo:
            pid = todo.pop()
            if pid in seen:
                continue
            seen.add(pid)
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            for children in Path(f"/proc/{pid}/task").glob("*/children"):
                todo += [int(c) for c in children.read_text().split()]
    except (OSError, ValueError, IndexError):
        return None
    return total


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(
    data: Path, port: int, env: dict[str, str], started: Callable[[], None] | None = None
) -> subprocess.Popen[bytes]:
    """``kitti-eval serve`` on ``data``, once ready; ``started`` is called once it answers (and its database
    exists), before it is ready (a service without workers of its own is ready once one is there)."""
    full = {**os.environ, "KITTI_EVAL_ADMIN_TOKEN": ADMIN, "KITTI_EVAL_LOG_FORMAT": "json", **env}
    cmd = [sys.executable, "-m", "kitti_eval.cli", "serve", "--port", str(port), "--data-dir", str(data)]
    proc = subprocess.Popen(cmd, env=full, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 180
    for path in ("/healthz", "/readyz"):
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}{path}", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                proc.terminate()
                raise SystemExit("the service did not become ready in 180 s")
            time.sleep(0.2)
        if path == "/healthz" and started is not None:
            started()
    return proc


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()


def _prepare(c: httpx.Client, kind: str, gt: bytes, clients: int) -> list[dict[str, str]]:
    """The ground truth registered (and for submissions a benchmark on it, with a participant a client); the
    headers each client sends."""
    admin = {"Authorization": f"Bearer {ADMIN}"}
    if kind == "uploads":
        files = {"file": ("kitti_infos_val.pkl", gt)}
        c.post("/v1/ground-truths", data={"name": "val"}, files=files, headers=admin).raise_for_status()
        return [{}] * clients
    headers = []
    for i in range(clients):
        c.post("/v1/admin/users", json={"name": f"team{i}"}, headers=admin).raise_for_status()
        token = c.post("/v1/admin/tokens", json={"user": f"team{i}"}, headers=admin).json()["token"]
        headers.append({"Authorization": f"Bearer {token}"})
    files = {"file": ("kitti_infos_test.pkl", gt)}
    c.post("/v1/ground-truths", data={"name": "val", "sealed": "true"}, files=files, headers=admin).raise_for_status()
    body = {"name": "bench", "ground_truth": "val", "quota": "1000/1"}
    c.post("/v1/benchmarks", json=body, headers=admin).raise_for_status()
    return headers


def _encode(pred: bytes, data: dict[str, str] | None = None) -> tuple[bytes, str]:
    """A multipart body with ``pred`` as the ``predictions`` file (and the form fields ``data``), encoded once:
    the clients stand for machines elsewhere, whose encoding is not the service's work. (body, content type)"""
    files = {"predictions": ("result.pkl", pred, "application/octet-stream")}
    request = httpx.Request("POST", "http://x/", data=data, files=files)
    return request.read(), request.headers["content-type"]


def _encoded(kind: str, pred: bytes) -> tuple[str, bytes, str]:
    """The request's path, body and content type."""
    if kind == "uploads":
        return ("/v1/evaluations", *_encode(pred, {"gt": "val"}))
    return ("/v1/benchmarks/bench/submissions", *_encode(pred))


def _post(port: int, request: tuple[str, bytes, str], headers: dict[str, str]) -> tuple[int, bytes]:
    """The upload as a client elsewhere sends it, with the least of this machine's CPU: the standard library's
    ``http.client`` hands the encoded body to the socket as it is. (httpx, through h11, spent ~44 ms of CPU an
    upload of a 22 MB file in this process, on the cores the service is measured on.) (status, body)"""
    path, body, content_type = request
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
    try:
        conn.request("POST", f"{path}?wait=0", body=body, headers={**headers, "Content-Type": content_type})
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def _last_finished(c: httpx.Client, count: int) -> float:
    """When the last of the ``count`` newest jobs finished, as the service recorded it (seconds since the epoch):
    the run's end to the job, not to the next look at the counts (a look every 0.25 s overstated a 10 s run by
    0.125 s on average, and looking more often costs the service's CPU)."""
    from datetime import datetime

    jobs = c.get("/v1/admin/jobs", params={"limit": count}, headers={"Authorization": f"Bearer {ADMIN}"}).json()
    return max(datetime.fromisoformat(j["finished_at"]).timestamp() for j in jobs["items"])


def variants(pred: bytes, count: int) -> list[bytes]:
    """``count`` result.pkl files that differ from ``pred`` and from each other in one detection's score (the
    first one, set to 1e-4, 2e-4, ...): the service keeps each of them (it keeps a file once by its content)."""
    results = pickle.loads(pred)  # the pickle made just above by this script
    scores = next(r["score"] for r in results if len(r["score"]))
    out = []
    for i in range(count):
        scores[0] = (i + 1) * 1e-4
        out.append(pickle.dumps(results, protocol=4))
    return out


def _run(
    label: str,
    kind: str,
    env: dict[str, str],
    gt: bytes,
    pred: bytes,
    uploads: int,
    clients: int,
    *,
    workers: int = 0,
    library: Callable[[], tuple[float, float]] | None = None,
    distinct: bool = False,
) -> None:
    """``kind``: uploads (``POST /v1/evaluations``) or benchmark submissions, ``uploads`` of them from ``clients``
    clients at once; ``workers``: a ``kitti-eval worker --processes N`` beside the service, on its SQLite
    database. An evaluation for each worker process first, sent at once, to warm them (as a service that has been
    running is); then the clock runs from the first request to the moment the service recorded the last job done
    (the counts are looked at every 0.25 s until all are done), and the CPU the service's processes use meanwhile
    is counted (the web process, its worker processes, ``kitti-eval worker``), and the clients' (this process's)."""
    env = {**env, "KITTI_EVAL_AUTH": "accounts" if kind == "submissions" else "open"}
    before = library() if library else None  # the library's rate just before and just after: others' load varies
    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        data = Path(tmp) / "data"
        worker: list[subprocess.Popen[bytes]] = []

        def start_workers() -> None:
            cmd = [sys.executable, "-m", "kitti_eval.cli", "worker", "--data-dir", str(data)]
            cmd += ["--processes", str(workers)]
            worker.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

        proc = _serve(data, port, env, start_workers if workers else None)
        base = f"http://127.0.0.1:{port}"
        admin = {"Authorization": f"Bearer {ADMIN}"}
        try:
            with httpx.Client(base_url=base, timeout=600) as c:
                headers = _prepare(c, kind, gt, clients)

                def done() -> int:
                    counts = c.get("/v1/admin/jobs", params={"limit": 1}, headers=admin).json()["counts"]
                    assert not counts.get("failed"), counts
                    return int(counts.get("done", 0))

                request = _encoded(kind, pred)
                requests = [_encoded(kind, f) for f in variants(pred, uploads)] if distinct else [request] * uploads
                warm = max(2, workers)  # one for each worker process: its kernels loaded, the ground truth read
                for i in range(warm):
                    status, text = _post(port, request, headers[i % clients])
                    assert status in (201, 202), text[:300]
                while done() < warm:
                    time.sleep(0.1)
                cpu_before = _cpu_of([proc.pid, *(w.pid for w in worker)])

                def accept(i: int) -> float:
                    t0 = time.perf_counter()
                    status, text = _post(port, requests[i], headers[i % clients])
                    assert status in (201, 202), text[:300]
                    return time.perf_counter() - t0

                started_at, client_before = time.time(), os.times()
                with ThreadPoolExecutor(clients) as pool:
                    latencies = sorted(pool.map(accept, range(uploads)))
                while done() < uploads + warm:
                    time.sleep(0.25)
                cpu_after = _cpu_of([proc.pid, *(w.pid for w in worker)])
                client_after = os.times()
                wall = _last_finished(c, uploads) - started_at  # the service runs here: one clock
        finally:
            _stop(proc)
            for w in worker:
                _stop(w)
    p95 = latencies[max(0, int(round(0.95 * len(latencies))) - 1)]
    share = cpu = ""
    if library and before:
        after = library()
        rate = (before[0] + after[0]) / 2
        share = f" ({uploads / wall / rate:.2f}x in-process: {before[0]:.2f} before, {after[0]:.2f} after)"
        if cpu_before is not None and cpu_after is not None:
            service_cpu, library_cpu = (cpu_after - cpu_before) / uploads, (before[1] + after[1]) / 2
            client_cpu = (sum(client_after[:2]) - sum(client_before[:2])) / uploads
            cpu = (
                f"; CPU an upload {service_cpu * 1000:.0f} ms, the library's {library_cpu * 1000:.0f} ms "
                f"({library_cpu / service_cpu:.2f}x); the clients' {client_cpu * 1000:.0f} ms"
            )
    what = kind + (", distinct files" if distinct else "")
    print(
        f"{label:<28} {what:<11} {uploads} in {wall:5.1f} s: {uploads / wall:4.2f} a second{share}; "
        f"acceptance median {statistics.median(latencies) * 1000:5.0f} ms, p95 {p95 * 1000:5.0f} ms{cpu}"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--uploads", type=int, default=40)
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--dets-per-frame", type=float, default=40.1, help="10: the 6.6 MB result.pkl of earlier runs")
    p.add_argument("--processes", type=int, default=2, help="worker processes of the third configuration")
    p.add_argument("--kind", choices=["uploads", "submissions", "both"], default="both")
    p.add_argument("--skip-threads", action="store_true", help="leave out the two-threads configuration")
    p.add_argument("--skip-workers", action="store_true", help="leave out the kitti-eval worker configuration")
    p.add_argument(
        "--distinct",
        action="store_true",
        help="every upload a file of its own (one score differs), as at a deadline: the service keeps each "
        "(default: the same file, kept once)",
    )
    args = p.parse_args(argv)
    gt, pred = generated(args.dets_per_frame)
    print(f"{os.cpu_count()} cores; {len(pred) / 1e6:.1f} MB result.pkl, 3769 frames")

    def library() -> tuple[float, float]:
        return in_process(gt, pred, seconds=15)

    kinds = ["uploads", "submissions"] if args.kind == "both" else [args.kind]
    threads = {"KITTI_EVAL_WORKER_PROCESSES": "0", "KITTI_EVAL_JOB_THREADS": "2"}
    none = {"KITTI_EVAL_WORKER_PROCESSES": "0", "KITTI_EVAL_JOB_THREADS": "0"}

    def run(label: str, kind: str, env: dict[str, str], workers: int = 0) -> None:
        _run(
            label,
            kind,
            env,
            gt,
            pred,
            args.uploads,
            args.clients,
            workers=workers,
            library=library,
            distinct=args.distinct,
        )

    for kind in kinds:
        run("kitti-eval serve (default)", kind, {})
        if not args.skip_threads:
            run("2 worker threads, no process", kind, threads)
        if not args.skip_workers:
            run(f"{args.processes} kitti-eval worker procs", kind, none, workers=args.processes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
