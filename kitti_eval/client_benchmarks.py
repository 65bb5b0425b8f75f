"""A participant's calls beyond submitting, one function each sent through the client's
:class:`~kitti_eval.client_http.Transport` (its token and retries; :class:`~kitti_eval.client.Client` has a method
for each, which the commands call):
a benchmark's teams (``/v1/benchmarks/NAME/teams``: the team is made by its first member, who invites the
others; each joins when they accept, and may leave until the benchmark's last phase has closed; in a team, each
phase's quota is the team's), one's entries on the board
(``.../submissions/ID/publish|withdraw``), and the board as CSV."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .client_http import Transport

__all__ = ["teams", "create_team", "join_team", "leave_team", "publish", "withdraw", "board_csv"]


def teams(http: Transport, benchmark: str) -> dict[str, Any]:
    """The benchmark's teams (``items``), the caller's own (``mine``, None when in none, with whom it invited)
    and the teams that invited them (``invitations``), and its ``team_size``."""
    return dict(http.get(f"/v1/benchmarks/{benchmark}/teams"))


def create_team(http: Transport, benchmark: str, name: str, invite: Sequence[str] = ()) -> dict[str, Any]:
    """Makes the team ``name`` (the caller is its first member), inviting ``invite``; the team as its members
    read it."""
    body = {"name": name, "members": [m.strip() for m in invite if m.strip()]}
    return dict(http.request("POST", f"/v1/benchmarks/{benchmark}/teams", json_body=body).json())


def join_team(http: Transport, benchmark: str, name: str) -> dict[str, Any]:
    """Joins the team ``name``, which invited the caller; the team as its members read it."""
    return dict(http.request("POST", f"/v1/benchmarks/{benchmark}/teams/{name}/join").json())


def leave_team(http: Transport, benchmark: str) -> dict[str, Any]:
    """Leaves the caller's team of the benchmark: the team left (``left``) and its ``members`` now."""
    return dict(http.request("POST", f"/v1/benchmarks/{benchmark}/teams/leave").json())


def publish(
    http: Transport,
    benchmark: str,
    submission_id: str,
    *,
    method: str,
    anonymous: bool = False,
    affiliation: str | None = None,
    link: str | None = None,
) -> dict[str, Any]:
    """Shows the submission on the board under ``method``; the submission as its participant reads it."""
    body: dict[str, Any] = {"method": method, "anonymous": anonymous}
    if affiliation is not None:
        body["affiliation"] = affiliation
    if link is not None:
        body["link"] = link
    path = f"/v1/benchmarks/{benchmark}/submissions/{submission_id}/publish"
    return dict(http.request("POST", path, json_body=body).json())


def withdraw(http: Transport, benchmark: str, submission_id: str) -> dict[str, Any]:
    """Takes the submission off the board; the submission as its participant reads it."""
    path = f"/v1/benchmarks/{benchmark}/submissions/{submission_id}/withdraw"
    return dict(http.request("POST", path).json())


def board_csv(http: Transport, path: str) -> str:
    """The board at ``path`` (a benchmark's or a phase's ``.../leaderboard``) as the service's CSV."""
    return http.request("GET", path, params={"format": "csv"}).text
