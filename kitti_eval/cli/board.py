"""``kitti-eval board``: a benchmark's leaderboard as the service shows it: a table (rank, key, method, team or
participant, date), the service's CSV, or its JSON. Exit codes as ``submit``'s."""

from __future__ import annotations

import argparse
import json
from typing import Any

from .common import EXIT_OK, emit
from .remote import add_connection_arguments, client_of

__all__ = ["add_parser", "run", "render_board"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def add_parser(sub: Any) -> argparse.ArgumentParser:
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
    add_connection_arguments(p, saved=True)
    p.set_defaults(run=run, quiet=False)
    return p


def _score(value: object) -> str:
    return f"{value:.2f}" if isinstance(value, (int, float)) else "-"


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


def run(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        if args.format == "csv":
            emit(client.leaderboard_csv(args.benchmark, phase=args.phase), None)
        else:
            board = client.leaderboard(args.benchmark, phase=args.phase)
            emit(json.dumps(board, indent=2) + "\n" if args.format == "json" else render_board(board), None)
    return EXIT_OK
