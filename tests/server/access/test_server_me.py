"""``GET /v1/me``: who a token is (what ``kitti-eval login`` says), with the three fields named and nothing else;
no token is refused."""

from __future__ import annotations

from server_benchmarks import bearer, ok
from server_helpers import ADMIN, app_client


def test_me_names_the_tokens_user_and_whether_it_is_read_only(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        ok(c.post("/v1/admin/users", json={"name": "alice"}, headers=ADMIN), 201)
        full = ok(c.post("/v1/admin/tokens", json={"user": "alice"}, headers=ADMIN), 201)["token"]
        reader = ok(c.post("/v1/admin/tokens", json={"user": "alice", "read_only": True}, headers=ADMIN), 201)
        assert ok(c.get("/v1/me", headers=bearer(full))) == {"user": "alice", "admin": False, "read_only": False}
        assert ok(c.get("/v1/me", headers=bearer(reader["token"]))) == {
            "user": "alice",
            "admin": False,
            "read_only": True,
        }
        assert c.get("/v1/me").status_code == 401
        assert c.get("/v1/me", headers=bearer("not-a-token")).status_code == 401
