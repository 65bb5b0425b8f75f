"""A sweep over every route of the app with hostile parameters: no answer is ever a 5xx.

The routes come from ``app.routes``, so a new endpoint is swept without a change here. Each request fills
the route's path, query and form (or JSON) parameters, and now and then names it does not declare, with
values that are out of range, huge (2**63, 10**400), negative, not numbers, not UTF-8 (``%ff%fe``), empty or
very long, mixed with valid ones (so that requests also get past validation); routes that need the admin
token are tried with it and without. A few seconds in the suite; ``KITTI_EVAL_SWEEP_EXAMPLES=2000 pytest
tests/server/access/test_server_sweep.py`` runs longer (and random rather than repeatable).
"""

from __future__ import annotations

import json
import os
import tempfile
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
from fastapi.params import File, Form
from fastapi.routing import APIRoute
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from server_helpers import ADMIN, ADMIN_TOKEN, assert_error, golden_bytes, register, upload
from starlette.routing import Mount

from kitti_eval_server import Settings, create_app
from kitti_eval_server.access.deps import require_admin

EXAMPLES = int(os.environ.get("KITTI_EVAL_SWEEP_EXAMPLES", "25"))
SWEEP = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=EXAMPLES <= 25,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# ------------------------------------------------------------------------------------------------ routes


@dataclass(frozen=True)
class Endpoint:
    """One route and method, with the names of what it takes (aliases, as a client sends them)."""

    method: str
    path: str
    path_params: tuple[str, ...] = ()
    query: tuple[str, ...] = ()
    form: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    json_fields: tuple[str, ...] = ()
    admin: bool = False
    mount: bool = False
    #: the query and form parameters that are numbers
    numbers: tuple[str, ...] = ()

    @property
    def id(self) -> str:
        return f"{self.method} {self.path}"


def _routes(routes: Any) -> list[Any]:
    """The routes, with those of included routers (newer FastAPI keeps an included router whole)."""
    out = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        out += _routes(inner.routes) if inner is not None else [route]
    return out


def _endpoints(app: Any) -> list[Endpoint]:
    out = []
    for route in _routes(app.routes):
        if isinstance(route, Mount):
            out.append(Endpoint("GET", route.path + "/{path}", ("path",), mount=True))
            continue
        if not isinstance(route, APIRoute):  # the OpenAPI document and the docs pages
            for method in sorted(set(getattr(route, "methods", None) or {"GET"}) - {"HEAD"}):
                out.append(Endpoint(method, route.path, tuple(getattr(route, "param_convertors", {}))))
            continue
        dependants = _all_dependants(route.dependant)
        body = [f for d in dependants for f in d.body_params]
        form = tuple(f.alias for f in body if isinstance(f.field_info, Form))
        files = tuple(f.alias for f in body if isinstance(f.field_info, File))
        json_fields: tuple[str, ...] = ()
        for f in body:
            if not isinstance(f.field_info, (Form, File)):
                model = f.field_info.annotation
                json_fields = tuple(getattr(model, "model_fields", {}) or (f.alias,))
        admin = any(d.call is require_admin for d in dependants)
        params = [f for d in dependants for f in d.query_params] + [f for f in body if isinstance(f.field_info, Form)]
        numbers = _unique(f.alias for f in params if _is_number(f.field_info.annotation))
        for method in sorted(route.methods - {"HEAD"}):
            out.append(
                Endpoint(
                    method,
                    route.path,
                    _unique(f.alias for d in dependants for f in d.path_params),
                    _unique(f.alias for d in dependants for f in d.query_params),
                    form,
                    files,
                    json_fields,
                    admin,
                    numbers=numbers,
                )
            )
    return out


def _is_number(annotation: Any) -> bool:
    """int or float, alone or in a union (``int | None``, ``list[float]``)."""
    if annotation in (int, float):
        return True
    return any(_is_number(a) for a in typing.get_args(annotation))


def _unique(names: Any) -> tuple[str, ...]:
    return tuple(dict.fromkeys(names))


def _all_dependants(dependant: Any) -> list[Any]:
    found = [dependant]
    for sub in dependant.dependencies:
        found += _all_dependants(sub)
    return found


def _app_endpoints() -> list[Endpoint]:
    """The app's routes, from an app that is built and never started (nothing touches the disk)."""
    unused = Path(tempfile.gettempdir()) / "kitti-eval-sweep-unused"
    return _endpoints(create_app(Settings(data_dir=unused, admin_token=ADMIN_TOKEN)))


ENDPOINTS = _app_endpoints()
#: every name any route takes: tried on the others too (the web form reads its fields itself)
ALL_FIELDS = sorted({n for e in ENDPOINTS for n in (*e.query, *e.form, *e.path_params)})
ALL_FILES = sorted({n for e in ENDPOINTS for n in e.files}) or ["file"]


# ------------------------------------------------------------------------------------------------ values


@dataclass
class Known:
    """Values that exist on the swept service, so that some requests get past the lookups."""

    evaluation: str = ""
    values: list[str] = field(default_factory=list)


KNOWN = Known()

HOSTILE_NUMBERS = [
    str(2**63),
    str(-(2**63) - 1),
    str(2**64),
    "1" + "0" * 400,  # 10**400
    "-" + "9" * 5000,
    "-1",
    "0",
    "-0",
    "1e400",
    "-1e400",
    "1e-400",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "Infinity",
    "0x10",
    "1_000",
    " 7 ",
    "1.5",
    "١٢",  # Arabic-Indic digits
]
HOSTILE_TEXT = ["", " ", "\x00", "A" * 10_000, "é" * 300, "../../etc/passwd", "%", "a=b=c", "key=", "=v", "\r\nX: y"]
VALID = ["demo", "small", "Car", "Pedestrian", "3d", "bev", "aos", "strict", "loose", "moderate", "hard", "json"]
VALID += ["markdown", "table", "junit", "000001", "official", "openpcdet", "Car,Van", "0,30,inf", "model=m"]
VALID += ["Car=0.7,0.7,0.7", "Car/3d/moderate >= 10", "0.5", "1", "20", "true"]


@st.composite
def raw_value(draw: st.DrawFn) -> str:
    """A value as it appears in a URL or an urlencoded form: percent-encoded, or raw bytes that are not UTF-8."""
    kind = draw(st.sampled_from(["number", "text", "valid", "known", "random", "not utf-8", "integer", "float"]))
    if kind == "not utf-8":
        return draw(st.sampled_from(["%ff%fe", "%c3%28", "%80", "%ed%a0%80", "abc%ff", "%00%ff"]))
    return quote(draw(value()), safe="")


@st.composite
def value(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(["number", "text", "valid", "known", "random", "integer", "float"]))
    if kind == "number":
        return draw(st.sampled_from(HOSTILE_NUMBERS))
    if kind == "text":
        return draw(st.sampled_from(HOSTILE_TEXT))
    if kind == "valid":
        return draw(st.sampled_from(VALID))
    if kind == "known":
        return draw(st.sampled_from(KNOWN.values or VALID))
    if kind == "integer":
        return str(draw(st.integers(min_value=-(2**70), max_value=2**70)))
    if kind == "float":
        return repr(draw(st.floats(allow_nan=True, allow_infinity=True)))
    return draw(st.text(max_size=40))


def byte_value(draw: st.DrawFn) -> bytes:
    """A form field's bytes: UTF-8 text, or bytes that are not UTF-8."""
    if draw(st.booleans()):
        return draw(value()).encode("utf-8", "surrogatepass")
    return draw(st.sampled_from([b"\xff\xfe", b"\xc3\x28", b"abc\x80", b"\xed\xa0\x80", b"\x00\xff" * 100]))


# ---------------------------------------------------------------------------------------------- requests

BOUNDARY = "sweep-boundary-51b2"


def _multipart(fields: list[tuple[str, bytes]], files: list[tuple[str, bytes]]) -> bytes:
    parts = [
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n'.encode() + v + b"\r\n" for k, v in fields
    ]
    parts += [
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{k}"; filename="up.bin"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n".encode()
        + v
        + b"\r\n"
        for k, v in files
    ]
    return b"".join(parts) + f"--{BOUNDARY}--\r\n".encode()


def _file_bytes(draw: st.DrawFn) -> bytes:
    return draw(
        st.sampled_from(
            [b"", b"\x80\x04", golden_bytes("result.pkl"), golden_bytes("kitti_infos_val.pkl"), b"PK\x03\x04junk"]
        )
    )


def _json_value(draw: st.DrawFn) -> Any:
    return draw(
        st.one_of(
            st.builds(str, value()),
            st.integers(min_value=-(2**80), max_value=2**80),
            st.floats(),
            st.none(),
            st.lists(value(), max_size=5),
            st.just([{"a": 1}]),
            st.just({"nested": [1, 2]}),
        )
    )


@st.composite
def request_for(draw: st.DrawFn, endpoint: Endpoint) -> dict[str, Any]:
    path = endpoint.path
    for name in endpoint.path_params:
        if endpoint.mount:
            segment = draw(st.sampled_from(["app.css", "app.js", "..%2f..%2fetc%2fpasswd", "%ff%fe", "x" * 300]))
        else:
            segment = draw(raw_value())
        path = path.replace("{" + name + "}", segment or "x")
    names = list(endpoint.query) + draw(st.lists(st.sampled_from(ALL_FIELDS), max_size=2))
    query = [(n, draw(raw_value())) for n in names if draw(st.integers(0, 3))]  # each left out now and then
    url = path + ("?" + "&".join(f"{quote(k, safe='')}={v}" for k, v in query) if query else "")
    headers: dict[str, str] = {}
    if endpoint.admin and draw(st.booleans()):
        headers.update(ADMIN)
    elif draw(st.integers(0, 9)) == 0:
        headers["authorization"] = draw(st.sampled_from(["Bearer ", "Bearer x", "Basic Zm9v", "Bearer " + "A" * 5000]))
    if draw(st.integers(0, 9)) == 0:
        headers["accept"] = draw(st.sampled_from(["text/plain", "text/markdown;q=nan", "*/*;q=1e400", "x" * 300]))
    content: bytes | None = None
    if endpoint.method in ("POST", "PUT", "PATCH"):
        if endpoint.json_fields:
            body = {n: _json_value(draw) for n in endpoint.json_fields if draw(st.integers(0, 3))}
            content = json.dumps(body, allow_nan=True).encode()
            headers["content-type"] = "application/json"
        elif draw(st.integers(0, 4)):
            names = list(endpoint.form) + draw(st.lists(st.sampled_from(ALL_FIELDS), max_size=3))
            fields = [(n, byte_value(draw)) for n in names if draw(st.integers(0, 3))]
            files = [(n, _file_bytes(draw)) for n in endpoint.files or ALL_FILES if draw(st.integers(0, 4))]
            content = _multipart(fields, files)
            headers["content-type"] = f"multipart/form-data; boundary={BOUNDARY}"
        else:
            pairs = [(n, draw(raw_value())) for n in list(endpoint.form) + ALL_FIELDS[:3] if draw(st.booleans())]
            content = "&".join(f"{k}={v}" for k, v in pairs).encode()
            headers["content-type"] = "application/x-www-form-urlencoded"
    return {"method": endpoint.method, "url": url, "headers": headers, "content": content}


# ------------------------------------------------------------------------------------------------- sweep


@pytest.fixture(scope="module")
def client(service_client):
    with service_client(max_upload_mb=2) as c:
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        response = upload(c, golden_bytes("result.pkl"), gt="small")
        assert response.status_code == 201, response.text
        KNOWN.evaluation = response.json()["id"]
        other = upload(c, golden_bytes("result.pkl"), gt="small", fields={"protocol": "openpcdet"}).json()["id"]
        KNOWN.values = [KNOWN.evaluation, other, "small", "000001", "000002"]
        yield c


def test_the_sweep_covers_every_route_of_the_running_app(client) -> None:
    assert {e.id for e in _endpoints(client.app)} == {e.id for e in ENDPOINTS}
    documented = {f"{method.upper()} {path}" for path, ops in client.app.openapi()["paths"].items() for method in ops}
    assert documented <= {e.id for e in ENDPOINTS}
    paths = {e.path for e in ENDPOINTS}
    assert {"/", "/ui/evaluations", "/frames/{frame_id}", "/static/{path}", "/docs"} <= paths  # and the pages
    assert any(e.admin for e in ENDPOINTS) and any(e.files for e in ENDPOINTS) and any(e.json_fields for e in ENDPOINTS)


@pytest.mark.parametrize("endpoint", ENDPOINTS, ids=lambda e: e.id)
def test_no_parameter_makes_a_route_answer_5xx(client, endpoint) -> None:
    @SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        response = client.request(**request)
        assert response.status_code < 500, (request["method"], request["url"][:300], response.text[:500])
        if response.status_code >= 400 and response.headers.get("content-type", "").startswith("application/json"):
            err = response.json()["error"]
            assert err["code"] and err["message"] and len(err["message"]) <= 1100

    sweep()
    assert client.get("/readyz").status_code == 200


#: no bounded number: out of any sensible range, not finite, not a number, empty, not UTF-8
NOT_A_BOUNDED_NUMBER = [str(2**63), str(-(2**63) - 1), "1" + "0" * 400, "1e400", "-1e400", "nan", "inf", "-inf"]
NOT_A_BOUNDED_NUMBER += ["", "abc", "%ff%fe", "1e", "0x10"]
NUMERIC = [(e, name) for e in ENDPOINTS for name in e.numbers]


def test_the_numeric_parameters_are_found() -> None:
    assert {"limit", "offset", "worst", "score_threshold"} <= {name for _, name in NUMERIC}


@pytest.mark.parametrize(("endpoint", "name"), NUMERIC, ids=[f"{e.id} {n}" for e, n in NUMERIC])
def test_every_numeric_parameter_is_bounded(client, endpoint, name) -> None:
    path = endpoint.path.replace("{evaluation_id}", KNOWN.evaluation).replace("{frame_id}", "000001")
    for raw in NOT_A_BOUNDED_NUMBER:
        if name in endpoint.query:
            url = f"{path}?evaluation={KNOWN.evaluation}&{name}={raw}"
            response = client.request(endpoint.method, url, headers=ADMIN)  # the access is decided first
        else:
            body = _multipart([(name, raw.encode())], [])
            headers = {"content-type": f"multipart/form-data; boundary={BOUNDARY}", **ADMIN}
            response = client.request(endpoint.method, path, content=body, headers=headers)
        err = assert_error(response, 422)
        assert f"'{name}'" in err["message"], (raw, err["message"])
