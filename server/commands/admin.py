"""``kitti-eval admin``: users, projects, memberships, tokens, ground truths, jobs and the audit log of the service,
run on the server's machine against its database (the service's settings: ``KITTI_EVAL_DATA_DIR``,
``KITTI_EVAL_DATABASE_URL``, or ``--data-dir``/``--database-url``).

Every run names its database on stderr, and refuses one that does not exist unless ``--create`` is given (a
new database would hold none of the service's accounts). Every change is recorded in the audit log as done by
``cli:<login name>``. ``token add`` prints the new
token as the last line of stdout, ``invite add`` the invitation's link, and ``user import`` ``name,token`` as CSV;
each is shown this once and stored only as its sha256.

Exit codes: 0 ok, 1 bad input (unknown user, taken name, unreadable file, no server extra), 2 usage.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import getpass
import sys
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kitti_eval.errors import KittiEvalError

from . import without_server_extra

if TYPE_CHECKING:  # the server extra's: imported when the command runs, so that its parser builds without them
    from ..access.policy import Caller
    from ..jobs.queue import JobRecord
    from ..service import Service
    from ..settings import Settings

__all__ = ["add_parser", "run"]

EXIT_OK, EXIT_INPUT, EXIT_USAGE = 0, 1, 2


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``admin`` and its subcommands to the CLI's subparsers."""
    p = sub.add_parser(
        "admin",
        help="accounts, projects, tokens, ground truths and jobs of the service (on the server's machine)",
        description="Manage the service's accounts and ground truths directly in its database. Reads the "
        "service's settings (KITTI_EVAL_DATA_DIR, KITTI_EVAL_DATABASE_URL); needs the server extra.",
    )
    p.add_argument("--data-dir", type=Path, help="KITTI_EVAL_DATA_DIR of the service")
    p.add_argument("--database-url", help="KITTI_EVAL_DATABASE_URL of the service")
    p.add_argument(
        "--create",
        action="store_true",
        help="make the database if there is none yet (without it, a missing database is an error: the settings "
        "do not point at the service's)",
    )
    what = p.add_subparsers(dest="admin_what", metavar="WHAT", required=True)

    user = what.add_parser("user", help="users").add_subparsers(dest="admin_action", metavar="ACTION", required=True)
    u = user.add_parser("add", help="add a user")
    u.add_argument("name")
    u.add_argument("--admin", action="store_true", help="an admin: sees every project, may run admin actions")
    user.add_parser("list", help="users and their projects")

    project = what.add_parser("project", help="projects").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    project.add_parser("add", help="add a project").add_argument("name")
    project.add_parser("list", help="projects")

    member = what.add_parser("member", help="memberships").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    for action, helptext in (("add", "make USER a member of PROJECT"), ("remove", "end a membership")):
        m = member.add_parser(action, help=helptext)
        m.add_argument("user")
        m.add_argument("project")

    u = user.add_parser(
        "import",
        help="make many accounts from a CSV (columns name and, optionally, project): prints name,token as CSV; "
        "refuses the whole file, naming the line, if a name is taken or not valid",
    )
    u.add_argument("file", type=Path, metavar="FILE.csv")

    invite = what.add_parser("invite", help="invitations: links people join a benchmark by").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    i = invite.add_parser("add", help="a link /join/CODE that makes accounts taking part in a benchmark (shown once)")
    i.add_argument("--benchmark", required=True, metavar="NAME")
    i.add_argument("--uses", type=int, metavar="N", help="at most N accounts (default: as many as join)")
    i.add_argument("--expires-days", type=float, metavar="D", help="valid for D days (default: 14)")
    i.add_argument(
        "--project",
        metavar="P",
        help="the accounts are members of P (default: of the benchmark's test set's project, which only its "
        "members take part in)",
    )
    i.add_argument("--url", metavar="URL", help="the service's address, to print the whole link (e.g. https://host)")
    invite.add_parser("list", help="invitations: their uses left and the accounts each made").add_argument(
        "--benchmark", metavar="NAME"
    )
    invite.add_parser("revoke", help="no one joins by it any more (the accounts it made stay)").add_argument(
        "invitation_id"
    )

    token = what.add_parser("token", help="tokens").add_subparsers(dest="admin_action", metavar="ACTION", required=True)
    t = token.add_parser("add", help="a new token for USER, printed as the last line (shown once)")
    t.add_argument("user")
    t.add_argument("--read-only", action="store_true", help="may read and gate, not upload or change anything")
    t.add_argument("--expires-days", type=float, metavar="N", help="valid for N days (default: until revoked)")
    token.add_parser("revoke", help="revoke a token (and its web sessions) at once").add_argument("token_id")
    token.add_parser("list", help="tokens (never their secrets)").add_argument("user", nargs="?")

    gt = what.add_parser("ground-truth", help="ground truths").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    g = gt.add_parser("add", help="register a ground truth")
    g.add_argument("name")
    g.add_argument("file", type=Path, help="an OpenPCDet infos .pkl[.gz], or a zip/tar of a label_2 folder")
    g.add_argument("--project", help="only this project's members see and use it (default: everyone)")
    g.add_argument("--sealed", action="store_true", help="a test set: aggregate results only, no per-frame view")

    bench = what.add_parser("benchmark", help="hosted benchmarks on sealed test sets").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    b = bench.add_parser("add", help="a benchmark on a sealed ground truth")
    b.add_argument("name")
    b.add_argument("--ground-truth", required=True, metavar="GT", help="a ground truth registered with --sealed")
    b.add_argument("--title", help="shown on the page (default: the name)")
    b.add_argument("--description", default="", help="Markdown (HTML is escaped); @FILE reads it from a file")
    b.add_argument("--quota", default="3/1", metavar="N/DAYS", help="accepted submissions per participant (3/1)")
    b.add_argument("--public", action="store_true", help="the board and page are readable without a token")
    b.add_argument(
        "--open-to-all",
        action="store_true",
        help="every account may take part (default: the members of the test set's project)",
    )
    b.add_argument(
        "--share-test-set",
        action="store_true",
        help="the test set is already another benchmark's: take it anyway (a second quota and public part on "
        "the same labels)",
    )
    b.add_argument(
        "--key",
        action="append",
        metavar="COLUMN",
        help="the ranking key, CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]] (default Car/3d/moderate/R40/strict); "
        "repeat it to rank by the mean of several",
    )
    b.add_argument("--column", action="append", metavar="COLUMN", help="a leaderboard column (default: 3D AP)")
    b.add_argument("--classes", default="Car,Pedestrian,Cyclist")
    b.add_argument("--protocol", default="official", choices=["official", "openpcdet"])
    b.add_argument("--threshold-sets", default="strict,loose")
    b.add_argument("--opens", metavar="TIME", help="ISO 8601 (default: now)")
    b.add_argument("--closes", metavar="TIME", help="ISO 8601 (default: never)")
    b.add_argument(
        "--split-percent",
        type=float,
        metavar="P",
        help="score the board on a secret P %% of the test frames until the private ranking is revealed",
    )
    b.add_argument(
        "--max-published",
        type=int,
        metavar="N",
        help="published entries per participant (default: no cap; Kaggle's is 2)",
    )
    ap = bench.add_parser("apply", help="create or change a benchmark as a TOML file defines it (phases, teams)")
    ap.add_argument("file", type=Path, metavar="FILE.toml")
    bench.add_parser("list", help="benchmarks")
    for action, helptext in (
        ("close", "close to submissions"),
        ("reopen", "open again (not once revealed)"),
        ("reveal", "show the private ranking (once closed)"),
        ("rescore", "evaluate every submission again on the ground truth as registered now"),
        ("submissions", "every submission, published or not"),
    ):
        bench.add_parser(action, help=helptext).add_argument("name")
    ex = bench.add_parser("export", help="the leaderboard as CSV on stdout; with FILE.toml, the benchmark's file")
    ex.add_argument("name")
    ex.add_argument("file", nargs="?", type=Path, metavar="FILE.toml", help="write the file that defines it there")
    dq = bench.add_parser("disqualify", help="hide an entry (it is kept)")
    dq.add_argument("name")
    dq.add_argument("submission")

    what.add_parser(
        "backup",
        help="a consistent copy of the service, running or not, into DIR (new or empty): SQLite's online backup "
        "or pg_dump, and the data folder's admin token",
    ).add_argument("dir", type=Path, metavar="DIR")
    what.add_parser(
        "restore",
        help="the service from the backup in DIR, into a data folder without a database (and an empty PostgreSQL "
        "database)",
    ).add_argument("dir", type=Path, metavar="DIR")
    db = what.add_parser("db", help="the database's schema: its revision, its upgrade").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    db.add_parser("current", help="the revision the database's schema is at, and this release's newest")
    db.add_parser(
        "upgrade",
        help="upgrade the schema to this release's (in one transaction, under a lock; back the service up first)",
    )
    jobs = what.add_parser("jobs", help="the queue of evaluations: list, cancel, run again").add_subparsers(
        dest="admin_action", metavar="ACTION", required=True
    )
    jl = jobs.add_parser("list", help="jobs of every owner, newest first (the counts by state on stderr)")
    jl.add_argument("--state", choices=["queued", "running", "done", "failed", "cancelled"])
    jl.add_argument("--limit", type=int, default=50)
    jobs.add_parser("cancel", help="cancel a queued or running job (its result is not stored)").add_argument("job_id")
    jobs.add_parser("rerun", help="queue an ended job again (a failed or cancelled evaluation)").add_argument("job_id")

    audit = what.add_parser("audit", help="the audit log, newest first")
    audit.add_argument("--limit", type=int, default=50)
    p.set_defaults(run=run)
    return p


def _say(msg: str) -> None:
    print(f"kitti-eval admin: {msg}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """``kitti-eval admin ...``: what it writes (a backup, a database it creates, ground truths it unpacks) is not
    readable by other users (:func:`~kitti_eval_server.data_folder.private_files`)."""
    try:
        from ..data_folder import private_files
    except ImportError as e:
        return without_server_extra("admin", e)
    with private_files():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    try:
        from sqlalchemy.exc import SQLAlchemyError

        from ..access.policy import Policy
        from ..errors import ApiError
        from ..service import Service
        from ..settings import Settings, settings_error
        from ..store import UnusableDatabase
    except ImportError as e:
        return without_server_extra("admin", e)

    overrides = {k: v for k, v in (("data_dir", args.data_dir), ("database_url", args.database_url)) if v}
    try:
        settings = Settings(**overrides)
    except ValueError as e:  # pydantic's ValidationError, or no data folder (NoDataFolder)
        _say(settings_error(e))
        return EXIT_USAGE
    # whoever may open the service's database acts as an admin
    caller = Policy.command_line(_login())
    where = settings.database_name
    _say(f"database {where}")  # every run names the database it reads and writes
    try:
        if args.admin_what == "restore":
            return _restore(args.dir, settings)
        if not args.create and not _database_exists(settings):
            _say(
                f"error: no kitti-eval database at {where}: give the service's settings (KITTI_EVAL_DATA_DIR or "
                "--data-dir, KITTI_EVAL_DATABASE_URL or --database-url), or --create to make a new one there"
            )
            return EXIT_INPUT
        if settings.database_url is None:  # SQLite in the data folder, which --create makes
            settings.data_dir.mkdir(parents=True, exist_ok=True)
        if args.admin_what == "db":
            return _db(args.admin_action, settings)
        if args.admin_what == "backup":
            return _backup(args.dir, settings)
        with _offline_service(Service(settings)) as service:
            if args.admin_what == "ground-truth":
                return _ground_truth(args, service, caller)
            if args.admin_what == "benchmark":
                return _benchmark(args, service, caller)
            if args.admin_what == "jobs":
                return _jobs(args, service, caller)
            if args.admin_what == "invite" or (args.admin_what == "user" and args.admin_action == "import"):
                return _invite(args, service, caller)
            return _account_command(args, service, caller)
    except (ApiError, KittiEvalError) as e:
        _say(f"error: {e.message if isinstance(e, ApiError) else e}")  # the library's names the file
        return EXIT_INPUT
    except UnusableDatabase as e:  # older or newer than this release, not UTF8: the sentence says what to do
        _say(f"error: {e.message}")
        return EXIT_INPUT
    except SQLAlchemyError as e:
        where = settings.resolved_database_url.split("@")[-1]  # not the password
        _say(f"error: the database at {where} is not usable: {getattr(e, 'orig', None) or e}")
        return EXIT_INPUT
    except OSError as e:
        _say(f"error: {e.strerror or e}: {e.filename or ''}".rstrip(": "))
        return EXIT_INPUT


def _backup(folder: Path, settings: Settings) -> int:
    from ..backup import BackupError, backup

    try:
        made = backup(settings, folder)
    except BackupError as e:
        _say(f"error: {e}")
        return EXIT_INPUT
    size = sum(int(str(f["bytes"])) for f in made.files.values())
    _say(
        f"backed up the {made.backend} database {settings.database_name} (revision {made.revision or 'none'}) and "
        f"{len(made.files) - 1} file(s) of the data folder into {folder}: {size / 1e6:.1f} MB in {made.seconds:.1f} s"
    )
    return EXIT_OK


def _restore(folder: Path, settings: Settings) -> int:
    from ..backup import BackupError, restore
    from ..store.schema import head

    try:
        made = restore(settings, folder)
    except BackupError as e:
        _say(f"error: {e}")
        return EXIT_INPUT
    _say(f"restored the {made.backend} database {settings.database_name} from {folder} in {made.seconds:.1f} s")
    if made.revision != head():
        _say(
            f"its schema is at revision {made.revision or 'none'}, older than this release's {head()}: run kitti-eval "
            "admin db upgrade before starting the service"
        )
    return EXIT_OK


def _db(action: str, settings: Settings) -> int:
    """``kitti-eval admin db current|upgrade``: the schema's revision, or its upgrade to this release's."""
    from ..store import Store
    from ..store.schema import head

    where = settings.database_name
    store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
    try:
        if action == "current":
            state = store.schema_state()
            print(state.revision or "none")  # noqa: T201 - the answer, on stdout
            _say(f"the database {where} is {state.describe()}; this release's newest revision is {head()}")
            return EXIT_OK
        before = store.schema_state()
        store.create_schema(upgrade=True, where=where)
        if before.empty:
            _say(f"made the schema of revision {head()} in the empty database {where}")
        elif before.current:
            _say(f"the database {where} is already at revision {head()}, this release's newest: nothing to do")
        else:
            _say(f"upgraded the database {where} from {before.revision or 'no revision'} to revision {head()}")
        print(head())  # noqa: T201
        return EXIT_OK
    finally:
        store.dispose()


def _database_exists(settings: Settings) -> bool:
    """Whether the settings' database is a kitti-eval database (its SQLite file exists, or its tables do): the
    service makes it at its first start, ``--create`` here."""
    from sqlalchemy import inspect
    from sqlalchemy.engine import make_url

    from ..store import Store

    url = settings.resolved_database_url
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        return parsed.database is not None and Path(parsed.database).is_file()
    store = Store(url, busy_s=settings.database_busy_s)
    try:
        return bool(inspect(store.engine).has_table("audit"))
    finally:
        store.dispose()


def _login() -> str:
    try:
        return getpass.getuser()
    except Exception:  # noqa: BLE001 - no login name (a container without a passwd entry)
        return "unknown"


def _account_command(args: argparse.Namespace, service: Service, caller: Caller) -> int:
    what, action = args.admin_what, getattr(args, "admin_action", None)
    store, accounts = service.store, service.accounts
    if what == "user" and action == "add":
        user = accounts.add_user(args.name, is_admin=args.admin, caller=caller)
        print(f"user {user.name}{' (admin)' if user.is_admin else ''}")
    elif what == "user":
        for user in store.account_store.list_users():
            print(f"{user.name}\t{'admin' if user.is_admin else 'member'}\t{','.join(user.projects) or '-'}")
    elif what == "project" and action == "add":
        print(f"project {accounts.add_project(args.name, caller=caller)}")
    elif what == "project":
        for name in store.account_store.list_projects():
            print(name)
    elif what == "member" and action == "add":
        accounts.add_member(args.user, args.project, caller=caller)
        print(f"{args.user} is a member of {args.project}")
    elif what == "member":
        accounts.remove_member(args.user, args.project, caller=caller)
        print(f"{args.user} is no longer a member of {args.project}")
    elif what == "token" and action == "add":
        scopes = ("read",) if args.read_only else ("read", "write")
        record, token = accounts.add_token(args.user, scopes=scopes, expires_days=args.expires_days, caller=caller)
        expires = record.expires_at.isoformat() if record.expires_at else "never"
        print(f"token id {record.id} for {record.user_name}: scopes {record.scopes}, expires {expires}")
        print("the token follows; it is shown this once (only its sha256 is kept):")
        print(token)
    elif what == "token" and action == "revoke":
        accounts.revoke_token(args.token_id, caller=caller)
        print(f"token {args.token_id} revoked")
    elif what == "token":
        for t in store.account_store.list_tokens(args.user):
            state = "revoked" if t.revoked_at else f"expires {t.expires_at.isoformat()}" if t.expires_at else "active"
            print(f"{t.id}\t{t.user_name}\t{t.scopes}\t{state}")
    elif what == "audit":
        for r in accounts.audit.entries(limit=max(1, args.limit)):
            print(f"{r.at.isoformat()}\t{r.actor}\t{r.action}\t{r.target}\t{r.outcome}\t{r.client}\t{r.detail}")
    else:  # pragma: no cover - argparse requires an action
        _say(f"error: unknown command {what} {action}")
        return EXIT_USAGE
    return EXIT_OK


@contextlib.contextmanager
def _offline_service(service: Service) -> Iterator[Service]:
    """The service's parts on this machine, as the application assembles them (:class:`Service`), without its
    HTTP side, its workers or its demo: scratch space and tables ready, closed after."""
    try:
        service.scratch_space.open()
        service.store.create_schema(upgrade=False, where=service.settings.database_name)
        yield service
    finally:
        service.stop()


def _run_jobs(service: Service, job_ids: list[str]) -> list[JobRecord | None]:
    """Run the queued rescoring jobs, and the jobs of the board's intervals they queue, in this process until none
    is left (a service's workers on the same database may take some of ``job_ids`` meanwhile: those are waited
    for); the jobs ``job_ids`` as they ended."""
    from ..jobs.workers import worker_name

    name = worker_name(0) + ":admin"
    while (job := service.jobs.claim(name, kinds=["rescore", "intervals"])) is not None:
        service.workers.run_one(job, name)
    return [service.jobs.wait(job_id, service.jobs.lease_s * service.jobs.max_attempts + 60) for job_id in job_ids]


def _ground_truth(args: argparse.Namespace, service: Service, caller: Caller) -> int:
    from ..service import FileIn

    with open(args.file, "rb") as fh:
        record = service.gt_catalog.add(
            args.name, FileIn(fh, args.file.name), caller=caller, project=args.project, sealed=args.sealed
        )
    sealed = ", sealed" if record.sealed else ""
    print(f"ground truth {record.name}: {record.frames} frames, {record.boxes} boxes{sealed}, sha256 {record.sha256}")
    return EXIT_OK


def _benchmark(args: argparse.Namespace, service: Service, caller: Caller) -> int:
    from ..benchmarks.phase_settings import PhaseSettings

    benchmarks = service.benchmarks
    action = args.admin_action
    if action == "add":
        description = args.description
        if description.startswith("@"):
            description = Path(description[1:]).read_text(encoding="utf-8")
        given = {
            "ground_truth": args.ground_truth,
            "title": args.title,
            "description": description,
            "protocol": args.protocol,
            "classes": args.classes,
            "threshold_sets": args.threshold_sets,
            "key": args.key,
            "columns": args.column,
            "quota": args.quota,
            "public": args.public,
            "opens_at": args.opens,
            "closes_at": args.closes,
            "split_percent": args.split_percent,
            "max_published": args.max_published,
            "open_to_all": args.open_to_all,
        }
        settings = PhaseSettings.parse(given, benchmark=args.name)
        bench = benchmarks.catalog.create(args.name, settings, share_test_set=args.share_test_set, caller=caller)
        n, days = bench.quota
        cap = f", at most {bench.max_published} published per participant" if bench.max_published else ""
        print(
            f"benchmark {bench.name} on {bench.gt_name}: key {' + '.join(bench.key)}, quota {n} per "
            f"{'day' if days == 1 else f'{days:g} days'}{cap}, {'public' if bench.public else 'not public'}"
        )
    elif action == "list":
        for b in benchmarks.catalog.visible(caller):
            state = b.state().value
            print(f"{b.shown_name}\t{b.gt_name}\t{state}\t{'public' if b.public else '-'}\t{b.title}")
    elif action in ("close", "reopen", "reveal"):
        values = {"close": {"closed": True}, "reopen": {"closed": False}, "reveal": {"revealed": True}}[action]
        bench = benchmarks.catalog.set_state(args.name, caller=caller, **values)
        print(f"benchmark {bench.name}: {bench.state().value}, board {bench.board_part}")
    elif action == "rescore":
        queued = benchmarks.submissions.rescore(args.name, caller=caller)
        ended = _run_jobs(service, queued["jobs"])
        done = sum(1 for j in ended if j is not None and j.state == "done")
        print(f"benchmark {args.name}: {done} submissions rescored, {len(ended) - done} failed")
    elif action == "submissions":
        for s in benchmarks.submissions.all_submissions(args.name, caller):
            flags = ",".join(k for k in ("published", "disqualified") if s[k]) or "-"
            print(f"{s['id']}\t{s['participant']}\t{s['created_at']}\t{s['status']}\t{flags}\t{s['method'] or '-'}")
    elif action == "disqualify":
        benchmarks.submissions.disqualify(args.name, args.submission, caller=caller)
        print(f"submission {args.submission} disqualified")
    elif action == "apply":
        from ..benchmarks.benchmark_file import apply_benchmark_file

        applied = apply_benchmark_file(benchmarks.catalog, _read_text(args.file), caller=caller, source=str(args.file))
        print(f"benchmark {applied.name}: " + ("; ".join(applied.lines)))
    elif action == "export" and args.file is not None:
        from ..benchmarks.benchmark_file import export_benchmark_file

        args.file.write_text(export_benchmark_file(benchmarks.catalog, args.name, caller=caller), encoding="utf-8")
        print(f"benchmark {args.name}: written to {args.file}")
    elif action == "export":
        board = benchmarks.board.leaderboard(args.name, caller)
        sys.stdout.write(benchmarks.board.leaderboard_csv(board))
    return EXIT_OK


def _read_text(path: Path) -> str:
    """A file the command reads (a benchmark file): its refusal is an input error naming it, not a traceback."""
    from kitti_eval.errors import InputError

    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot be read as UTF-8 text: {getattr(e, 'strerror', None) or e}") from None


def _jobs(args: argparse.Namespace, service: Service, caller: Caller) -> int:
    from ..jobs.workers import JobFailed

    admin = service.job_admin
    if args.admin_action == "list":
        for job in admin.listed(caller, state=args.state, limit=max(1, args.limit)):
            if job.state == "done":
                detail = job.result_id or "-"
            elif job.state == "running":
                detail = job.worker or "-"
            else:
                detail = JobFailed(job.error).message if job.error else "-"
            print(
                f"{job.id}\t{job.kind}\t{job.state}\t{job.attempts}/{job.max_attempts}\t{job.owner}\t"
                f"{job.accepted_at.isoformat()}\t{detail}"
            )
        counts = admin.counts(caller)
        _say(", ".join(f"{n} {state}" for state, n in counts.items()))
    elif args.admin_action == "cancel":
        job = admin.cancel(args.job_id, caller)
        print(f"job {job.id} cancelled")
    elif args.admin_action == "rerun":
        job = admin.rerun(args.job_id, caller)
        print(f"job {job.id} queued again")
    return EXIT_OK


def _invite(args: argparse.Namespace, service: Service, caller: Caller) -> int:
    """``invite add|list|revoke`` and ``user import``."""
    from ..access.invitations import parse_import, state_of

    invitations = service.invitations
    if args.admin_what == "user":
        made = invitations.import_users(parse_import(_read_text(args.file)), caller=caller)
        out = csv.writer(sys.stdout, lineterminator="\n")
        out.writerow(("name", "token"))
        out.writerows(made)
        _say(
            f"made {len(made)} account(s) from {args.file}; the tokens are shown this once (only their sha256 is kept)"
        )
    elif args.admin_action == "add":
        record, code = invitations.add(
            args.benchmark, uses=args.uses, expires_days=args.expires_days, project=args.project, caller=caller
        )
        uses = f"{record.max_uses} use(s)" if record.max_uses else "any number of uses"
        expires = record.expires_at.isoformat(timespec="seconds") if record.expires_at else "never"
        members = f", members of {record.project}" if record.project else ""
        print(f"invitation {record.id} to {record.benchmark}: {uses}, expires {expires}{members}")
        print("the link follows; it is shown this once (only its code's sha256 is kept):")
        print(f"{(args.url or '').rstrip('/')}/join/{code}")
    elif args.admin_action == "list":
        now = datetime.now(timezone.utc)
        for r in invitations.listed(caller, args.benchmark):
            left = "-" if r.max_uses is None else str(max(0, r.max_uses - r.uses))
            state = state_of(r, now)
            expires = r.expires_at.isoformat(timespec="seconds") if r.expires_at else "never"
            print(f"{r.id}\t{r.benchmark}\t{state}\tleft {left}\texpires {expires}\t{','.join(r.accounts) or '-'}")
    else:
        invitations.revoke(args.invitation_id, caller=caller)
        print(f"invitation {args.invitation_id} revoked")
    return EXIT_OK
