"""``kitti-eval submissions``: one's submissions to a benchmark's phase, newest first, with their status, the
scores one may see (the ranking key's), whether each is published, and the quota left (the team's in a team).
Exit codes as ``submit``'s."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

from .common import EXIT_OK, emit, say
from .remote import add_connection_arguments, client_of, quota_left

if TYPE_CHECKING:
    from ..client import Submission

__all__ = ["add_parser", "run", "render_submissions"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def add_parser(sub: Any) -> argparse.ArgumentParser:
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
    add_connection_arguments(p, saved=True)
    p.set_defaults(run=run, quiet=False)
    return p


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


def run(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        items = client.submissions(args.benchmark, phase=args.phase)
        if args.format == "json":
            emit(json.dumps([s.view for s in items], indent=2) + "\n", None)
            return EXIT_OK
        info = client.benchmark(args.benchmark)
        say(quota_left(client, args.benchmark, args.phase, info))
        emit(render_submissions(items, list(info.get("key") or [])), None)
    return EXIT_OK
