"""Shared by the benchmark tests: accounts-mode users and tokens, a sealed test set and a benchmark on it.

``alice`` and ``bob`` take part (any signed-in account sees a benchmark on a shared ground truth); ``root`` is
an admin. The sealed set is the golden ``kitti_infos_val.pkl`` (50 frames), registered as ``test-set``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from server_helpers import ADMIN, golden_bytes

__all__ = ["Hosted", "host", "submit", "bearer", "ok"]


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def ok(response: Any, status: int = 200) -> Any:
    assert response.status_code == status, response.text[:2000]
    return response.json() if response.content else None


@dataclass
class Hosted:
    tokens: dict[str, str] = field(default_factory=dict)

    def headers(self, who: str) -> dict[str, str]:
        return bearer(self.tokens[who])


def host(client: Any, *, benchmark: dict[str, Any] | None = None, users: tuple[str, ...] = ("alice", "bob")) -> Hosted:
    hosted = Hosted()
    for user in users:
        ok(client.post("/v1/admin/users", json={"name": user}, headers=ADMIN), 201)
        hosted.tokens[user] = ok(client.post("/v1/admin/tokens", json={"user": user}, headers=ADMIN), 201)["token"]
    ok(client.post("/v1/admin/users", json={"name": "root", "admin": True}, headers=ADMIN), 201)
    hosted.tokens["root"] = ok(client.post("/v1/admin/tokens", json={"user": "root"}, headers=ADMIN), 201)["token"]
    files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
    ok(client.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=files, headers=ADMIN), 201)
    body = {"name": "bench", "ground_truth": "test-set", "quota": "3/1", "public": True, **(benchmark or {})}
    ok(client.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
    return hosted


def submit(client: Any, headers: dict[str, str], data: bytes, filename: str = "result.pkl", name: str = "bench") -> Any:
    files = {"predictions": (filename, data, "application/octet-stream")}
    return client.post(f"/v1/benchmarks/{name}/submissions", files=files, headers=headers)
