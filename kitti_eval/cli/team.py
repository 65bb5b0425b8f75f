"""``kitti-eval team create|join|leave|show``: a benchmark's team, made, joined, left and read from the command line
(the routes ``/v1/benchmarks/NAME/teams``; in a team, each phase's quota is the team's). Exit codes as
``submit``'s."""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..errors import ConfigError
from .common import EXIT_OK, emit, say
from .remote import add_connection_arguments, client_of

__all__ = ["add_parser", "run", "render_team"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "team",
        help="make a benchmark's team and invite others, join one that invited you, leave yours, or show it",
        description="A benchmark's teams: 'create NAME --invite USER,USER' makes a team (you are its first member) "
        "and invites the others, who join with 'join NAME'; 'leave' leaves yours (until the benchmark's last phase "
        "has closed); 'show' lists the benchmark's teams, yours and the teams that invited you. In a team, each "
        "phase's quota is the team's; leaving frees none of it.",
        epilog=_EPILOG,
    )
    p.set_defaults(run=run, quiet=False)
    actions = p.add_subparsers(dest="team_action", metavar="ACTION", required=True)
    create = actions.add_parser("create", help="make a team and invite others", epilog=_EPILOG)
    create.add_argument("name", help="the team's name (1-48 letters, digits, spaces, '.', '_' or '-')")
    create.add_argument(
        "--invite", default="", metavar="USER,USER", help="the others invited to join it (default: none)"
    )
    join = actions.add_parser("join", help="join a team that invited you", epilog=_EPILOG)
    join.add_argument("name", help="the team's name")
    leave = actions.add_parser("leave", help="leave your team", epilog=_EPILOG)
    show = actions.add_parser("show", help="the benchmark's teams, yours and your invitations", epilog=_EPILOG)
    for q in (create, join, leave, show):
        q.add_argument("--benchmark", required=True, metavar="NAME", help="the benchmark's name")
        add_connection_arguments(q, saved=True)
        q.add_argument("--format", choices=["table", "json"], default="table", help="(default: table)")
        q.set_defaults(run=run, quiet=False)
    return p


def run(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        if args.team_action == "create":
            invite = [u.strip() for u in args.invite.split(",") if u.strip()]
            team = client.create_team(args.benchmark, args.name, invite=invite)
            say(f"made the team {team.get('name')} of {args.benchmark}; invited: {', '.join(invite) or 'nobody'}")
            emit(_one(team, args.format), None)
        elif args.team_action == "join":
            team = client.join_team(args.benchmark, args.name)
            say(f"joined the team {team.get('name')} of {args.benchmark}: each phase's quota is the team's")
            emit(_one(team, args.format), None)
        elif args.team_action == "leave":
            left = client.leave_team(args.benchmark)
            say(
                f"left the team {left.get('left')} of {args.benchmark}: what you submit from now on counts against "
                "your own quota; what you submitted for the team still counts against its quota and yours"
            )
            now = {"name": left.get("left"), "members": left.get("members")}
            emit(json.dumps(left, indent=2) + "\n" if args.format == "json" else _line(now) + "\n", None)
        elif args.team_action == "show":
            emit(render_team(client.teams(args.benchmark), args.format), None)
        else:  # pragma: no cover - argparse allows no other
            raise ConfigError(f"no team action {args.team_action!r}")
    return EXIT_OK


def _line(team: dict[str, Any]) -> str:
    from ..client import _shown

    members = ", ".join(_shown(m) for m in team.get("members") or [])
    invited = [_shown(m) for m in team.get("invited") or []]
    return f"{_shown(team.get('name'))}: {members}" + (f" (invited: {', '.join(invited)})" if invited else "")


def _one(team: dict[str, Any], fmt: str) -> str:
    return json.dumps(team, indent=2) + "\n" if fmt == "json" else _line(team) + "\n"


def render_team(doc: dict[str, Any], fmt: str) -> str:
    """``team show``: yours, the teams that invited you, and the benchmark's teams."""
    from ..client import _shown

    if fmt == "json":
        return json.dumps(doc, indent=2) + "\n"
    mine = doc.get("mine")
    lines = [f"your team: {_line(mine)}" if isinstance(mine, dict) else "your team: none"]
    invitations = [_shown(i if isinstance(i, str) else i.get("name")) for i in doc.get("invitations") or []]
    if invitations:
        lines.append(f"invited to: {', '.join(invitations)} (kitti-eval team join NAME --benchmark ...)")
    lines.append(f"teams ({len(doc.get('items') or [])}, at most {doc.get('team_size')} members each):")
    lines += [f"  {_line(t)}" for t in doc.get("items") or []]
    return "\n".join(lines) + "\n"
