"""What a participant could learn, or do, beyond the rules by trying as an attacker would: read back which frames
are public, keep a cancelled submission counting, take a second quota on one sealed set, sign a victim in, frame
the pages, learn the sealed set's name or submit to another project's benchmark. One test a side door."""

from __future__ import annotations

import pickle
import re
from datetime import timedelta
from ipaddress import ip_network
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from server_accounts import make_teams
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, golden_bytes
from starlette.testclient import TestClient

from kitti_eval_server.access.auth import CSRF_COOKIE, cross_site, over_https
from kitti_eval_server.benchmarks.rules import part_frames


@pytest.fixture()
def split_world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        yield c, host(c, benchmark={"split_percent": 50, "quota": "10/1"})


def padded(frames: dict[str, int]) -> bytes:
    """The golden result.pkl with ``n`` more Car detections far away from every box (z = 500 m, scored below
    every other detection, so no AP changes) in each frame ``frame id -> n``."""
    annos = pickle.loads(golden_bytes("result.pkl"))  # the test's own golden file
    for anno in annos:
        n = frames.get(anno["frame_id"], 0)
        if not n:
            continue
        extra: dict[str, Any] = {
            "name": np.array(["Car"] * n),
            "truncated": np.zeros(n),
            "occluded": np.zeros(n),
            "alpha": np.zeros(n),
            "bbox": np.tile([100.0, 100.0, 200.0, 200.0], (n, 1)),
            "dimensions": np.tile([3.9, 1.6, 1.6], (n, 1)),
            "location": np.tile([0.0, 1.0, 500.0], (n, 1)) + np.arange(n)[:, None] * [0.0, 0.0, 10.0],
            "rotation_y": np.zeros(n),
            "score": np.full(n, 1e-6),
            "boxes_lidar": np.tile([500.0, 0.0, -1.0, 3.9, 1.6, 1.6, 0.0], (n, 1)),
        }
        for key, value in extra.items():
            anno[key] = np.concatenate([anno[key], value.astype(anno[key].dtype)])
    return pickle.dumps(annos)


#: what differs between two submissions whatever the split: their identity, participant, times and file's size
_IDENTITY = {"id", "participant", "created_at", "sha256", "size", "scored_at", "location", "result_location"}
_IDENTITY |= {"accepted_at"}
_IDENTITY |= {"started_at", "finished_at", "submission"}


def without_identity(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: without_identity(v) for k, v in value.items() if k not in _IDENTITY}
    if isinstance(value, list):
        return [without_identity(v) for v in value]
    return value


def submit_queued(c: Any, headers: dict[str, str]) -> Any:
    """A submission answered at once (the service has no worker: it stays queued)."""
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post("/v1/benchmarks/bench/submissions", params={"wait": 0}, files=files, headers=headers)


def participant_views(c: Any, headers: dict[str, str], sid: str) -> dict[str, Any]:
    """Every JSON view a participant has of one of their submissions."""
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=headers))
    return {
        "own": ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=headers)),
        "listed": next(s for s in mine["items"] if s["id"] == sid),
        "job": ok(c.get(f"/v1/jobs/{sid}", headers=headers)),
    }


# -- 1. the secret split --------------------------------------------------------------------------------------


def test_where_a_participants_detections_fall_does_not_show_which_frames_are_public(split_world) -> None:
    """The same detections added to a public frame or to a private one (far from every box, scored below all):
    the participant's views of the two submissions are the same (a count over the public part told them apart,
    and 2^k detections in frame k read the whole split back)."""
    c, hosted = split_world
    bench = c.app.state.service.store.benchmark_store.get_benchmark("bench")
    frames = [a["frame_id"] for a in pickle.loads(golden_bytes("result.pkl"))]
    parts = part_frames(bench.split_seed, frames, 50)
    views = []
    for who, frame in (("alice", parts["public"][0]), ("bob", parts["private"][0])):  # each their first
        sid = ok(submit(c, hosted.headers(who), padded({frame: 7})), 201)["id"]
        views.append(participant_views(c, hosted.headers(who), sid))
    assert without_identity(views[0]) == without_identity(views[1])
    # what the participant is told about their own file does not depend on the split: its size and frames, and
    # its detections per class over the whole file
    result = views[0]["own"]["result"]
    assert result["frames"] == 50 and result["num_det"]["Car"] == views[1]["own"]["result"]["num_det"]["Car"]
    assert "num_gt" not in result and "curves" not in result


# -- 2. the quota counts what was scored ----------------------------------------------------------------------


def test_a_cancelled_submission_is_failed_with_its_reason_and_frees_its_slot(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000, ready=False, job_threads=0) as c:
        hosted = host(c, benchmark={"quota": "1/1"})
        alice = hosted.headers("alice")
        sid = submit_queued(c, alice).json()["id"]
        before = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
        assert before["quota"]["left"] == 0 and before["items"][0]["status"] == "accepted"
        ok(c.post(f"/v1/admin/jobs/{sid}/cancel", headers=ADMIN))
        after = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
        assert after["quota"] == {"submissions": 1, "days": 1.0, "used": 0, "left": 1, "next_at": None}
        item = after["items"][0]
        assert item["status"] == "failed" and "cancelled by an admin" in item["reason"]
        assert submit_queued(c, alice).status_code == 202  # the freed slot


def test_a_submission_whose_job_is_given_up_on_is_failed_and_frees_its_slot(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000, ready=False, job_threads=0) as c:
        hosted = host(c, benchmark={"quota": "1/1"})
        alice = hosted.headers("alice")
        sid = submit_queued(c, alice).json()["id"]
        store = c.app.state.service.store
        job = store.job_store.get_job(sid)
        now = job.accepted_at
        for attempt in range(2):  # a worker takes it and is lost, and the one that takes it over too
            claimed, _ = store.job_store.claim_job(
                f"w{attempt}", now=now, lease_until=now + timedelta(seconds=1), kinds=None
            )
            assert claimed is not None and claimed.id == sid
            now += timedelta(seconds=2)
        claimed, lost = store.job_store.claim_job("w-last", now=now, lease_until=now + timedelta(seconds=1), kinds=None)
        assert claimed is None and lost == [sid] and store.job_store.get_job(sid).state == "failed"
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
        assert mine["quota"]["left"] == 1
        item = mine["items"][0]
        assert item["status"] == "failed" and "worker was lost" in item["reason"]


# -- 3. one sealed set, one benchmark -------------------------------------------------------------------------


def test_a_test_set_is_one_benchmarks_unless_the_admin_says_it_is_shared(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        host(c)
        again = c.post("/v1/benchmarks", json={"name": "bench2", "ground_truth": "test-set"}, headers=ADMIN)
        assert again.status_code == 409, again.text
        assert "'bench'" in again.json()["error"]["message"] and "share_test_set" in again.json()["error"]["message"]
        body = {"name": "bench2", "ground_truth": "test-set", "share_test_set": True}
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)


# -- 4. where a request comes from ----------------------------------------------------------------------------


def _hidden_csrf(page: str) -> str:
    found = re.search(r'name="csrf" value="([^"]+)"', page)
    assert found, page[:500]
    return found.group(1)


def test_sign_in_refuses_a_csrf_pair_the_server_did_not_issue(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c)
        c.cookies.set(CSRF_COOKIE, "made-up-by-the-attacker", path="/signin")
        r = c.post("/signin", data={"token": hosted.tokens["bob"], "csrf": "made-up-by-the-attacker"})
        assert r.status_code == 403 and "kitti_eval_session" not in r.headers.get("set-cookie", "")
        c.cookies.clear()
        form = c.get("/signin")
        good = c.post(
            "/signin", data={"token": hosted.tokens["bob"], "csrf": _hidden_csrf(form.text)}, follow_redirects=False
        )
        assert good.status_code == 303, good.text[:500]


def test_sign_in_and_a_sessions_changes_from_another_origin_are_refused(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c)
        form = c.get("/signin")
        data = {"token": hosted.tokens["bob"], "csrf": _hidden_csrf(form.text)}
        evil = {"Origin": "http://testserver:8081"}  # another port of the same host
        assert c.post("/signin", data=data, headers=evil).status_code == 403
        assert c.post("/signin", data=data, headers={"Sec-Fetch-Site": "same-site"}).status_code == 403
        ok(c.post("/signin", data=data, headers={"Origin": "http://testserver"}, follow_redirects=False), 303)
        page = c.get("/benchmarks/bench")
        assert page.status_code == 200
        csrf = _hidden_csrf(page.text)  # the session's own token: refused for where it comes from alone
        r = c.post("/signout", data={"csrf": csrf}, headers=evil)
        assert r.status_code == 403, r.text[:300]
        ok(
            c.post("/signout", data={"csrf": csrf}, headers={"Origin": "http://testserver"}, follow_redirects=False),
            303,
        )


# -- 5. framing -----------------------------------------------------------------------------------------------


def test_pages_and_the_api_may_not_be_framed(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        host(c)
        for path in ("/signin", "/benchmarks/bench", "/v1/benchmarks/bench", "/healthz"):
            r = c.get(path)
            assert r.headers["x-frame-options"] == "DENY", path
            assert "frame-ancestors 'none'" in r.headers["content-security-policy"], path
            assert r.headers["x-content-type-options"] == "nosniff", path
            assert r.headers["referrer-policy"] == "same-origin", path


# -- 6. the sealed set's name and who takes part --------------------------------------------------------------


@pytest.fixture()
def teams_world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        teams = make_teams(c)
        body = {"name": "bench-a", "ground_truth": "sealed-a", "public": True, "quota": "5/1"}
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        yield c, teams


def test_an_anonymous_visitor_and_other_projects_never_read_the_sealed_sets_name(teams_world) -> None:
    c, teams = teams_world
    for headers in ({}, teams.headers("bob"), teams.headers("carol")):
        for path in ("/v1/benchmarks/bench-a", "/v1/benchmarks", "/v1/benchmarks/bench-a/leaderboard"):
            r = c.get(path, headers=headers)
            assert r.status_code == 200 and "sealed-a" not in r.text, (path, headers)
    assert "sealed-a" not in c.get("/benchmarks/bench-a").text
    assert ok(c.get("/v1/benchmarks/bench-a", headers=teams.headers("alice")))["ground_truth"] == "sealed-a"
    assert ok(c.get("/v1/benchmarks/bench-a", headers=ADMIN))["ground_truth"] == "sealed-a"


def test_a_public_benchmark_takes_part_from_its_projects_members_unless_it_is_open(teams_world) -> None:
    c, teams = teams_world
    data = golden_bytes("result.pkl")
    for who in ("bob", "carol"):
        r = submit(c, teams.headers(who), data, name="bench-a")
        assert r.status_code == 403 and "members of its test set's project" in r.text and "team-a" not in r.text
    assert submit(c, teams.headers("alice"), data, name="bench-a").status_code in (201, 202)
    body = {
        "name": "bench-open",
        "ground_truth": "sealed-a",
        "public": True,
        "open_to_all": True,
        "share_test_set": True,
    }
    ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
    r = submit(c, teams.headers("carol"), data, name="bench-open")
    assert r.status_code in (201, 202)
    # and follows its job where the answer points, although she is no member of the test set's project
    assert ok(c.get(f"/v1/jobs/{r.json()['id']}", headers=teams.headers("carol")))["id"] == r.json()["id"]


# -- smaller: the built-in callers' names, a removed member's jobs ---------------------------------------------


def test_no_user_takes_a_built_in_callers_name(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        for name in ("admin-token", "anyone", "Anonymous", "metrics-scraper", "admin", "Admin", "ADMIN"):
            r = c.post("/v1/admin/users", json={"name": name}, headers=ADMIN)
            assert r.status_code == 422 and "reserved" in r.text, (name, r.text)
        ok(c.post("/v1/admin/users", json={"name": "anyone-else"}, headers=ADMIN), 201)
        # a name equal to an existing one ignoring case is taken, as the name itself is
        for name in ("ANYONE-ELSE", "Anyone-Else"):
            r = c.post("/v1/admin/users", json={"name": name}, headers=ADMIN)
            assert r.status_code == 409 and "exists" in r.text, (name, r.text)


def test_a_removed_members_jobs_follow_their_current_rights(teams_world) -> None:
    c, teams = teams_world
    alice = teams.headers("alice")
    sid = submit(c, alice, golden_bytes("result.pkl"), name="bench-a").json()["id"]
    evaluation = teams.evaluations["gt-a"]
    assert c.get(f"/v1/jobs/{sid}", headers=alice).status_code == 200
    assert c.get(f"/v1/jobs/{evaluation}", headers=alice).status_code == 200
    assert c.delete("/v1/admin/members/alice/team-a", headers=ADMIN).status_code == 204
    for job_id in (sid, evaluation):
        r = c.get(f"/v1/jobs/{job_id}", headers=alice)
        assert r.status_code == 404 and "bench-a" not in r.text


def test_behind_https_the_cookies_are_host_prefixed(tmp_path) -> None:
    """Over HTTPS the session and sign-in cookies are ``__Host-`` cookies (Secure, Path=/, no Domain): a page on
    another port or a sibling subdomain cannot plant one, and a cookie without the prefix is not a session."""
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as plain:
        hosted = host(plain)
        c = TestClient(plain.app, base_url="https://testserver")
        form = c.get("/signin")
        assert form.headers["set-cookie"].startswith("__Host-kitti_eval_signin=")
        assert "Path=/;" in form.headers["set-cookie"] and "Secure" in form.headers["set-cookie"]
        r = c.post(
            "/signin", data={"token": hosted.tokens["bob"], "csrf": _hidden_csrf(form.text)}, follow_redirects=False
        )
        assert r.status_code == 303, r.text[:300]
        session = next(v for k, v in r.headers.multi_items() if k == "set-cookie" and "session" in v)
        assert session.startswith("__Host-kitti_eval_session=") and "Secure" in session and "Path=/;" in session
        # the form's cookie is cleared with the attributes it was set with (it was cleared SameSite=lax)
        cleared = next(v for k, v in r.headers.multi_items() if k == "set-cookie" and "signin" in v)
        set_with = form.headers["set-cookie"]
        for attribute in ("HttpOnly", "SameSite=strict", "Secure", "Path=/"):
            assert attribute in set_with and attribute in cleared, (attribute, set_with, cleared)
        assert "Max-Age=0" in cleared
        assert '<span class="who" id="who">bob</span>' in c.get("/").text
        value = c.cookies.get("__Host-kitti_eval_session")
        c.cookies.clear()
        c.cookies.set("kitti_eval_session", value)  # the same session under the name a plain-http page could set
        page = c.get("/")
        assert page.status_code == 401 and 'action="/signin"' in page.text and 'id="who"' not in page.text


def _scope(*headers: tuple[str, str], peer: str = "10.0.0.2", scheme: str = "http") -> dict[str, Any]:
    state = SimpleNamespace(trusted_proxies=(ip_network("10.0.0.0/8"),))
    return {
        "type": "http",
        "scheme": scheme,
        "client": (peer, 1234),
        "app": SimpleNamespace(state=state),
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers],
    }


def test_the_services_own_origin_behind_a_proxy() -> None:
    """Behind a proxy that rewrites Host (nginx's default) the browser's host comes in X-Forwarded-Host, taken
    from a trusted proxy only; a proxy that ends TLS shows http where the browser says https."""
    browser = ("Origin", "https://bench.example.org")
    assert cross_site(_scope(browser, ("Host", "127.0.0.1:8000"), ("X-Forwarded-Host", "bench.example.org"))) is None
    untrusted = _scope(browser, ("Host", "127.0.0.1:8000"), ("X-Forwarded-Host", "bench.example.org"), peer="8.8.8.8")
    assert cross_site(untrusted) is not None
    assert cross_site(_scope(browser, ("Host", "bench.example.org"))) is None
    assert cross_site(_scope(browser, ("Host", "bench.example.org:443"))) is None
    assert cross_site(_scope(("Origin", "https://bench.example.org:8443"), ("Host", "bench.example.org"))) is not None
    assert cross_site(_scope(("Origin", "http://bench.example.org"), ("Host", "bench.example.org"), scheme="https"))
    assert cross_site(_scope(("Host", "bench.example.org"))) is None  # no browser: curl, a script
    assert cross_site(_scope(("Sec-Fetch-Site", "same-site"), ("Host", "bench.example.org"))) is not None
    # a trusted proxy that ends TLS says so: the request came over HTTPS (Secure, __Host- cookies; http refused)
    https = ("X-Forwarded-Proto", "https")
    assert over_https(_scope(https)) and not over_https(_scope(https, peer="8.8.8.8")) and not over_https(_scope())
    assert cross_site(_scope(("Origin", "http://bench.example.org"), ("Host", "bench.example.org"), https))
    assert cross_site(_scope(browser, ("Host", "bench.example.org"), https)) is None
