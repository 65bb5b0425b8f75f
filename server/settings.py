"""Service settings: environment variables ``KITTI_EVAL_*`` (or keyword arguments in tests)."""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

import platformdirs
from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from kitti_eval.core.cpus import available_cpus

__all__ = [
    "Settings",
    "AuthMode",
    "ENV_PREFIX",
    "NoDataFolder",
    "default_data_dir",
    "default_data_dir_text",
    "settings_error",
    "serve_overrides",
]

ENV_PREFIX = "KITTI_EVAL_"
_MB = 1 << 20


class AuthMode(str, Enum):
    """``KITTI_EVAL_AUTH``: ``open`` (no accounts: everyone is everyone) or ``accounts``."""

    OPEN = "open"
    ACCOUNTS = "accounts"


class NoDataFolder(ValueError):
    """No data folder is set and the user's cannot be found (no HOME, and a uid without a home of its own)."""


def default_data_dir() -> Path:
    """The user's data folder for kitti-eval (``~/.local/share/kitti-eval`` or ``$XDG_DATA_HOME/kitti-eval``
    on Linux, ``~/Library/Application Support/kitti-eval`` on macOS, ``%LOCALAPPDATA%\\kitti-eval`` on
    Windows): never the working directory, where a ``git add .`` would pick up the admin token. Asked only when
    no data folder is set; without a home (``env -i``, a uid with no entry in /etc/passwd) it raises
    :class:`NoDataFolder`, which says to set one."""
    try:
        return Path(platformdirs.user_data_dir("kitti-eval", appauthor=False))
    except RuntimeError:  # platformdirs: no HOME, and none in the user database
        raise NoDataFolder(
            "no data folder: KITTI_EVAL_DATA_DIR (or --data-dir) is unset and the user's data folder is unknown "
            f"without a home (HOME is unset and uid {os.getuid()} has none): set KITTI_EVAL_DATA_DIR"
        ) from None


def default_data_dir_text() -> str:
    """The default data folder as a help text names it, without failing where there is no home."""
    try:
        return str(default_data_dir())
    except NoDataFolder:
        return "the user's data folder; none here, as there is no HOME: set it"


def settings_error(error: ValueError) -> str:
    """What a command says when its settings are refused: pydantic's list of fields, or :class:`NoDataFolder`."""
    if isinstance(error, NoDataFolder):
        return f"error: {error}"
    return f"error: invalid settings:\n{error}"


def serve_overrides(
    data_dir: str | None, database_url: str | None, auth: str | None, upgrade: bool, environ: Mapping[str, str]
) -> dict[str, Any]:
    """What ``kitti-eval serve``'s options change in the settings. Unless ``KITTI_EVAL_WORKER_PROCESSES`` or
    ``KITTI_EVAL_JOB_THREADS`` is set, one command uses the machine: a worker process a CPU (evaluations in
    parallel processes, not threads of one, whose pickle loading shares one interpreter lock), none of the web
    process's own."""
    given = (("data_dir", data_dir), ("database_url", database_url), ("auth", auth), ("db_upgrade", upgrade))
    overrides: dict[str, Any] = {k: v for k, v in given if v}
    if "KITTI_EVAL_WORKER_PROCESSES" not in environ and "KITTI_EVAL_JOB_THREADS" not in environ:
        overrides.update(worker_processes=available_cpus(), job_threads=0)
    return overrides


class Settings(BaseSettings):
    """Everything the service can be told; each field is also ``KITTI_EVAL_<FIELD>`` in the environment."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX, extra="ignore", env_ignore_empty=True, validate_default=True
    )

    data_dir: Path = Field(default_factory=default_data_dir)
    """Holds the SQLite database (when ``database_url`` is unset), unpacked copies of registered ground truths
    (the files themselves are in the database), the generated admin token, the scratch space of uploads being
    processed (``tmp/``) and the locks that tell whose scratch folders they are (``run/``: what a killed
    process left is removed at the next start)."""

    database_url: str | None = None
    """SQLAlchemy URL. Unset: ``sqlite:///<data_dir>/kitti-eval.db`` (WAL). ``postgresql://user:pw@host/db``
    uses PostgreSQL through psycopg 3."""

    db_upgrade: bool = False
    """Upgrade an older database's schema at start (in one transaction, under a lock, by the first process to
    start), instead of refusing to start with one sentence naming ``kitti-eval admin db upgrade``. A database
    that a newer release upgraded is refused either way. ``kitti-eval serve --upgrade`` sets it."""

    database_busy_s: Annotated[float, Field(gt=0)] = 10.0
    """SQLite: how long a request keeps trying while another process holds the database's write lock (a CLI
    command, another worker, a backup), in attempts of at most 1 s with short pauses between; past that it
    gets 503 ``database_unavailable`` with Retry-After. Not used with PostgreSQL."""

    max_upload_mb: Annotated[float, Field(gt=0)] = 200.0
    """Largest request body accepted (all uploaded files together); larger ones get 413."""

    max_unpacked_mb: Annotated[float, Field(gt=0)] = 512.0
    """Largest decompressed pickle, and largest total unpacked size of an archive (zip-bomb guard)."""

    max_archive_members: Annotated[int, Field(gt=0)] = 20_000
    """Most members (files and folders) an uploaded zip or tar may have. KITTI val has 3769 frames."""

    max_concurrent_evals: Annotated[int, Field(gt=0)] = 2
    """Uploads read and stored as jobs at the same time, each on a thread of its own (the workers run the
    evaluations: ``job_threads``, ``worker_processes``, ``kitti-eval worker``)."""

    wait_s: Annotated[float, Field(ge=0, le=3600)] = 600.0
    """How long ``POST /v1/evaluations`` waits for its result when the request does not say (``wait``): 201 with
    the evaluation when it is done by then, else 202 with the job to poll."""

    job_threads: Annotated[int, Field(ge=0)] = 2
    """Workers in the service's own process that run the accepted evaluations (0: none; ``kitti-eval worker``
    processes on this or other machines run them)."""

    worker_processes: Annotated[int, Field(ge=0)] = 0
    """Worker processes the service starts with itself (``kitti-eval serve``, or any process running the app),
    one thread each, stopped (drained) with it: one command uses the machine's cores. 0: only the threads of
    ``job_threads`` (and any ``kitti-eval worker``). Each process of ``uvicorn --workers`` would start its own."""

    worker_nice: Annotated[int, Field(ge=0, le=19)] = 10
    """How much a worker process (``kitti-eval worker``, and the service's own) lowers its scheduling priority
    (``nice``) once its kernels are warm, before it takes a job: on a machine it shares with a web process,
    accepting requests comes before evaluating them, so a rush is answered at once and evaluated right after,
    while a start (which accepts nothing yet) is not slowed. 0: the same priority."""

    job_lease_s: Annotated[float, Field(gt=0)] = 30.0
    """How long a worker holds a job without a heartbeat (it beats every third of it); a worker that stops
    loses its job to another once it has run out."""

    job_max_attempts: Annotated[int, Field(ge=1)] = 3
    """Attempts of a job whose worker was lost or failed on something other than its input."""

    max_queued_evals: Annotated[int, Field(ge=0)] = 256
    """Requests that wait for their result at once (``wait``); past that a request is answered 202 at once with
    its job to poll. It bounds the connections held open, never what is accepted: a waiting request holds no
    evaluator, and accepting never waits for one."""

    job_timeout_s: Annotated[float, Field(gt=0)] = 1800.0
    """How long a job may run: one still running past it is failed then with its reason (``job_timeout``), not
    tried again, and its worker's place is taken by a new thread at once (the late one's result is not stored).
    KITTI val's evaluation takes a few seconds; the limits on work bound what a job asks for, this its time."""

    max_queued_jobs: Annotated[int, Field(gt=0)] = 2000
    """Jobs queued or running, all callers together; past that an evaluation or a submission is answered 503
    ``queue_full`` with Retry-After (nothing of it is kept or counted)."""

    max_queued_per_caller: Annotated[int, Field(gt=0)] = 20
    """Jobs of one user queued or running (accounts mode); past that 429 ``too_many_queued`` with Retry-After."""

    max_queued_input_mb: Annotated[float, Field(gt=0)] = 4096.0
    """Uploaded inputs of the jobs not yet ended, kept in the database until their job ends; past that 503
    ``queue_full`` with Retry-After."""

    retry_after_s: Annotated[int, Field(ge=1)] = 2
    """The Retry-After a 503 carries."""

    body_timeout_s: Annotated[float, Field(gt=0)] = 120.0
    """Time a request body may take to arrive in full; a slower one is answered 408 and its connection closed.
    A body is received before its request takes an evaluation place, so slow senders hold no evaluation place,
    only a receiving one (``max_receiving_bodies``) and for this long at most. 120 s is 200 MB at 1.7 MB/s."""

    body_memory_mb: Annotated[float, Field(ge=0)] = 256.0
    """Request bodies kept in memory, all together, while they arrive and until their request is answered. A body
    that declares its length waits for room (``body_memory_wait_s``); one that would pass it still goes to a
    temporary file in the data folder. An uploaded file whose body was kept in memory stays in memory; of one on
    disk, a file of up to 16 MB (KITTI val's result.pkl is 6.6 MB)."""

    body_memory_wait_s: Annotated[float, Field(ge=0)] = 60.0
    """How long a body of declared length (up to ``body_memory_mb``) waits, unread, for the bodies before it to
    give back room in memory before it goes to a temporary file instead (0: never waits). Received from memory,
    a val-sized upload costs the web process half what one written to disk and read back twice costs."""

    max_receiving_bodies: Annotated[int | None, Field(gt=0)] = None
    """Request bodies received at the same time; a request past that waits its turn, its body unread, for up to
    ``receive_wait_s``. Unset: 64, or four times ``max_concurrent_evals`` when that is more."""

    max_receiving_per_client: Annotated[int, Field(ge=0)] = 16
    """Of those, the bodies one client address (as ``KITTI_EVAL_TRUSTED_PROXIES`` tells it) may send at once; its
    next waits, unread, for one of its own to end (within ``receive_wait_s``), so that one client's connections that
    send nothing cannot hold every turn until their deadline. 0: no limit of a client's own."""

    receive_wait_s: Annotated[float, Field(ge=0)] = 300.0
    """How long a request waits for its turn to send its body (past ``max_receiving_bodies``) before it is answered
    503 ``busy`` with Retry-After. A benchmark submission over its quota never waits: it is answered at once."""

    idempotency_key_hours: Annotated[float, Field(gt=0)] = 24.0
    """How long an ``Idempotency-Key`` sent with an evaluation or a submission is kept: sent again within it, with
    the same request, it is answered with the first request's job (the same id, no second record or quota count);
    after it, the key is a new one."""

    admin_token: SecretStr | None = None
    """Bearer token for registering and deleting ground truths. Unset: one is generated on first start and
    kept in ``<data_dir>/admin-token`` (readable by the server's user only); replicas sharing a database must
    all be given the same one."""

    auth: AuthMode = AuthMode.OPEN
    """``open``: everyone who reaches the service sees and changes everything but the ground truths (which
    need the admin token). ``accounts``: every request but those to the routes declared public (the probes,
    the static files, the sign-in page, public benchmarks' boards) needs a token (``kitti-eval admin token
    add``), and sees only its projects' work (:mod:`kitti_eval_server.access.policy`)."""

    allow_open_with_accounts: bool = False
    """Open mode on a database that holds accounts (users, or tokens not revoked: made in accounts mode) serves
    all of every project to anyone; the service refuses to start so unless this is set."""

    auth_max_failures: Annotated[int, Field(ge=1)] = 10
    """Accounts mode: refused tokens one client address may send within ``auth_failure_window_s`` before it
    gets 429 for the rest of the window (counted by each process on its own)."""

    auth_failure_window_s: Annotated[float, Field(gt=0)] = 60.0
    """The window of ``auth_max_failures``."""

    join_max_attempts: Annotated[int, Field(ge=1)] = 30
    """Accounts mode: attempts to join by an invitation (``/join/CODE``, ``/v1/join/CODE``) one client address may
    make within ``join_window_s``, made or refused, before it gets 429 for the rest of the window (counted by each
    process on its own). A class behind one address joins at this pace."""

    join_window_s: Annotated[float, Field(gt=0)] = 60.0
    """The window of ``join_max_attempts``."""

    trusted_proxies: str = ""
    """The reverse proxies in front of the service: IP addresses or CIDR networks, comma-separated (e.g.
    ``10.0.0.5,fd00::/64``). A request whose socket peer is one of them is taken to come from the right-most
    address of its ``X-Forwarded-For`` that is not itself one of them (the failure limit, the audit log and the
    log lines name that address). Empty: no one is trusted, and the socket peer is the client."""

    session_hours: Annotated[float, Field(gt=0, le=24 * 365)] = 12.0
    """How long a web sign-in lasts (never beyond the token it was made with)."""

    gt_cache_entries: Annotated[int, Field(ge=1)] = 4
    """Ground-truth sets kept loaded in memory (least recently used ones are dropped first)."""

    gt_cache_mb: Annotated[float, Field(gt=0)] = 2048.0
    """Memory the cached ground-truth sets may take together (the arrays' size)."""

    keep_predictions: bool = True
    """Keep each uploaded predictions file (once per content, in the database) so that the frames of an
    evaluation against a registered ground truth can be looked at later (``/v1/evaluations/{id}/frames``,
    ``/v1/frames/{frame}``, the web page's frame view). Off: only the scores are kept."""

    pred_cache_entries: Annotated[int, Field(ge=1)] = 4
    """Kept predictions held loaded in memory for looking at frames (least recently used dropped first)."""

    frames_max_boxes: Annotated[int, Field(gt=0)] = 1_000_000
    """The most boxes kept predictions may hold for their frames to be looked at (``/v1/evaluations/{id}/frames``,
    ``/v1/frames/{frame}``, the web page's frame view), which reads them whole, once, in the process that answers
    (then keeps them in ``pred_cache_entries``); more are refused 413 at the frame that passes it. KITTI val's
    predictions hold about 150,000 boxes; a frame listing of 1,000,000 boxes of txt peaked at 922 MB in a fresh
    process (docs/service/operations.md)."""

    register_demo: bool = True
    """Register the bundled 200-frame demo ground truth as ``demo`` at startup (if absent)."""

    warmup: bool = True
    """Evaluate the demo once at startup, in the background, so the first request does not compile the
    kernels; ``/readyz`` answers 200 once it is done."""

    shutdown_grace_s: Annotated[float, Field(gt=0)] = 30.0
    """On SIGTERM (``kitti-eval serve``): ``/readyz`` answers 503 at once, new evaluation requests 503 with
    Retry-After, and the evaluations already admitted finish and are committed; the process exits when they
    have, or after this long at most."""

    metrics: Literal["on", "off"] = "on"
    """``GET /metrics`` in Prometheus' text format (see docs/service/operations.md); ``off`` answers 404 there."""

    metrics_token: SecretStr | None = None
    """When set, ``/metrics`` needs ``Authorization: Bearer <this>`` (a scraper's own token, not the admin's)."""

    log_format: Literal["auto", "json", "text"] = "auto"
    """The service's log lines (one a request, and its own messages): ``json`` lines, human-readable ``text``,
    or ``auto``: text on a terminal, JSON otherwise (a container, a file, a log shipper)."""

    @field_validator("database_url")
    @classmethod
    def _normalise_url(cls, url: str | None) -> str | None:
        """``postgres://`` and ``postgresql://`` mean psycopg 3 (SQLAlchemy's default driver is psycopg2)."""
        if url is None:
            return None
        for prefix in ("postgres://", "postgresql://"):
            if url.startswith(prefix):
                return "postgresql+psycopg://" + url[len(prefix) :]
        return url

    @field_validator("trusted_proxies")
    @classmethod
    def _check_proxies(cls, text: str) -> str:
        """Each entry an address or a network (``10.0.0.0/8``; host bits set are refused), written normalised."""
        return ",".join(str(network) for network in _networks(text))

    @property
    def trusted_networks(self) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
        return _networks(self.trusted_proxies)

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir.resolve() / 'kitti-eval.db'}"

    @property
    def database_name(self) -> str:
        """The database as the start's log and ``kitti-eval admin`` name it: SQLite's file, or the URL without
        its password."""
        from sqlalchemy.engine import make_url

        url = make_url(self.resolved_database_url)
        if url.get_backend_name() == "sqlite":
            return str(url.database)
        return url.render_as_string(hide_password=True)

    @property
    def receiving_bodies(self) -> int:
        return self.max_receiving_bodies or max(64, 4 * self.max_concurrent_evals)

    @property
    def body_memory_bytes(self) -> int:
        return int(self.body_memory_mb * (1 << 20))

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * _MB)

    @property
    def max_unpacked_bytes(self) -> int:
        return int(self.max_unpacked_mb * _MB)

    @property
    def gt_cache_bytes(self) -> int:
        return int(self.gt_cache_mb * _MB)


def _networks(text: str) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
    out = []
    for item in (part.strip() for part in text.split(",")):
        if item:
            try:
                out.append(ipaddress.ip_network(item))
            except ValueError as e:
                raise ValueError(f"{item!r} is not an IP address or network: {e}") from None
    return tuple(out)
