"""Shared by the accounts-mode tests: a service with two teams' projects, their tokens and their work.

Project ``team-a`` (alice, and a read-only token of hers) has the ground truth ``gt-a`` and a sealed copy of the
same file ``sealed-a``, each with one evaluation; project ``team-b`` (bob) has ``gt-b`` (the same labels as a
txt archive, so another file) and one evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from server_helpers import ADMIN, golden_bytes, upload

__all__ = ["Teams", "make_teams", "bearer", "add_token"]


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@dataclass
class Teams:
    tokens: dict[str, str] = field(default_factory=dict)  # alice, alice-ro, bob, carol (no project), root (admin)
    token_ids: dict[str, str] = field(default_factory=dict)
    evaluations: dict[str, str] = field(default_factory=dict)  # gt-a, sealed-a, gt-b -> evaluation id
    sha256: dict[str, str] = field(default_factory=dict)  # ground truth -> sha256

    def headers(self, who: str) -> dict[str, str]:
        return bearer(self.tokens[who])


def _ok(response: Any, status: int = 201) -> Any:
    assert response.status_code == status, response.text
    return response.json() if response.content else None


def add_token(client: Any, user: str, **options: Any) -> tuple[str, str]:
    body = _ok(client.post("/v1/admin/tokens", json={"user": user, **options}, headers=ADMIN))
    return body["id"], body["token"]


def make_teams(client: Any) -> Teams:
    """Users, projects, memberships and tokens through the admin endpoints; ground truths and evaluations."""
    teams = Teams()
    for project in ("team-a", "team-b"):
        _ok(client.post("/v1/admin/projects", json={"name": project}, headers=ADMIN))
    for user, admin in (("alice", False), ("bob", False), ("carol", False), ("root", True)):
        _ok(client.post("/v1/admin/users", json={"name": user, "admin": admin}, headers=ADMIN))
    for user, project in (("alice", "team-a"), ("bob", "team-b")):
        _ok(client.post("/v1/admin/members", json={"user": user, "project": project}, headers=ADMIN))
    for who, user, options in (
        ("alice", "alice", {}),
        ("alice-ro", "alice", {"read_only": True}),
        ("bob", "bob", {}),
        ("carol", "carol", {}),
        ("root", "root", {}),
    ):
        teams.token_ids[who], teams.tokens[who] = add_token(client, user, **options)
    for name, project, sealed, filename in (
        ("gt-a", "team-a", False, "kitti_infos_val.pkl"),
        ("sealed-a", "team-a", True, "kitti_infos_val.pkl"),
        ("gt-b", "team-b", False, "label_2.tar.gz"),  # the same labels as txt: another file
    ):
        form = {"name": name, "project": project, "sealed": "true" if sealed else "false"}
        files = {"file": (filename, golden_bytes(filename))}
        body = _ok(client.post("/v1/ground-truths", data=form, files=files, headers=ADMIN))
        assert body["project"] == project and body["sealed"] is sealed
        teams.sha256[name] = body["sha256"]
    predictions = golden_bytes("result.pkl")
    for name, who in (("gt-a", "alice"), ("sealed-a", "alice"), ("gt-b", "bob")):
        client.headers.update(teams.headers(who))
        try:
            body = _ok(upload(client, predictions, gt=name, fields={"model": f"model-of-{who}-on-{name}"}))
        finally:
            del client.headers["Authorization"]
        teams.evaluations[name] = body["id"]
    return teams
