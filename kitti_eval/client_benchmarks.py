"""A participant's calls beyond submitting, one function each of a :class:`Sender` (the client's sending, with
its token and retries; :class:`~kitti_eval.client.Client` has a method for each, which the commands call):
a benchmark's teams (``/v1/benchmarks/NAME/teams``: the team is made by its first member, who invites the
others; each joins when they accept, and may leave until the benchmark's last phase has closed; in a team, each
phase's quota is the team's), one's entries on the board
(``.../submissions/ID/publish|withdraw``), and the board as CSV."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import httpx

__all__ = ["Sender", "teams", "create_team", "join_team", "leave_team", "publish", "withdraw", "board_csv"]


class Sender(Protocol):
    """What an area's calls need of the client: its address, and one request sent with its token and retries."""

    service: str

    def _request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        data: Mapping[str, Any] | None = None,
        json_body: Any = None,
        files: Any = None,
        headers: Mapping[str, str] | None = None,
        ok: Sequence[int] = (200, 201, 202),
    ) -> httpx.Response: ...

    def _get(self, path: str, **params: Any) -> Any: ...


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


def leave_team(sender: Sender, benchmark: str) -> dict[str, Any]:
    """Leaves the caller's team of the benchmark: the team left (``left``) and its ``members`` now."""
    return dict(sender._request("POST", f"/v1/benchmarks/{benchmark}/teams/leave").json())


def publish(
    sender: Sender,
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
    return dict(sender._request("POST", path, json_body=body).json())


def withdraw(sender: Sender, benchmark: str, submission_id: str) -> dict[str, Any]:
    """Takes the submission off the board; the submission as its participant reads it."""
    path = f"/v1/benchmarks/{benchmark}/submissions/{submission_id}/withdraw"
    return dict(sender._request("POST", path).json())


def board_csv(sender: Sender, path: str) -> str:
    """The board at ``path`` (a benchmark's or a phase's ``.../leaderboard``) as the service's CSV."""
    return sender._request("GET", path, params={"format": "csv"}).text
