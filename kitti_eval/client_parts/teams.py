"""A benchmark's teams, as a participant makes and joins them (``/v1/benchmarks/NAME/teams``): the team is made
by its first member, who invites the others; each joins when they accept; in a team, each phase's quota is the
team's."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from . import Sender

__all__ = ["teams", "create_team", "join_team"]


def teams(sender: Sender, benchmark: str) -> dict[str, Any]:
    """The benchmark's teams (``items``), the caller's own (``mine``, None when in none, with whom it invited)
    and the teams that invited them (``invitations``), and its ``team_size``."""
    return dict(sender._get(f"/v1/benchmarks/{benchmark}/teams"))


def create_team(sender: Sender, benchmark: str, name: str, invite: Sequence[str] = ()) -> dict[str, Any]:
    """Makes the team ``name`` (the caller is its first member), inviting ``invite``; the team as its members
    read it."""
    body = {"name": name, "members": [m.strip() for m in invite if m.strip()]}
    return dict(sender._request("POST", f"/v1/benchmarks/{benchmark}/teams", json_body=body).json())


def join_team(sender: Sender, benchmark: str, name: str) -> dict[str, Any]:
    """Joins the team ``name``, which invited the caller; the team as its members read it."""
    return dict(sender._request("POST", f"/v1/benchmarks/{benchmark}/teams/{name}/join").json())
