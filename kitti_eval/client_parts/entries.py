"""One's entries on a benchmark's board: a submission published under a method's name, or withdrawn
(``/v1/benchmarks/NAME/submissions/ID/publish|withdraw``), and the board read as CSV."""

from __future__ import annotations

from typing import Any

from . import Sender

__all__ = ["publish", "withdraw", "board_csv"]


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
