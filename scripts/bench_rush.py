"""A deadline rush on a hosted benchmark, measured on this machine: 200 submissions from 50 participants sent at
the same moment to a benchmark with a quota of 3 a day, on a KITTI-val-sized sealed test set (3769 frames; a
22 MB result.pkl of about 151,000 detections, as a real detector's). With ``--spread S`` each submission is sent
at a planned moment within S seconds instead, one in each S/200 taken in a random order; either way whether or
not the earlier ones have been answered (an open loop: a slow service does not slow the senders down, so its
delays are all counted). Each submission is sent as a participant sends it from a shell: a ``curl`` process of its
own, the file as a multipart form (``-F``). What it checks and prints:

* every answer is 202 (accepted, ``?wait=0``) or 429 (the quota): exactly 150 and 50, and no 503;
* how long acceptance took to answer, from the planned moment (median, 95th percentile; spread over a window,
  the target is 2 s);
* that all 150 accepted are scored, none lost and none twice (one scored submission and one finished job
  each, no job attempted more than once), and how long the scoring of them all took (evaluations a second),
  beside the library's own rate measured in the same run (``bench_jobs.in_process_rate``).

Two configurations: the default ``kitti-eval serve`` on SQLite (its own workers), and, with ``--postgres``,
3 replicas of ``kitti-eval serve`` without workers of their own and 2 ``kitti-eval worker`` processes on a
throwaway PostgreSQL cluster (Debian's ``postgresql`` binaries), the participants' requests spread over the
replicas.

``--compare PYTHON [--rounds 2]`` measures another checkout's service (the interpreter of its environment, e.g. a
``git worktree`` of the commit before with its own ``pip install -e '.[server]'``) and this one's, alternated, on
SQLite: each rush, and three times each the seconds from starting ``kitti-eval serve`` to its first ``/readyz``
200 (numba's cache warm), then the medians; the load average is printed with each run.

``python scripts/bench_rush.py [--participants 50] [--each 4] [--spread 0] [--postgres] [--dets-per-frame 40.1]
[--compare PYTHON --rounds N]``. Needs ``curl``. Prints the figures; exits 1 when a check fails. Everything runs on
loopback in temporary folders and stops by itself.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import pwd
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
from bench_jobs import _free_port, _stop, generated, in_process_rate  # this folder's

ADMIN = "bench-admin-token"
QUOTA = 3


def _start(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    full = {**os.environ, "KITTI_EVAL_ADMIN_TOKEN": ADMIN, "KITTI_EVAL_LOG_FORMAT": "json", **env}
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, env=full, stdout=out, stderr=subprocess.STDOUT)


def _serve(data: Path, env: dict[str, str], python: str = sys.executable) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    cmd = [python, "-m", "kitti_eval.cli", "serve", "--port", str(port), "--data-dir", str(data)]
    data.mkdir(parents=True, exist_ok=True)
    proc = _start(cmd, {"KITTI_EVAL_AUTH": "accounts", **env}, data.parent / f"serve-{port}.log")
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    proc.terminate()
    raise SystemExit(f"the service did not answer in 180 s (see {data.parent}/serve-{port}.log)")


def _ready(url: str, timeout_s: float = 180) -> None:
    deadline = time.monotonic() + timeout_s
    while httpx.get(f"{url}/readyz", timeout=5).status_code != 200:
        if time.monotonic() > deadline:
            raise SystemExit(f"{url} not ready in {timeout_s:g} s")
        time.sleep(0.2)


class _Postgres:
    """initdb + pg_ctl in a temporary folder on a free loopback port (as ``nobody`` when run as root)."""

    def __init__(self) -> None:
        found = shutil.which("pg_ctl") or next(iter(sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"))[-1:]), None)
        if found is None:
            raise SystemExit("--postgres needs PostgreSQL's binaries (Debian's postgresql package)")
        self.bindir = Path(found).resolve().parent
        self.root = Path(tempfile.mkdtemp(prefix="kitti-eval-rush-pg-"))
        self.port = _free_port()
        self.as_nobody = os.geteuid() == 0
        if self.as_nobody:
            nobody = pwd.getpwnam("nobody")
            os.chown(self.root, nobody.pw_uid, nobody.pw_gid)

    @property
    def url(self) -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/postgres"

    def _run(self, *args: str) -> None:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        if self.as_nobody:
            cmd = ["runuser", "-u", "nobody", "--", *cmd]
        subprocess.run(cmd, cwd=self.root, check=True, capture_output=True, timeout=120)

    def __enter__(self) -> _Postgres:
        data = str(self.root / "data")
        self._run("initdb", "-D", data, "-U", "postgres", "--auth=trust", "-E", "UTF8", "--locale=C", "--no-sync")
        options = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c max_connections=200"
        self._run("pg_ctl", "-D", data, "-o", options, "-l", str(self.root / "log"), "-w", "-t", "60", "start")
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._run("pg_ctl", "-D", str(self.root / "data"), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


def _host(url: str, gt: bytes, participants: int) -> dict[str, str]:
    """Users with tokens, the sealed test set and the benchmark (quota 3 a day); {user: token}."""
    admin = {"Authorization": f"Bearer {ADMIN}"}
    tokens = {}
    with httpx.Client(base_url=url, timeout=600, headers=admin) as c:
        for i in range(participants):
            user = f"team{i:02d}"
            c.post("/v1/admin/users", json={"name": user}).raise_for_status()
            tokens[user] = c.post("/v1/admin/tokens", json={"user": user}).json()["token"]
        files = {"file": ("kitti_infos_test.pkl", gt)}
        c.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=files).raise_for_status()
        body = {"name": "rush", "ground_truth": "test-set", "quota": f"{QUOTA}/1"}
        c.post("/v1/benchmarks", json=body).raise_for_status()
    return tokens


def _schedule(participants: int, each: int, window_s: float, seed: int = 0) -> list[tuple[int, float]]:
    """When each submission is sent: (participant, seconds from the start). The window is cut into as many equal
    slots as there are submissions, one sent at a random moment of each slot, the slots dealt to the
    participants in a random order (each sends ``each``)."""
    rng = random.Random(seed)
    n = participants * each
    owners = [k for k in range(participants) for _ in range(each)]
    rng.shuffle(owners)
    return [(owners[i], window_s * (i + rng.random()) / n) for i in range(n)]


def _curl(url: str, token: str, path: Path) -> tuple[int, str]:
    """One submission as a participant sends it from a shell: a ``curl`` process of its own, the file as a
    multipart form (``-F``; curl asks to continue, ``Expect: 100-continue``, for a body over 1 MB). (status, what:
    the job's id or the error's code)"""
    out = subprocess.run(
        [
            "curl",
            "-sS",
            "-w",
            "\\n%{http_code}",
            "-H",
            f"Authorization: Bearer {token}",
            "-F",
            f"predictions=@{path}",
            f"{url}/v1/benchmarks/rush/submissions?wait=0",
        ],
        capture_output=True,
        timeout=900,
    )
    body, _, code = out.stdout.decode().rpartition("\n")
    status = int(code) if code.isdigit() else 0
    try:
        answer: Any = json.loads(body)
    except ValueError:
        return status, f"curl exit {out.returncode}: {out.stderr.decode().strip()[:200]}"
    return status, str(answer.get("id") if status == 202 else answer.get("error", {}).get("code", "?"))


def _rush(
    urls: list[str], tokens: dict[str, str], path: Path, each: int, window_s: float
) -> list[tuple[str, int, float, str]]:
    """Every participant sends ``each`` submissions, all of them within ``window_s`` seconds (:func:`_schedule`),
    each at its planned moment whatever the answers to the others (an open loop: a slow service does not slow
    the senders), each by a ``curl`` process of its own (:func:`_curl`), to the replicas in turn: (participant,
    status, seconds from the planned moment to the answer, the job's id or the error's code)."""
    users = list(tokens)
    plan = _schedule(len(users), each, window_s)
    start = time.perf_counter() + 0.5

    def send(i: int) -> tuple[str, int, float, str]:
        k, at = plan[i]
        time.sleep(max(0.0, start + at - time.perf_counter()))
        status, what = _curl(urls[i % len(urls)], tokens[users[k]], path)
        return users[k], status, time.perf_counter() - (start + at), what

    with ThreadPoolExecutor(len(plan)) as pool:
        return list(pool.map(send, range(len(plan))))


def _until_scored(url: str, count: int, timeout_s: float) -> tuple[list[dict[str, Any]], float]:
    admin = {"Authorization": f"Bearer {ADMIN}"}
    started = time.perf_counter()
    with httpx.Client(base_url=url, timeout=600, headers=admin) as c:
        while True:
            rows = c.get("/v1/benchmarks/rush/submissions/all").json()["items"]
            if sum(r["status"] in ("scored", "failed") for r in rows) >= count or len(rows) < count:
                return rows, time.perf_counter() - started
            if time.perf_counter() - started > timeout_s:
                return rows, time.perf_counter() - started
            time.sleep(0.5)


def _jobs(url: str) -> list[dict[str, Any]]:
    admin = {"Authorization": f"Bearer {ADMIN}"}
    out: list[dict[str, Any]] = []
    with httpx.Client(base_url=url, timeout=600, headers=admin) as c:
        while True:
            page = c.get("/v1/admin/jobs", params={"limit": 500, "offset": len(out)}).json()["items"]
            out += page
            if len(page) < 500:
                return out


def _run(
    label: str,
    urls: list[str],
    gt: bytes,
    path: Path,
    participants: int,
    each: int,
    window_s: float,
    library: float,
) -> tuple[bool, dict[str, float]]:
    """The rush on the services at ``urls``, its figures printed: (every check passed, {median, p95, scored_s})."""
    tokens = _host(urls[0], gt, participants)
    for url in urls:
        _ready(url)
    t0 = time.perf_counter()
    answers = _rush(urls, tokens, path, each, window_s)
    statuses = Counter(status for _, status, _, _ in answers)
    latencies = sorted(seconds for _, _, seconds, _ in answers)
    p95 = latencies[max(0, int(round(0.95 * len(latencies))) - 1)]
    accepted = [job for _, status, _, job in answers if status == 202]
    rows, scoring = _until_scored(urls[0], len(accepted), timeout_s=1800)
    total = time.perf_counter() - t0
    scored = [r for r in rows if r["status"] == "scored"]
    jobs = [j for j in _jobs(urls[0]) if j["kind"] == "submission"]
    attempts = Counter(j["attempts"] for j in jobs)
    per_user = Counter(r["participant"] for r in rows)
    checks: dict[str, bool] = {
        f"{participants * QUOTA} accepted, {participants * (each - QUOTA)} refused 429, no 503": (
            statuses[202] == participants * QUOTA
            and statuses[429] == participants * (each - QUOTA)
            and sum(statuses.values()) == participants * each
        ),
        "every accepted one scored, each once": (
            len(scored) == len(accepted) == len(rows)
            and {r["id"] for r in scored} == set(accepted)
            and len({r["id"] for r in rows}) == len(rows)
        ),
        f"at most {QUOTA} a participant": max(per_user.values(), default=0) <= QUOTA,
        "one job a submission, all done, none run twice": (
            len(jobs) == len(accepted) and all(j["state"] == "done" for j in jobs) and set(attempts) <= {1}
        ),
    }
    if window_s:  # spread over a window, the acceptance is answered within 2 s (all at once: printed only)
        checks["acceptance answered within 2 s at the 95th percentile"] = p95 <= 2.0
    print(f"\n{label}")
    when = f"within {window_s:g} s" if window_s else "at the same moment"
    print(f"  {len(answers)} submissions sent {when}, a curl process each: {dict(sorted(statuses.items()))}")
    odd = Counter(what for _, status, _, what in answers if status not in (202, 429))
    if odd:
        print(f"  other answers: {dict(odd)}")
    print(
        f"  answered, from the planned moment: median {statistics.median(latencies):.1f} s, "
        f"p95 {p95:.1f} s, max {latencies[-1]:.1f} s"
    )
    print(
        f"  {len(scored)} scored {scoring:.1f} s after the last answer, {total:.1f} s after the first request: "
        f"{len(scored) / total:.2f} evaluations a second ({len(scored) / total / library:.2f}x in-process); "
        f"job attempts {dict(attempts)}"
    )
    for name, ok in checks.items():
        print(f"  [{'ok' if ok else 'FAILED'}] {name}")
    figures = {"median": statistics.median(latencies), "p95": p95, "scored_s": total}
    return all(checks.values()), figures


def readiness(python: str) -> float:
    """Seconds from starting ``kitti-eval serve`` (on an empty data folder; numba's cache as it is, warm once a
    service has run) to its first ``/readyz`` 200, a look every 50 ms."""
    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        cmd = [python, "-m", "kitti_eval.cli", "serve", "--port", str(port), "--data-dir", str(Path(tmp) / "data")]
        started = time.perf_counter()
        proc = _start(cmd, {}, Path(tmp) / "serve.log")
        try:
            while time.perf_counter() - started < 180:
                try:
                    if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                        return time.perf_counter() - started
                except httpx.HTTPError:
                    pass
                if proc.poll() is not None:
                    raise SystemExit(f"the service exited: {(Path(tmp) / 'serve.log').read_text()[-2000:]}")
                time.sleep(0.05)
            raise SystemExit("the service was not ready in 180 s")
        finally:
            _stop(proc)


def _sqlite_rush(python: str, gt: bytes, path: Path, args: argparse.Namespace, library: float, label: str):
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        proc, url = _serve(Path(tmp) / "data", dict(v.split("=", 1) for v in args.env), python)
        stack.callback(_stop, proc)
        return _run(label, [url], gt, path, args.participants, args.each, args.spread, library)


def _loadavg() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _compare(other: str, rounds: int, gt: bytes, path: Path, args: argparse.Namespace, library: float) -> bool:
    """The rush and the readiness of the service run by ``other`` (another checkout's interpreter) and by this
    one, alternated ``rounds`` times (the other first in odd rounds): each run's figures, then their medians."""
    pythons = {"other": other, "this": sys.executable}
    runs: dict[str, list[dict[str, float]]] = {"other": [], "this": []}
    ok = True
    for r in range(rounds):
        for name in ("other", "this") if r % 2 == 0 else ("this", "other"):
            ready = [readiness(pythons[name]) for _ in range(3)]
            print(f"\n[round {r + 1}, {name}: {pythons[name]}; load average {_loadavg()}]")
            print(f"  ready (/readyz 200) {', '.join(f'{x:.1f}' for x in ready)} s after the start")
            good, figures = _sqlite_rush(pythons[name], gt, path, args, library, f"round {r + 1}: {name}")
            ok &= good
            runs[name].append({**figures, "ready": statistics.median(ready)})
    print("\nsummary (each run; the median of the runs)")
    for name, items in runs.items():
        for key in ("median", "p95", "scored_s", "ready"):
            values = [f[key] for f in items]
            print(
                f"  {name} {key:>8}: {', '.join(f'{v:.1f}' for v in values)} s (median {statistics.median(values):.1f})"
            )
    return ok


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--participants", type=int, default=50)
    p.add_argument("--each", type=int, default=4, help="submissions each participant sends (the quota is 3)")
    p.add_argument("--dets-per-frame", type=float, default=40.1, help="10: the 6.6 MB result.pkl of earlier runs")
    p.add_argument("--spread", type=float, default=0.0, help="seconds over which they are sent (0: all at once)")
    p.add_argument("--postgres", action="store_true", help="also 3 replicas and 2 workers on PostgreSQL")
    p.add_argument("--skip-sqlite", action="store_true")
    p.add_argument(
        "--compare",
        metavar="PYTHON",
        help="another checkout's interpreter: its service and this one's "
        "alternated (SQLite), with the time each takes to be ready",
    )
    p.add_argument("--rounds", type=int, default=2, help="with --compare: alternations")
    p.add_argument("--env", action="append", default=[], metavar="NAME=VALUE", help="a setting of the service (SQLite)")
    p.add_argument("--skip-library", action="store_true", help="do not measure the library's rate first")
    args = p.parse_args(argv)
    if shutil.which("curl") is None:
        raise SystemExit("the participants send with curl: install it (Debian's curl package)")
    gt, pred = generated(args.dets_per_frame)
    print(f"{os.cpu_count()} cores, load average {_loadavg()}; a {len(pred) / 1e6:.1f} MB result.pkl of 3769 frames")
    library = float("nan") if args.skip_library else in_process_rate(gt, pred)
    print(f"in-process (the library): {library:.2f} evaluations a second (load + evaluate, a process a CPU)")
    ok = True
    with tempfile.TemporaryDirectory() as files:
        path = Path(files) / "result.pkl"
        path.write_bytes(pred)
        if args.compare:
            return 0 if _compare(args.compare, args.rounds, gt, path, args, library) else 1
        if not args.skip_sqlite:
            ok &= _sqlite_rush(sys.executable, gt, path, args, library, "kitti-eval serve (SQLite, its own workers)")[0]
        if args.postgres:
            with tempfile.TemporaryDirectory() as tmp, _Postgres() as pg, ExitStack() as stack:
                env = {"KITTI_EVAL_DATABASE_URL": pg.url, "KITTI_EVAL_JOB_THREADS": "0"}
                urls = []
                for i in range(3):
                    proc, url = _serve(Path(tmp) / f"replica{i}", env)
                    stack.callback(_stop, proc)
                    urls.append(url)
                worker = [
                    sys.executable,
                    "-m",
                    "kitti_eval.cli",
                    "worker",
                    "--database-url",
                    pg.url,
                    "--processes",
                    "2",
                ]
                stack.callback(_stop, _start(worker, {}, Path(tmp) / "worker.log"))
                label = "3 replicas of kitti-eval serve, 2 kitti-eval worker processes, PostgreSQL"
                ok &= _run(label, urls, gt, path, args.participants, args.each, args.spread, library)[0]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
