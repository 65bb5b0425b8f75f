"""``kitti-eval submissions``, ``publish``, ``withdraw`` and ``board``: one's submissions to a benchmark (with
their status, the scores one may see, published or not), one shown on the board or taken off it, and the board
read, from the command line. Exit codes as ``submit``'s."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

from .common import EXIT_OK, emit, say
from .remote import add_connection_arguments, client_of

if TYPE_CHECKING:
    from ..client import Submission

__all__ = ["add_parsers", "render_submissions", "render_board"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def _common(p: argparse.ArgumentParser) -> None:
    add_connection_arguments(p, saved=True)
    p.set_defaults(quiet=False)


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "submissions",
        help="your submissions to a benchmark: status, scores, published or not, and the quota left",
        description="Your submissions to a benchmark's phase (the team's quota in a team), newest first, with "
        "their status, the scores you may see (on the part of the test set the board shows) and whether each is "
        "published.",
        epilog=_EPILOG,
    )
    p.add_argument("benchmark", help="the benchmark's name")
    p.add_argument("--phase", metavar="PHASE", help="the phase (default: its current one)")
    p.add_argument("--format", choices=["table", "json"], default="table", help="(default: table)")
    _common(p)
    p.set_defaults(run=run_submissions)

    p = sub.add_parser(
        "publish",
        help="show one of your scored submissions on the board under a method's name",
        description="Show one of your scored submissions on the benchmark's board (the phase it is in).",
        epilog=_EPILOG,
    )
    p.add_argument("submission", metavar="SUBMISSION_ID", help="the submission's id (kitti-eval submissions lists)")
    p.add_argument("--benchmark", required=True, metavar="NAME", help="the benchmark's name")
    p.add_argument("--method", metavar="TEXT", help="the method's name on the board (default: the file's name)")
    p.add_argument("--affiliation", metavar="TEXT", help="shown beside it (default: none)")
    p.add_argument("--link", metavar="URL", help="the method's paper or code (default: none)")
    p.add_argument(
        "--anonymous", action="store_true", help="show neither your name, affiliation nor link (default: off)"
    )
    _common(p)
    p.set_defaults(run=run_publish)

    p = sub.add_parser(
        "withdraw",
        help="take one of your entries off the board",
        description="Take one of your published submissions off the benchmark's board (it stays yours).",
        epilog=_EPILOG,
    )
    p.add_argument("submission", metavar="SUBMISSION_ID", help="the submission's id")
    p.add_argument("--benchmark", required=True, metavar="NAME", help="the benchmark's name")
    _common(p)
    p.set_defaults(run=run_withdraw)

    p = sub.add_parser(
        "board",
        help="a benchmark's leaderboard as a table, CSV or JSON",
        description="The board of a benchmark's phase as the service shows it to you: rank, method, team or "
        "participant, the key and the date (the columns too in CSV and JSON).",
        epilog=_EPILOG,
    )
    p.add_argument("benchmark", help="the benchmark's name")
    p.add_argument("--phase", metavar="PHASE", help="the phase (default: its current one)")
    p.add_argument("--format", choices=["table", "csv", "json"], default="table", help="(default: table)")
    _common(p)
    p.set_defaults(run=run_board)


def _score(value: object) -> str:
    return f"{value:.2f}" if isinstance(value, (int, float)) else "-"


def render_submissions(items: list[Submission], key: list[str]) -> str:
    """``submissions --format table``: one line a submission, the key's mean first."""
    from ..client import _shown

    lines = [f"{'id':<36}  {'status':<8}  {'key':>7}  {'published':<9}  created"]
    for s in items:
        values = [(s.scores or {}).get(c) for c in key]
        numbers = [float(v) for v in values if isinstance(v, (int, float))]
        mean = sum(numbers) / len(numbers) if numbers and len(numbers) == len(values) else None
        published = "yes" if s.view.get("published") else "no"
        created = _shown(s.view.get("created_at") or "")[:19]
        lines.append(f"{s.id:<36}  {s.status:<8}  {_score(mean):>7}  {published:<9}  {created}")
    return "\n".join(lines) + "\n"


def run_submissions(args: argparse.Namespace) -> int:
    from .submit import _left

    with client_of(args) as client:
        items = client.submissions(args.benchmark, phase=args.phase)
        if args.format == "json":
            emit(json.dumps([s.view for s in items], indent=2) + "\n", None)
            return EXIT_OK
        info = client.benchmark(args.benchmark)
        team = None
        if int(info.get("team_size") or 1) > 1:
            mine = client.teams(args.benchmark).get("mine")
            team = mine.get("name") if isinstance(mine, dict) else None
        say(_left(client.quota(args.benchmark, phase=args.phase), team))
        emit(render_submissions(items, list(info.get("key") or [])), None)
    return EXIT_OK


def run_publish(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        method = args.method or client.submission(args.benchmark, args.submission).view.get("filename") or "method"
        published = client.publish(
            args.benchmark,
            args.submission,
            method=method,
            anonymous=args.anonymous,
            affiliation=args.affiliation,
            link=args.link,
        )
        say(f"published: submission {published.id} is on the board of {args.benchmark} as {method!r}")
        say(f"the board: {client.service}/benchmarks/{args.benchmark}")
    return EXIT_OK


def run_withdraw(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        withdrawn = client.withdraw(args.benchmark, args.submission)
        say(f"withdrawn: submission {withdrawn.id} is off the board of {args.benchmark} (it stays yours)")
    return EXIT_OK


def render_board(board: dict[str, Any]) -> str:
    """``board --format table``: rank, method, team (else participant), key and date, one line an entry."""
    from ..client import _shown

    entries = board.get("entries") or []
    lines = [f"{_shown(board.get('benchmark'))}, phase {_shown(board.get('phase'))}: {len(entries)} entries"]
    lines.append(f"{'rank':>8}  {'key':>7}  {'method':<28}  {'team / participant':<24}  date")
    for e in entries:
        rank = "baseline" if e.get("baseline") else str(e.get("rank") or "-")
        who = _shown(e.get("team") or e.get("participant") or "anonymous")
        lines.append(
            f"{rank:>8}  {_score(e.get('key')):>7}  {_shown(e.get('method') or '')[:28]:<28}  {who[:24]:<24}  "
            f"{_shown(e.get('date') or '')[:10]}"
        )
    return "\n".join(lines) + "\n"


def run_board(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        if args.format == "csv":
            emit(client.leaderboard_csv(args.benchmark, phase=args.phase), None)
        else:
            board = client.leaderboard(args.benchmark, phase=args.phase)
            emit(json.dumps(board, indent=2) + "\n" if args.format == "json" else render_board(board), None)
    return EXIT_OK
