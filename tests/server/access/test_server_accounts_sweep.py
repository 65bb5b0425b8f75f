"""Accounts mode swept: every route, method and parameter (the hostile requests of ``test_server_sweep``) sent
as someone who may not see or change what the request is about. None gets an answer >= 500, none reveals
another project's work, none changes what the caller may not change, and none lets a box of a sealed ground
truth out.

Callers: (a) no token, (b) a revoked and an expired token, (c) a member of another project, (d) a read-only
token, and, for the sealed set, a member of its own project. ``KITTI_EVAL_SWEEP_EXAMPLES`` sets the examples
per route and caller (default 12 here).
"""

from __future__ import annotations

import json
import os
import re
from datetime import datetime, timedelta, timezone
from typing import Any
from urllib.parse import unquote

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from server_accounts import Teams, add_token, bearer, make_teams
from server_helpers import ADMIN, GOLDEN, app_client, golden_bytes
from sqlalchemy import update
from test_server_sweep import ENDPOINTS, KNOWN, request_for

from kitti_eval.io.loaders import load_ground_truth
from kitti_eval_server.access.auth import SESSION_COOKIE
from kitti_eval_server.access.policy import Access
from kitti_eval_server.store import Store, tokens

EXAMPLES = int(os.environ.get("KITTI_EVAL_SWEEP_EXAMPLES", "12"))
ROLE_SWEEP = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=EXAMPLES <= 25,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)
#: routes that change something (besides the sign-in page, which only opens a session for a valid token)
WRITES = {
    "POST /v1/evaluations",
    "POST /ui/evaluations",
    "POST /v1/ground-truths",
    "DELETE /v1/ground-truths/{name}",
}
WRITES |= {e.id for e in ENDPOINTS if e.path.startswith("/v1/admin") and e.method in ("POST", "DELETE")}
WRITES |= {e.id for e in ENDPOINTS if e.path.startswith("/v1/benchmarks") and e.method == "POST"}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The two teams, plus a revoked and an expired token of alice's; the sweep's known values are theirs."""
    data = tmp_path_factory.mktemp("accounts-sweep") / "data"
    with app_client(data, auth="accounts", auth_max_failures=1_000_000, max_upload_mb=2) as c:
        teams = make_teams(c)
        revoked_id, teams.tokens["revoked"] = add_token(c, "alice")
        assert c.delete(f"/v1/admin/tokens/{revoked_id}", headers=ADMIN).status_code == 204
        expired_id, teams.tokens["expired"] = add_token(c, "alice", expires_days=1)
        store: Store = c.app.state.service.store
        with store.engine.begin() as conn:
            past = datetime.now(timezone.utc) - timedelta(days=1)
            conn.execute(update(tokens).where(tokens.c.id == expired_id).values(expires_at=past))
        # a benchmark of team-a's on a sealed set of its own, with one submission of alice's
        files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
        form = {"name": "bench-set", "project": "team-a", "sealed": "true"}
        assert c.post("/v1/ground-truths", data=form, files=files, headers=ADMIN).status_code == 201
        body = {"name": "bench", "ground_truth": "bench-set", "quota": "1000/1"}
        assert c.post("/v1/benchmarks", json=body, headers=ADMIN).status_code == 201
        pred = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
        r = c.post("/v1/benchmarks/bench/submissions", files=pred, headers=teams.headers("alice"))
        assert r.status_code == 201, r.text
        teams.evaluations["bench-submission"] = r.json()["id"]
        KNOWN.evaluation = teams.evaluations["gt-a"]
        KNOWN.values = [
            *teams.evaluations.values(),
            "gt-a",
            "sealed-a",
            "gt-b",
            "team-a",
            "team-b",
            "alice",
            "bob",
            *teams.token_ids.values(),
            "bench",
            "bench-set",
            "000001",
            "000002",
            "000007",
        ]
        yield c, teams


def snapshot(store: Store, *, skip_project: str | None = None) -> dict[str, Any]:
    """What the callers may not change: evaluations (but those of ``skip_project``), ground truths, users,
    projects, memberships and tokens, benchmarks and their submissions."""
    return {
        "evaluations": sorted(
            (r.id, r.project, r.gt_name)
            for r in store.evaluation_store.list_evaluations(limit=100_000)
            if r.project != skip_project
        ),
        "ground_truths": [
            (g.name, g.sha256, g.project, g.sealed) for g in store.ground_truth_store.list_ground_truths()
        ],
        "users": [(u.name, u.is_admin, u.projects) for u in store.account_store.list_users()],
        "projects": store.account_store.list_projects(),
        "tokens": [
            (t.id, t.user_name, t.scopes, t.revoked_at is None, t.expires_at) for t in store.account_store.list_tokens()
        ],
        "benchmarks": [
            (b.name, b.gt_name, b.closed, b.revealed, b.public) for b in store.benchmark_store.list_benchmarks()
        ],
        "submissions": [
            (x.id, x.participant, x.status, x.published, x.disqualified, x.method)
            for b in store.benchmark_store.list_benchmarks()
            for x in store.benchmark_store.list_submissions(b.name)
        ],
    }


def _send(client: Any, request: dict[str, Any], headers: dict[str, str]) -> Any:
    """The drawn request with the caller's credentials instead of any the drawing put in."""
    sent = {k: v for k, v in request["headers"].items() if k.lower() != "authorization"}
    sent.update(headers)
    client.cookies.clear()  # no session from an earlier answer
    return client.request(request["method"], request["url"], headers=sent, content=request["content"])


def _request_text(request: dict[str, Any]) -> str:
    body = request["content"] or b""
    return unquote(request["url"]) + body.decode("utf-8", "replace")


SWEPT = list(ENDPOINTS)


def is_public(client: Any, method: str, path: str) -> bool:
    """Whether the route serving ``path`` declared it may be read without a token (the door's own answer)."""
    _, access = client.app.state.door.access({"type": "http", "method": method, "path": path, "root_path": ""})
    return access in (Access.PUBLIC, Access.ANYONE)


@pytest.mark.parametrize("role", ["none", "revoked", "expired"])
@pytest.mark.parametrize("endpoint", SWEPT, ids=lambda e: e.id)
def test_without_a_valid_token_nothing_but_the_public_paths_answers(world, endpoint, role) -> None:
    c, teams = world
    headers = {} if role == "none" else bearer(teams.tokens[role])

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        response = _send(c, request, headers)
        assert response.status_code < 500, (request["url"][:200], response.text[:300])
        if not is_public(c, request["method"], unquote(request["url"].split("?", 1)[0])):
            assert response.status_code == 401, (request["method"], request["url"][:200], response.text[:300])
            assert "model-of-" not in response.text and teams.sha256["gt-a"] not in response.text

    sweep()


@pytest.mark.parametrize("endpoint", SWEPT, ids=lambda e: e.id)
def test_another_projects_member_learns_and_changes_nothing_of_it(world, endpoint) -> None:
    c, teams = world
    store: Store = c.app.state.service.store
    before = snapshot(store, skip_project="team-b")  # bob may add evaluations to his own project
    secrets = [teams.evaluations["gt-a"], teams.evaluations["sealed-a"], teams.sha256["gt-a"], "model-of-alice"]
    secrets += ["gt-a", "sealed-a", "team-a", "alice", teams.evaluations["bench-submission"], "bench-set"]

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        response = _send(c, request, teams.headers("bob"))
        assert response.status_code < 500, (request["url"][:200], response.text[:300])
        sent = _request_text(request)
        for secret in secrets:
            if secret not in sent:  # a message may quote what the caller sent, nothing more
                assert secret not in response.text, (secret, request["method"], request["url"][:200])

    sweep()
    assert snapshot(store, skip_project="team-b") == before


@pytest.mark.parametrize("endpoint", SWEPT, ids=lambda e: e.id)
def test_a_read_only_token_changes_nothing(world, endpoint) -> None:
    c, teams = world
    store: Store = c.app.state.service.store
    before = snapshot(store)

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        response = _send(c, request, teams.headers("alice-ro"))
        assert response.status_code < 500, (request["url"][:200], response.text[:300])
        if endpoint.id in WRITES:
            assert response.status_code >= 400, (request["method"], request["url"][:200], response.text[:300])

    sweep()
    assert snapshot(store) == before


# --------------------------------------------------------------------------------- the session cookie alone

#: the public forms that take no session (signing in, joining by an invitation) carry a CSRF token of their own
_NO_SESSION = ("/signin", "/join/{code}", "/v1/join/{code}")
CHANGES = [e for e in SWEPT if e.method in ("POST", "PUT", "PATCH", "DELETE") and e.path not in _NO_SESSION]


def _admin_session(c: Any, teams: Teams) -> str:
    """An admin's web session (the most a forged request could borrow): the cookie's value."""
    c.cookies.clear()
    form = c.get("/signin")
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)
    assert csrf is not None
    r = c.post("/signin", data={"token": teams.tokens["root"], "csrf": csrf.group(1)}, follow_redirects=False)
    assert r.status_code == 303, r.text
    session = c.cookies[SESSION_COOKIE]
    c.cookies.clear()
    return session


@pytest.mark.parametrize("endpoint", CHANGES, ids=lambda e: e.id)
def test_a_session_cookie_alone_changes_nothing(world, endpoint) -> None:
    """What a page of another site (or another port of this host) can send with the signed-in admin's cookie:
    every route that changes something, every drawn request, without the session's CSRF token."""
    c, teams = world
    store: Store = c.app.state.service.store
    session = _admin_session(c, teams)
    before = snapshot(store)

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        sent = {k: v for k, v in request["headers"].items() if k.lower() not in ("authorization", "x-csrf-token")}
        sent["cookie"] = f"{SESSION_COOKIE}={session}"
        c.cookies.clear()
        response = c.request(request["method"], request["url"], headers=sent, content=request["content"])
        assert 400 <= response.status_code < 500, (request["method"], request["url"][:200], response.text[:300])

    sweep()
    assert snapshot(store) == before


def test_a_well_formed_change_with_the_session_cookie_alone_is_refused(world) -> None:
    """The same, with requests that would succeed with the CSRF token: each is 403, and nothing changes."""
    c, teams = world
    store: Store = c.app.state.service.store
    session = _admin_session(c, teams)
    values = {
        "evaluation_id": teams.evaluations["gt-a"],
        "name": "bench",
        "submission_id": teams.evaluations["bench-submission"],
        "user": "alice",
        "project": "team-a",
        "token_id": teams.token_ids["carol"],
    }
    pred = golden_bytes("result.pkl")
    before = snapshot(store)
    for endpoint in CHANGES:
        path = endpoint.path
        for p in endpoint.path_params:
            path = path.replace("{" + p + "}", values.get(p, "gt-a"))
        kwargs: dict[str, Any] = {"headers": {"cookie": f"{SESSION_COOKIE}={session}"}}
        if endpoint.files:
            wanted = "predictions" if "predictions" in endpoint.files else endpoint.files[0]
            kwargs["files"] = {wanted: ("result.pkl", pred)}
            kwargs["data"] = {"gt": "gt-a", "name": "forged", "project": "team-a"}
        elif endpoint.json_fields:
            kwargs["json"] = {"name": "forged", "user": "carol", "project": "team-a", "method": "forged"}
        c.cookies.clear()
        response = c.request(endpoint.method, path, **kwargs)
        assert response.status_code == 403, (endpoint.id, response.status_code, response.text[:300])
    assert snapshot(store) == before


# ------------------------------------------------------------------------------------------ sealed boxes


def box_needles() -> list[str]:
    """The sealed set's boxes as the service would print them: each value as the frame view's JSON writes it
    (seven significant digits; values of fewer than five digits are too common to tell anything), and each
    bbox, location and size as the frame page's table writes them ("%.2f, %.2f, %.2f")."""
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    care = np.asarray(gt.name) != "DontCare"
    needles: set[str] = set()
    for field in ("bbox", "dimensions", "location", "rotation_y"):
        values = np.asarray(getattr(gt, field))[care]
        for v in values.reshape(-1):
            text = json.dumps(float(f"{float(v):.7g}"))
            if sum(ch.isdigit() for ch in text) >= 5:
                needles.add(text)
        if values.ndim == 2:
            needles.update(", ".join(f"{float(x):.2f}" for x in row) for row in values)
    return sorted(needles)


NEEDLES = box_needles()
# A needle counts where it stands as a number of its own, not inside a longer run of letters, digits or dots: a
# form's CSRF token ("<expiry>.<nonce>.<hex mac>") once held "...176.71..." across its first dot.
_ALONE = {n: re.compile(r"(?<![\w.])(?<!\w-)" + re.escape(n) + r"(?![\w.])") for n in NEEDLES}


def leaked(text: str) -> list[str]:
    return [n for n in NEEDLES if n in text and _ALONE[n].search(text)]


def test_the_needles_find_the_boxes_of_an_open_set(world) -> None:
    """The same file registered unsealed: its frame view and frame page show the boxes, and the needles find
    them (so that finding none below means something)."""
    c, teams = world
    a = teams.evaluations["gt-a"]
    api = c.get("/v1/frames/000001", params={"evaluation": a}, headers=teams.headers("alice"))
    page = c.get(f"/frames/000001?e={a}", headers=teams.headers("alice"))
    assert api.status_code == page.status_code == 200
    assert len(NEEDLES) > 500
    assert len(leaked(api.text)) >= 10 and len(leaked(page.text)) >= 5


@pytest.mark.parametrize("endpoint", SWEPT, ids=lambda e: e.id)
def test_no_box_of_a_sealed_set_leaves_the_service(world, endpoint) -> None:
    c, teams = world
    sealed = teams.evaluations["sealed-a"]
    frames = [f"{i:06d}" for i in range(1, 12)]
    alice = teams.headers("alice")

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        # aim at the sealed set: its evaluation and its frames
        for known in (teams.evaluations["gt-a"], teams.evaluations["gt-b"]):
            request["url"] = request["url"].replace(known, sealed)
        if "{" not in endpoint.path or data.draw(st.booleans()):
            request["url"] = request["url"].replace("000002", data.draw(st.sampled_from(frames)))
        response = _send(c, request, alice)
        assert response.status_code < 500, (request["url"][:200], response.text[:300])
        assert not leaked(response.text), (request["method"], request["url"][:200], leaked(response.text)[:5])

    sweep()
    for frame in frames:  # and directly: the frame view, the frame page, the worst frames, the evaluation
        for path in (f"/v1/frames/{frame}?evaluation={sealed}", f"/frames/{frame}?e={sealed}"):
            response = c.get(path, headers=alice)
            assert response.status_code == 403 and not leaked(response.text)
    for path in (f"/v1/evaluations/{sealed}", f"/evaluations/{sealed}", f"/v1/evaluations/{sealed}/frames"):
        assert not leaked(c.get(path, headers=alice).text)


def test_teams_are_as_the_sweep_assumes(world) -> None:
    _, teams = world
    assert isinstance(teams, Teams) and {"revoked", "expired"} <= set(teams.tokens)
