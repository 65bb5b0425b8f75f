"""One policy, closed by default: every route declares its access, the door refuses one that does not, no
service method defaults its caller, callers are made by the policy alone, and the table of who may do what
(docs/service/accounts.md) is the policy's own.

A web session's change carries its CSRF token whatever the door (a page form's field, a script's header):
the session cookie alone drives nothing.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from server_accounts import make_teams
from server_benchmarks import host, ok
from server_helpers import ADMIN, app_client

import kitti_eval_server
from kitti_eval_server.access.deps import PublicCaller
from kitti_eval_server.access.policy import RULES, Access, Caller, Policy
from kitti_eval_server.errors import Forbidden, Unauthorized
from kitti_eval_server.main import create_app
from kitti_eval_server.settings import AuthMode, Settings

ROOT = Path(__file__).resolve().parents[3]


def _app(tmp_path: Path, auth: str = "accounts"):
    return create_app(Settings(data_dir=tmp_path / "data", auth=auth, register_demo=False, warmup=False))


def _table(app) -> dict[str, Access | None]:
    out = {}
    for route, access in app.state.door.table():
        methods = sorted(m for m in (getattr(route, "methods", None) or {"GET"}) if m != "HEAD")
        for method in methods:
            out[f"{method} {getattr(route, 'path', '?')}"] = access
    return out


def test_every_route_of_the_app_declares_its_access(tmp_path) -> None:
    table = _table(_app(tmp_path))
    assert len(table) > 50
    undeclared = sorted(k for k, v in table.items() if v is None)
    assert undeclared == []
    # a few, as the docs' table has them
    assert table["GET /healthz"] is Access.PUBLIC and table["POST /signin"] is Access.PUBLIC
    assert table["GET /v1/benchmarks/{name}/leaderboard"] is Access.ANYONE
    assert table["GET /v1/evaluations/{evaluation_id}"] is Access.READER
    assert table["POST /v1/evaluations"] is Access.WRITER
    assert table["POST /v1/benchmarks/{name}/submissions"] is Access.WRITER
    assert table["POST /v1/benchmarks/{name}/reveal"] is Access.ADMIN
    assert table["GET /v1/admin/audit"] is Access.ADMIN
    assert table["GET /metrics"] is Access.SCRAPER
    assert table["GET /docs"] is Access.PUBLIC and table["GET /static"] is Access.PUBLIC  # the API's docs
    assert table["GET /openapi.json"] is Access.PUBLIC


@pytest.mark.parametrize("auth", ["open", "accounts"])
def test_a_route_that_declares_nothing_is_refused(tmp_path, auth) -> None:
    """Fail closed: a route added without an access (as a careless new route would be) never runs."""
    app = _app(tmp_path, auth)
    ran = []

    @app.get("/v1/forgot-to-ask")
    def forgot() -> dict[str, str]:
        ran.append(1)
        return {"secret": "everything"}

    @app.get("/v1/asked")
    def asked(caller: PublicCaller) -> dict[str, str]:
        return {"caller": caller.name}

    from fastapi.testclient import TestClient

    with TestClient(app) as c:
        r = c.get("/v1/forgot-to-ask", headers=ADMIN)
        assert r.status_code == 403 and "declares no access" in r.json()["error"]["message"]
        assert ran == [] and "everything" not in r.text
        assert c.get("/v1/asked").json() == {"caller": "anonymous" if auth == "accounts" else "anyone"}


def _server_modules() -> list:
    return [  # walked by full names: a bare "web" could be another folder on the path (tests/web)
        importlib.import_module(m.name)
        for m in pkgutil.walk_packages(kitti_eval_server.__path__, prefix="kitti_eval_server.")
        if not m.name.startswith("kitti_eval_server.web.templates")
    ]


def test_no_method_of_the_service_defaults_its_caller() -> None:
    """A call that forgets the caller is a TypeError, never a caller that sees everything."""
    checked, defaulted = 0, []
    for module in _server_modules():
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != module.__name__:
                continue
            for name, fn in inspect.getmembers(cls, inspect.isfunction):
                parameter = inspect.signature(fn).parameters.get("caller")
                if parameter is not None:
                    checked += 1
                    if parameter.default is not inspect.Parameter.empty:
                        defaulted.append(f"{cls.__name__}.{name}")
    assert checked >= 15 and defaulted == []


def _outside_the_policy() -> Iterator[tuple[Path, ast.AST]]:
    """Every module of the service and the library but server/access/policy.py and server/access/accounts.py: its
    path and each node of its syntax tree."""
    allowed = {ROOT / "server" / "access" / "policy.py", ROOT / "server" / "access" / "accounts.py"}
    for folder in (ROOT / "server", ROOT / "kitti_eval"):
        for path in folder.rglob("*.py"):
            if path not in allowed:
                for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                    yield path, node


def test_callers_are_made_by_the_policy_alone() -> None:
    """No module of the service or the command line builds a Caller itself (the policy's constructors, and the
    accounts resolving a token, are the only places)."""
    found = [
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for path, node in _outside_the_policy()
        if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == "Caller"
    ]
    assert found == []


#: what a caller may do and the mode the service runs in: read only by the policy (and the accounts, which make
#: callers from their records)
_RIGHTS = frozenset({"is_admin", "projects", "scopes", "signed_in", "session", "token_id", "can_write"})


def test_nothing_but_the_policy_reads_a_callers_rights_or_the_mode() -> None:
    """Outside server/access/policy.py and server/access/accounts.py no code reads a Caller's rights (is_admin,
    projects, scopes, signed_in, session, token_id, can_write) or the policy's mode: it asks the policy a question."""
    found = []
    for path, node in _outside_the_policy():
        if not isinstance(node, ast.Attribute):
            continue
        owner = node.value
        named = owner.id if isinstance(owner, ast.Name) else getattr(owner, "attr", "")
        if (node.attr in _RIGHTS and named in ("caller", "signed", "admitted")) or (
            node.attr in ("accounts", "mode") and named == "policy"
        ):
            found.append(f"{path.relative_to(ROOT)}:{node.lineno} {named}.{node.attr}")
    assert found == []


def test_a_caller_made_without_saying_otherwise_is_nobody_and_a_policy_needs_its_test_sets() -> None:
    nobody = Caller("x")
    assert (nobody.is_admin, nobody.projects, nobody.scopes, nobody.signed_in) == (
        False,
        frozenset(),
        frozenset(),
        False,
    )
    policy = Policy(AuthMode.ACCOUNTS, admin_token=lambda: "t", test_sets=lambda: {"gt": ["b"]})
    assert not policy.sees_project(nobody, "p") and not policy.is_participant(nobody)
    with pytest.raises(Unauthorized):
        policy.admit(Access.READER, nobody, method="GET", bearer=None, csrf=None)
    with pytest.raises(Forbidden):  # signed in, and no scope it was not given
        policy.admit(Access.WRITER, Caller("y", signed_in=True), method="POST", bearer=None, csrf=None)
    with pytest.raises(TypeError):
        Policy(AuthMode.ACCOUNTS, admin_token=lambda: "t")  # type: ignore[call-arg]


def test_the_readme_table_is_the_policy() -> None:
    text = (ROOT / "docs" / "service" / "accounts.md").read_text()
    start = text.index("| Route group | Access | A member | An admin |")
    rows = []
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows.append((cells[0], cells[1].strip("`"), cells[2], cells[3]))
    assert rows == [(group, access.value, member, admin) for group, access, member, admin in RULES]
    # and the accesses the table names are the ones the routes declare
    declared = set(_table(create_app(Settings(data_dir=ROOT / "unused", warmup=False))).values())
    assert {Access(a) for _, a, _, _ in rows} == declared


# -------------------------------------------------------------------------------------- sessions and CSRF


def _hidden(html: str, name: str = "csrf") -> str:
    found = re.search(rf'name="{name}" value="([^"]+)"', html)
    assert found, html[:2000]
    return found.group(1)


def _sign_in(c, token: str) -> str:
    """A web session for ``token``; returns the page's CSRF token."""
    c.cookies.clear()
    form = c.get("/signin")
    r = c.post("/signin", data={"token": token, "csrf": _hidden(form.text)}, follow_redirects=False)
    assert r.status_code == 303, r.text
    return _hidden(c.get("/").text)


@pytest.fixture(scope="module")
def hosted(tmp_path_factory):
    data = tmp_path_factory.mktemp("policy") / "data"
    with app_client(data, auth="accounts", auth_max_failures=1000) as c:
        yield c, host(c)


def test_the_session_cookie_alone_drives_no_admin_action(hosted) -> None:
    c, h = hosted
    csrf = _sign_in(c, h.tokens["root"])  # an admin signed in on the pages
    for action in ("close", "reveal", "reopen", "rescore"):
        r = c.post(f"/v1/benchmarks/bench/{action}")
        assert r.status_code == 403 and "X-CSRF-Token" in r.json()["error"]["message"], (action, r.text)
        r = c.post(f"/v1/benchmarks/bench/{action}", headers={"X-CSRF-Token": "0" * 64})
        assert r.status_code == 403, action
    assert ok(c.get("/v1/benchmarks/bench"))["open"] is True  # reading with the cookie is fine; nothing changed
    assert ok(c.post("/v1/benchmarks/bench/close", headers={"X-CSRF-Token": csrf}))["open"] is False
    assert ok(c.post("/v1/benchmarks/bench/reopen", headers={"X-CSRF-Token": csrf}))["open"] is True
    c.cookies.clear()


def test_the_session_cookie_alone_uploads_nothing(hosted) -> None:
    c, h = hosted
    _sign_in(c, h.tokens["alice"])
    files = {"predictions": ("result.pkl", b"x" * 2_000_000)}
    before = ok(c.get("/v1/benchmarks/bench/submissions"))["quota"]
    r = c.post("/v1/benchmarks/bench/submissions", files=files)
    assert r.status_code == 403 and r.headers["connection"] == "close"  # refused before the body is read
    r = c.post("/v1/evaluations", data={"gt": "demo"}, files=files)
    assert r.status_code == 403
    assert ok(c.get("/v1/benchmarks/bench/submissions"))["quota"] == before
    c.cookies.clear()
    # a bearer token needs no CSRF token: another site's page cannot send it
    assert c.post("/v1/benchmarks/bench/close", headers=h.headers("root")).status_code == 200
    assert c.post("/v1/benchmarks/bench/reopen", headers=h.headers("root")).status_code == 200


def test_a_member_evaluates_against_no_benchmark_test_set(hosted) -> None:
    """The quota is not nominal: the test set is scored only through submissions; the upload form does not
    offer it; admins may evaluate against it (their baselines), and that is audited."""
    from server_helpers import golden_bytes

    c, h = hosted
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
    r = c.post("/v1/evaluations", data={"gt": "test-set"}, files=files, headers=h.headers("alice"))
    assert r.status_code == 403 and "'bench'" in r.json()["error"]["message"], r.text
    assert "AP" not in r.text and "Car" not in r.text
    page = c.get("/", headers=h.headers("alice")).text
    assert 'value="test-set"' not in page and 'value="demo"' in page
    ok(c.post("/v1/admin/projects", json={"name": "hosts"}, headers=ADMIN), 201)
    r = c.post("/v1/evaluations", data={"gt": "test-set", "project": "hosts"}, files=files, headers=h.headers("root"))
    assert r.status_code == 201, r.text
    audit = ok(c.get("/v1/admin/audit", headers=ADMIN))["items"]
    assert any(a["action"] == "evaluation.test_set" and a["actor"].startswith("root") for a in audit)
    assert 'value="test-set"' in c.get("/", headers=h.headers("root")).text


def test_a_member_of_a_project_sees_and_changes_what_the_policy_says(tmp_path) -> None:
    """The services ask the policy: another project's evaluation is a 404, a read-only token writes nothing."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        teams = make_teams(c)
        theirs = teams.evaluations["gt-b"]
        assert c.get(f"/v1/evaluations/{theirs}", headers=teams.headers("alice")).status_code == 404
        assert c.get(f"/v1/evaluations/{theirs}", headers=teams.headers("bob")).status_code == 200
        r = c.post("/v1/evaluations", data={"gt": "gt-a"}, headers=teams.headers("alice-ro"))
        assert r.status_code == 403 and "read-only" in r.text


# ------------------------------------------------------------------------- every route, through the policy


def _spied_methods(service) -> list[tuple[object, str]]:
    """(part, method name) of every method of the service's parts that takes a caller."""
    found = []
    hosted = service.benchmarks
    benchmarks = (hosted.catalog, hosted.submissions, hosted.scoring, hosted.board, hosted.intervals)
    parts = (service.evaluations, service.evaluation_frames, service.gt_catalog, *benchmarks, service.accounts)
    for part in (*parts, service.job_admin):
        for name, fn in inspect.getmembers(type(part), inspect.isfunction):
            if not name.startswith("_") and "caller" in inspect.signature(fn).parameters:
                found.append((part, name))
    return found


def test_every_route_reaches_the_services_with_a_caller_the_policy_decided(tmp_path, monkeypatch) -> None:
    """Walk every route of the app as an admin, a member, a read-only member and without a token; every
    call of a service method that takes a caller gets one the policy admitted for the request (or the accounts
    resolved from a token, for the sign-in form), never one a route made up; nothing answers 5xx."""
    from server_helpers import golden_bytes
    from test_server_sweep import ENDPOINTS

    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        teams = make_teams(c)
        files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
        ok(c.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=files, headers=ADMIN), 201)
        body = {"name": "bench", "ground_truth": "test-set", "quota": "100/1", "public": True}
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        pred = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
        submission = ok(c.post("/v1/benchmarks/bench/submissions", files=pred, headers=teams.headers("alice")), 201)
        service = c.app.state.service

        decided: list[object] = []
        admit, resolve = service.policy.admit, service.accounts.resolve

        def admitted(*args, **kwargs):
            caller = admit(*args, **kwargs)
            decided.append(caller)
            return caller

        def resolved(*args, **kwargs):
            caller = resolve(*args, **kwargs)
            decided.append(caller)
            return caller

        calls: list[str] = []
        strays: list[str] = []

        def spy(part, name):
            method = getattr(part, name)
            signature = inspect.signature(method)

            def wrapper(*args, **kwargs):
                caller = signature.bind(*args, **kwargs).arguments["caller"]
                calls.append(f"{type(part).__name__}.{name}")
                base = getattr(caller, "token_id", None), getattr(caller, "name", None)
                # the sign-in form's session is opened for the resolved caller, seen from the client's address
                if not any(caller is d or (name == "open_session" and base == (d.token_id, d.name)) for d in decided):
                    strays.append(f"{type(part).__name__}.{name}: {caller!r}")
                return method(*args, **kwargs)

            return wrapper

        monkeypatch.setattr(service.policy, "admit", admitted)
        monkeypatch.setattr(service.accounts, "resolve", resolved)
        for part, name in _spied_methods(service):
            monkeypatch.setattr(part, name, spy(part, name))

        values = {
            "evaluation_id": teams.evaluations["gt-a"],
            "other_id": teams.evaluations["sealed-a"],
            "name": "bench",
            "submission_id": submission["id"],
            "frame_id": "000001",
            "user": "alice",
            "project": "team-a",
            "token_id": teams.token_ids["carol"],
            "path": "app.css",
        }
        roles = {"admin": ADMIN, "alice": teams.headers("alice"), "alice-ro": teams.headers("alice-ro"), "none": {}}
        statuses = []
        for endpoint in ENDPOINTS:
            if endpoint.method == "DELETE" and endpoint.path.startswith(("/v1/admin", "/v1/ground-truths")):
                continue  # the walk keeps its world
            path = endpoint.path
            for p in endpoint.path_params:
                path = path.replace("{" + p + "}", values.get(p, "x"))
            if path.endswith("/v1/benchmarks/bench/close"):
                continue  # keeps the benchmark open for the routes after it
            query = f"?evaluation={values['evaluation_id']}" if "evaluation" in endpoint.query else ""
            for role, headers in roles.items():
                c.cookies.clear()
                kwargs: dict = {"headers": headers}
                if endpoint.method == "POST" and endpoint.files:
                    kwargs["files"] = pred if "predictions" in endpoint.files else files
                    kwargs["data"] = {"gt": "gt-a", "name": "walked", "project": "team-a"}
                elif endpoint.method == "POST" and endpoint.json_fields:
                    kwargs["json"] = {"name": "walked", "user": "alice", "project": "team-a", "method": "m"}
                r = c.request(endpoint.method, path + query, **kwargs)
                statuses.append((endpoint.id, role, r.status_code))
                assert r.status_code < 500, (endpoint.id, role, r.text[:300])
        assert strays == []
        reached = set(calls)
        assert len(reached) >= 20, sorted(reached)  # the walk reached the services, or it proves nothing
        for expected in (
            "Evaluations.accept",
            "Evaluations.get",
            "GroundTruthCatalog.listed",
            "Leaderboard.leaderboard",
            "Submissions.submit",
        ):
            assert expected in reached
        assert any(s == 200 for _, role, s in statuses if role == "none")  # public routes answered anonymously
        anonymous = {(e, s) for e, role, s in statuses if role == "none" and not (s in (401, 404, 405) or s < 300)}
        assert anonymous == {("POST /signin", 403)}  # the sign-in form without its own CSRF cookie


def test_an_evaluation_against_a_benchmarks_test_set_scores_nothing_for_a_member(tmp_path) -> None:
    """Made before the benchmark existed, it would score the test set beyond the quota: once the set is a
    benchmark's, a member can no longer read, list, gate, compare or look into it; an admin still can."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        teams = make_teams(c)
        old, other = teams.evaluations["sealed-a"], teams.evaluations["gt-a"]
        alice = teams.headers("alice")
        assert c.get(f"/v1/evaluations/{old}", headers=alice).status_code == 200  # before: a project's evaluation
        body = {"name": "bench", "ground_truth": "sealed-a", "quota": "1/30"}
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        assert c.get(f"/v1/evaluations/{old}", headers=alice).status_code == 404
        listed = [e["id"] for e in ok(c.get("/v1/evaluations", headers=alice))["items"]]
        assert old not in listed and other in listed
        assert c.get(f"/v1/evaluations/{old}/compare/{other}", headers=alice).status_code == 404
        assert (
            c.post("/v1/gates", json={"evaluation": old, "min": ["Car/3d/moderate >= 0"]}, headers=alice).status_code
            == 404
        )
        assert c.get(f"/v1/evaluations/{old}/frames", headers=alice).status_code == 404
        assert f"/evaluations/{old}" not in c.get("/", headers=alice).text
        assert c.get(f"/v1/evaluations/{old}", headers=teams.headers("root")).status_code == 200
        assert old in [e["id"] for e in ok(c.get("/v1/evaluations", headers=teams.headers("root")))["items"]]


def test_a_path_no_route_serves_is_a_404_that_spoils_no_sign_in_form(tmp_path) -> None:
    """A browser showing the sign-in form also asks for /favicon.ico: its answer must not set a new sign-in
    CSRF cookie, or the form it is showing could not be sent."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        r = c.get("/favicon.ico")
        assert r.status_code == 404 and "set-cookie" not in r.headers
        assert c.get("/v1/no-such-thing").status_code == 401  # the API asks for a token first, as before
        assert c.get("/").status_code == 401  # a page that exists still asks for a token


def test_no_class_of_the_service_needs_400_lines() -> None:
    sizes = {}
    for path in (ROOT / "server").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                sizes[f"{path.relative_to(ROOT)}:{node.name}"] = node.end_lineno - node.lineno + 1
    assert len(sizes) > 30 and max(sizes.values()) < 400, max(sizes.items(), key=lambda kv: kv[1])


def test_routes_call_the_parts_never_the_store() -> None:
    """The routes and pages reach the database only through the service's parts."""
    found = []
    for folder in (ROOT / "server" / "routes", ROOT / "server" / "web"):
        for path in folder.rglob("*.py"):
            text = path.read_text(encoding="utf-8")
            found += [f"{path.name}: {m}" for m in re.findall(r"\.store\.\w+", text)]
    assert found == []
