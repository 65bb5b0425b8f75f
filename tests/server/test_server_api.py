"""The service in-process (TestClient): endpoints, formats, history, comparison, admin, limits, readiness."""

from __future__ import annotations

import gzip
import hashlib
import json
import sys
import threading
import time
from pathlib import Path

import pytest
from server_helpers import (
    ADMIN,
    ADMIN_TOKEN,
    GOLDEN,
    app_client,
    assert_error,
    golden_bytes,
    golden_txt,
    register,
    upload,
    zip_of,
)

from kitti_eval.cli import main as cli_main
from kitti_eval.demo import demo_paths
from kitti_eval_server import Settings, create_app
from kitti_eval_server.evaluations.evaluations import Evaluations
from kitti_eval_server.ground_truths.cache import GroundTruthCache, annotations_nbytes
from kitti_eval_server.service import Service

DEMO_PRED = demo_paths()[1].read_bytes()
META = ("id", "evaluation")


def cli(tmp_path: Path, gt: Path, pred: Path, fmt: str = "json", *extra: str) -> str:
    out = tmp_path / f"cli.{fmt}"
    assert (
        cli_main(["--gt", str(gt), "--pred", str(pred), "--format", fmt, "--output", str(out), "--quiet", *extra]) == 0
    )
    return out.read_text()


def doc_of(body: dict) -> dict:
    return {k: v for k, v in body.items() if k not in META}


# --------------------------------------------------------------------------------------------- basics


def test_openapi_documents_the_versioned_endpoints(client) -> None:
    spec = client.get("/openapi.json").json()
    paths = spec["paths"]
    assert {"post", "get"} <= set(paths["/v1/evaluations"])
    assert "get" in paths["/v1/evaluations/{evaluation_id}"]
    assert "get" in paths["/v1/evaluations/{evaluation_id}/compare/{other_id}"]
    assert {"post", "get"} <= set(paths["/v1/ground-truths"])
    assert {"get", "delete"} <= set(paths["/v1/ground-truths/{name}"])
    assert "/healthz" in paths and "/readyz" in paths
    form = spec["components"]["schemas"]
    body = next(v for k, v in form.items() if k.startswith("Body_create_evaluation"))
    assert {
        "predictions",
        "gt",
        "gt_file",
        "protocol",
        "classes",
        "threshold_sets",
        "iou",
        "model",
        "commit",
        "epoch",
        "label",
    } <= set(body["properties"])
    assert "HTTPBearer" in spec["components"]["securitySchemes"]


def test_health_and_readiness(client) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready"}


def test_demo_ground_truth_is_registered_out_of_the_box(client) -> None:
    items = client.get("/v1/ground-truths").json()["items"]
    demo = next(i for i in items if i["name"] == "demo")
    assert demo["frames"] == 200 and demo["format"] == "pickle" and len(demo["sha256"]) == 64
    assert client.get("/v1/ground-truths/demo").json() == demo


def test_uploading_the_demo_gives_the_cli_json_with_an_id(client, tmp_path) -> None:
    r = upload(client, DEMO_PRED, "result.pkl.gz", fields={"model": "pp", "commit": "abc123", "epoch": "80"})
    assert r.status_code == 201, r.text
    body = r.json()
    assert r.headers["location"] == f"/v1/evaluations/{body['id']}"
    expected = json.loads(cli(tmp_path, *demo_paths()))
    assert doc_of(body) == expected
    meta = body["evaluation"]
    assert meta["labels"] == {"commit": "abc123", "epoch": "80", "model": "pp"}
    assert meta["predictions"]["filename"] == "result.pkl.gz" and meta["predictions"]["format"] == "pickle"
    assert meta["predictions"]["sha256"] == hashlib.sha256(DEMO_PRED).hexdigest()
    assert meta["ground_truth"]["name"] == "demo"
    assert meta["ground_truth"]["sha256"] == hashlib.sha256(demo_paths()[0].read_bytes()).hexdigest()
    got = client.get(f"/v1/evaluations/{body['id']}")
    assert got.status_code == 200 and got.json() == body


@pytest.mark.parametrize("how", ["query", "accept"])
@pytest.mark.parametrize("fmt,media", [("table", "text/plain"), ("markdown", "text/markdown")])
def test_table_and_markdown_when_asked(client, tmp_path, how, fmt, media) -> None:
    kw = {"params": {"format": fmt}} if how == "query" else {}
    if how == "accept":
        r = client.post(
            "/v1/evaluations",
            data={"gt": "demo"},
            files={"predictions": ("r.pkl.gz", DEMO_PRED)},
            headers={"Accept": f"{media}, application/json;q=0.5"},
        )
    else:
        r = upload(client, DEMO_PRED, "r.pkl.gz", **kw)
    assert r.status_code == 201, r.text
    assert r.headers["content-type"].startswith(media)
    assert r.text == cli(tmp_path, *demo_paths(), fmt)
    again = client.get(f"/v1/evaluations/{r.headers['x-evaluation-id']}", params={"format": fmt})
    assert again.text == r.text


def test_unknown_format_and_evaluation(client) -> None:
    assert_error(client.get("/v1/evaluations/nope"), 404, "nope")
    r = upload(client, DEMO_PRED, params={"format": "xml"})
    assert_error(r, 422, "format")
    assert_error(client.get("/v1/nothing-here"), 404)
    assert_error(client.delete("/v1/evaluations"), 405)


def test_options_protocol_classes_thresholds_iou_curves(client, tmp_path) -> None:
    fields = {
        "protocol": "openpcdet",
        "classes": "Car,Van",
        "threshold_sets": "strict",
        "iou": "Car=0.6,0.5,0.5",
        "curves": "true",
    }
    r = upload(client, DEMO_PRED, "r.pkl.gz", fields=fields)
    assert r.status_code == 201, r.text
    expected = json.loads(
        cli(
            tmp_path,
            *demo_paths(),
            "json",
            "--protocol",
            "openpcdet",
            "--classes",
            "Car,Van",
            "--iou",
            "Car=0.6,0.5,0.5",
            "--curves",
        )
    )
    body = doc_of(r.json())
    assert body["threshold_sets"] == ["strict"] and body["classes"] == ["Car", "Van"]
    assert body["overlaps"]["Car"]["strict"] == {"bbox": 0.6, "bev": 0.5, "3d": 0.5}
    assert body["ap"]["strict"] == expected["ap"]["strict"]
    assert body["curves"]["strict"] == expected["curves"]["strict"]


@pytest.mark.parametrize(
    "fields,needle",
    [
        ({"protocol": "devkit"}, "protocol"),
        ({"classes": "Bus"}, "bus"),
        ({"classes": " , "}, "no classes"),
        ({"threshold_sets": "medium"}, "threshold set"),
        ({"iou": "Car=0.7,0.7"}, "iou"),
        ({"iou": "Car=1.5,0.7,0.7"}, "[0, 1)"),
        ({"label": "no-equals-sign"}, "key=value"),
        ({"label": "bad key!=1"}, "label key"),
    ],
)
def test_bad_options_are_422_before_anything_is_loaded(client, fields, needle) -> None:
    assert_error(upload(client, DEMO_PRED, fields=fields), 422, needle)


def test_ground_truth_by_name_or_file_not_both_nor_neither(client) -> None:
    assert_error(upload(client, DEMO_PRED, gt=None), 422, "gt")
    both = upload(client, DEMO_PRED, gt="demo", gt_file=("gt.pkl.gz", demo_paths()[0].read_bytes()))
    assert_error(both, 422, "not both")
    assert_error(upload(client, DEMO_PRED, gt="missing-set"), 404, "missing-set")


def test_ground_truth_uploaded_with_the_request(client, tmp_path) -> None:
    r = upload(client, golden_bytes("result.pkl"), gt=None, gt_file=("infos.pkl", golden_bytes("kitti_infos_val.pkl")))
    assert r.status_code == 201, r.text
    assert doc_of(r.json()) == json.loads(cli(tmp_path, GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl"))
    assert r.json()["evaluation"]["ground_truth"]["name"] is None
    labels = ("label_2.tar.gz", golden_bytes("label_2.tar.gz"))
    txt = upload(client, golden_bytes("result.pkl"), gt=None, gt_file=labels)
    assert txt.status_code == 201, txt.text


# ------------------------------------------------------------------------------------- history, compare


def test_history_filters_by_ground_truth_and_labels_newest_first(tmp_path) -> None:
    with app_client(tmp_path / "data") as c:
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        ids = []
        for epoch in range(3):
            r = upload(c, golden_bytes("result.pkl"), gt="small", fields={"model": "a", "epoch": str(epoch)})
            ids.append(r.json()["id"])
        other = upload(c, DEMO_PRED, gt="demo", fields={"model": "b", "label": ["team=x", "run=7"]}).json()["id"]
        everything = c.get("/v1/evaluations").json()
        assert [i["id"] for i in everything["items"]] == [other, *reversed(ids)]
        assert everything["next_offset"] is None
        assert [i["id"] for i in c.get("/v1/evaluations", params={"gt": "small"}).json()["items"]] == ids[::-1]
        assert [i["id"] for i in c.get("/v1/evaluations", params={"model": "a", "epoch": "1"}).json()["items"]] == [
            ids[1]
        ]
        assert [i["id"] for i in c.get("/v1/evaluations", params={"label": ["team=x", "run=7"]}).json()["items"]] == [
            other
        ]
        assert c.get("/v1/evaluations", params={"label": "team=y"}).json()["items"] == []
        page = c.get("/v1/evaluations", params={"limit": 2, "offset": 1}).json()
        assert [i["id"] for i in page["items"]] == [ids[2], ids[1]] and page["next_offset"] == 3
        item = page["items"][0]
        assert item["evaluation"]["labels"] == {"epoch": "2", "model": "a"}
        full = c.get(f"/v1/evaluations/{ids[2]}").json()
        assert item["summary"]["Car"]["3d"] == full["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
        assert_error(c.get("/v1/evaluations", params={"limit": 0}), 422, "limit")
        for offset in (2**63, 2**64, -1, 10**9 + 1):  # 2**63 overflowed the database's integer: a 500
            assert_error(c.get("/v1/evaluations", params={"offset": offset}), 422, "offset")
        assert c.get("/v1/evaluations", params={"offset": 10**9}).json()["items"] == []


def test_comparison_gives_per_value_deltas(client) -> None:
    a = upload(client, DEMO_PRED, "a.pkl.gz", fields={"model": "a"}).json()
    b = upload(client, golden_bytes("result.pkl"), "b.pkl", fields={"model": "b", "epoch": "2"}).json()
    r = client.get(f"/v1/evaluations/{a['id']}/compare/{b['id']}")
    assert r.status_code == 200, r.text
    cmp = r.json()
    assert cmp["base"]["id"] == a["id"] and cmp["other"]["id"] == b["id"]
    values = {v["key"]: v for v in cmp["values"]}
    assert len(values) == 2 * 2 * 3 * 4 * 3  # sets x recalls x classes x metrics x difficulties
    for oset in ("strict", "loose"):
        for recall in ("R11", "R40"):
            for cls in ("Car", "Pedestrian", "Cyclist"):
                for metric in ("bbox", "bev", "3d", "aos"):
                    for d in ("easy", "moderate", "hard"):
                        va, vb = a["ap"][oset][recall][cls][metric][d], b["ap"][oset][recall][cls][metric][d]
                        got = values[f"{cls}/{metric}/{d}/{recall}/{oset}"]
                        assert (got["a"], got["b"]) == (va, vb)
                        assert got["delta"] == (None if va is None or vb is None else vb - va)
    assert cmp["num_det"]["Car"] == b["num_det"]["Car"] - a["num_det"]["Car"]
    assert cmp["notes"] == []  # same ground truth, protocol and thresholds
    md = client.get(f"/v1/evaluations/{a['id']}/compare/{b['id']}", params={"format": "markdown"})
    assert md.headers["content-type"].startswith("text/markdown")
    assert "a → b (epoch 2)" in md.text and "| `Car/3d/moderate/R40/strict` |" in md.text
    assert_error(client.get(f"/v1/evaluations/{a['id']}/compare/nope"), 404)


# --------------------------------------------------------------------------------------------- admin


def test_admin_actions_need_the_token(client) -> None:
    data = golden_bytes("kitti_infos_val.pkl")
    assert_error(register(client, "gt-a", data, "i.pkl", headers={}), 401, "token")
    assert_error(register(client, "gt-a", data, "i.pkl", headers={"Authorization": "Bearer wrong"}), 403)
    assert_error(register(client, "gt-a", data, "i.pkl", headers={"Authorization": f"Basic {ADMIN_TOKEN}"}), (401, 403))
    assert client.get("/v1/ground-truths/gt-a").status_code == 404
    r = register(client, "gt-a", data, "i.pkl")
    assert r.status_code == 201, r.text
    assert r.json()["frames"] == 50 and r.headers["location"] == "/v1/ground-truths/gt-a"
    assert_error(register(client, "gt-a", data, "i.pkl"), 409, "gt-a")
    assert_error(register(client, "../etc", data, "i.pkl"), 422, "name")
    assert upload(client, golden_bytes("result.pkl"), gt="gt-a").status_code == 201
    assert_error(client.delete("/v1/ground-truths/gt-a"), 401)
    assert_error(client.delete("/v1/ground-truths/gt-a", headers={"Authorization": "Bearer nope"}), 403)
    assert client.get("/v1/ground-truths/gt-a").status_code == 200
    assert client.delete("/v1/ground-truths/gt-a", headers=ADMIN).status_code == 204
    assert_error(client.delete("/v1/ground-truths/gt-a", headers=ADMIN), 404)
    assert_error(upload(client, golden_bytes("result.pkl"), gt="gt-a"), 404)
    assert register(client, "gt-a", data, "i.pkl").status_code == 201  # the name is free again


def test_ground_truth_from_a_label_2_archive_and_shared_storage(client, tmp_path) -> None:
    labels = golden_txt("label_2.tar.gz")
    for name, blob, fname in (
        ("txt-tar", golden_bytes("label_2.tar.gz"), "label_2.tar.gz"),
        ("txt-zip", zip_of(labels), "label_2.zip"),
    ):
        r = register(client, name, blob, fname)
        assert r.status_code == 201, r.text
        assert r.json()["frames"] == 50
    twin = register(client, "txt-tar-2", golden_bytes("label_2.tar.gz"), "copy.tar.gz").json()
    assert twin["sha256"] == client.get("/v1/ground-truths/txt-tar").json()["sha256"]
    assert client.delete("/v1/ground-truths/txt-tar", headers=ADMIN).status_code == 204
    r = upload(client, golden_bytes("result.pkl"), gt="txt-tar-2")  # its files are still there
    assert r.status_code == 201, r.text


def test_generated_admin_token_is_kept_in_the_data_dir(tmp_path) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir, admin_token=None) as c:
        token_file = data_dir / "admin-token"
        token = token_file.read_text().strip()
        assert len(token) >= 32 and (token_file.stat().st_mode & 0o777) == 0o600
        bearer = {"Authorization": f"Bearer {token}"}
        ok = register(c, "x", golden_bytes("kitti_infos_val.pkl"), "i.pkl", headers=bearer)
        assert ok.status_code == 201
        assert_error(register(c, "y", golden_bytes("kitti_infos_val.pkl"), "i.pkl"), 403)
    with app_client(data_dir, admin_token=None) as c:  # the same token after a restart
        assert c.delete("/v1/ground-truths/x", headers={"Authorization": f"Bearer {token}"}).status_code == 204


# ---------------------------------------------------------------------------------------------- limits


def _multipart(fields: dict[str, str], name: str, filename: str, payload: bytes) -> tuple[bytes, str]:
    boundary = "testboundary0123456789"
    parts = [
        f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode() for k, v in fields.items()
    ]
    parts.append(
        f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{filename}"\r\n'
        f"Content-Type: application/octet-stream\r\n\r\n".encode()
        + payload
        + b"\r\n"
    )
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def test_oversized_upload_is_413_declared_or_streamed(tmp_path) -> None:
    with app_client(tmp_path / "data", max_upload_mb=1) as c:
        big = b"\x80\x04" + b"\0" * (1 << 20)
        assert_error(upload(c, big), 413, "upload limit")
        body, ctype = _multipart({"gt": "demo"}, "predictions", "r.pkl", big)

        def chunks():  # no Content-Length: the cap must hold while the body streams
            for i in range(0, len(body), 64 * 1024):
                yield body[i : i + 64 * 1024]

        r = c.post("/v1/evaluations", content=chunks(), headers={"content-type": ctype})
        assert_error(r, 413, "upload limit")
        assert list((tmp_path / "data" / "tmp").iterdir()) == []
        assert upload(c, golden_bytes("result.pkl")).status_code == 201  # and it goes on serving


def test_a_full_job_queue_answers_503_with_retry_after(tmp_path, monkeypatch) -> None:
    started, release = threading.Event(), threading.Event()
    original = Evaluations.execute  # what a worker runs of an accepted evaluation

    def slow_evaluate(self, *args, **kwargs):
        started.set()
        assert release.wait(30)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Evaluations, "execute", slow_evaluate)
    with app_client(tmp_path / "data", max_queued_jobs=1, retry_after_s=7) as c:
        results = {}
        t = threading.Thread(target=lambda: results.setdefault("first", upload(c, golden_bytes("result.pkl"))))
        t.start()
        try:
            assert started.wait(30)
            busy = upload(c, golden_bytes("result.pkl"))
            assert_error(busy, 503, "KITTI_EVAL_MAX_QUEUED_JOBS")
            assert busy.json()["error"]["code"] == "queue_full" and busy.headers["retry-after"] == "7"
            assert c.get("/v1/evaluations").status_code == 200  # reads are not queued behind evaluations
        finally:
            release.set()
            t.join(30)
        assert results["first"].status_code == 201
        assert upload(c, golden_bytes("result.pkl")).status_code == 201


def test_queued_requests_wait_for_a_slot(tmp_path) -> None:
    with app_client(tmp_path / "data", max_concurrent_evals=1, max_queued_evals=6) as c:
        out: list[int] = []
        threads = [
            threading.Thread(target=lambda: out.append(upload(c, golden_bytes("result.pkl")).status_code))
            for _ in range(6)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert out == [201] * 6


def test_readyz_is_503_until_the_kernels_are_warm(tmp_path, monkeypatch) -> None:
    gate = threading.Event()
    original = Service._warm_up

    def gated(self):
        gate.wait(30)
        original(self)

    monkeypatch.setattr(Service, "_warm_up", gated)
    app = create_app(Settings(data_dir=tmp_path / "data", admin_token=ADMIN_TOKEN))
    from server_helpers import TestClient

    with TestClient(app) as c:
        assert c.get("/healthz").status_code == 200
        err = assert_error(c.get("/readyz"), 503, "warming up")
        assert err["code"] == "not_ready"
        gate.set()
        deadline = time.monotonic() + 60
        while c.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.05)


def test_an_unexpected_failure_is_a_500_without_details(tmp_path, monkeypatch) -> None:
    def boom(self, *args, **kwargs):
        raise RuntimeError("secret detail /srv/internal/path")

    monkeypatch.setattr(Evaluations, "execute", boom)
    with app_client(tmp_path / "data") as c:
        r = upload(c, DEMO_PRED)
        err = assert_error(r, 500)
        assert err["code"] == "internal_error" and "secret" not in r.text and "/srv" not in r.text


# ------------------------------------------------------------------------------------------ durability


def test_evaluations_survive_a_restart_and_scratch_is_cleaned(tmp_path) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir) as c:
        first = upload(c, DEMO_PRED, fields={"model": "m"}).json()
        assert list((data_dir / "tmp").iterdir()) == []
    with app_client(data_dir) as c:
        assert c.get(f"/v1/evaluations/{first['id']}").json() == first
        assert [g["name"] for g in c.get("/v1/ground-truths").json()["items"]] == ["demo"]
    import sqlite3

    con = sqlite3.connect(data_dir / "kitti-eval.db")
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    # 64 KB pages: an uploaded file kept in the database is written with half the CPU of the 4 KB default
    assert con.execute("PRAGMA page_size").fetchone()[0] == 65536
    con.close()


def test_settings_come_from_the_environment(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "env-data"))
    monkeypatch.setenv("KITTI_EVAL_MAX_UPLOAD_MB", "3.5")
    monkeypatch.setenv("KITTI_EVAL_DATABASE_URL", "postgresql://u:p@db:5432/kitti")
    monkeypatch.setenv("KITTI_EVAL_ADMIN_TOKEN", "tok")
    s = Settings()
    assert s.data_dir == tmp_path / "env-data" and s.max_upload_bytes == int(3.5 * (1 << 20))
    assert s.resolved_database_url == "postgresql+psycopg://u:p@db:5432/kitti"
    assert s.admin_token is not None and s.admin_token.get_secret_value() == "tok"
    monkeypatch.delenv("KITTI_EVAL_DATABASE_URL")
    assert Settings().resolved_database_url.startswith("sqlite:///") and "env-data" in Settings().resolved_database_url


@pytest.fixture
def no_settings(monkeypatch) -> None:
    """No KITTI_EVAL_* variable from the environment the tests run in."""
    import os

    for name in [n for n in os.environ if n.startswith("KITTI_EVAL_")]:
        monkeypatch.delenv(name)


def test_the_data_dir_defaults_to_the_users_data_folder(tmp_path, monkeypatch, no_settings) -> None:
    import platformdirs

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))  # where Linux keeps per-user data
    expected = Path(platformdirs.user_data_dir("kitti-eval", appauthor=False))
    assert Settings().data_dir == expected and expected.is_absolute()
    if sys.platform.startswith("linux"):
        assert expected == tmp_path / "xdg" / "kitti-eval"
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "chosen"))
    assert Settings().data_dir == tmp_path / "chosen"


def test_serve_from_a_repository_leaves_nothing_in_it(tmp_path, monkeypatch, no_settings) -> None:
    """``kitti-eval serve`` in a checkout: the database and the generated admin token go to the user's data
    folder, where a ``git add .`` cannot pick them up."""
    import platformdirs
    import uvicorn
    from fastapi.testclient import TestClient

    from kitti_eval_server.main import serve

    served = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: served.append(app))
    repo = tmp_path / "repo"
    repo.mkdir()
    monkeypatch.chdir(repo)
    monkeypatch.setattr(platformdirs, "user_data_dir", lambda name, **kw: str(tmp_path / "user" / name))
    monkeypatch.setenv("KITTI_EVAL_WARMUP", "false")
    monkeypatch.setenv("KITTI_EVAL_REGISTER_DEMO", "false")
    # jobs on a thread of this process: where the files go does not depend on worker processes, and the service is
    # ready at once (with worker processes it is ready once one of them takes jobs)
    monkeypatch.setenv("KITTI_EVAL_WORKER_PROCESSES", "0")
    assert serve([]) == 0
    with TestClient(served[-1]) as c:
        assert c.get("/readyz").status_code == 200
    assert list(repo.iterdir()) == []
    data = tmp_path / "user" / "kitti-eval"
    assert {"admin-token", "kitti-eval.db"} <= {p.name for p in data.iterdir()}
    assert serve(["--data-dir", str(tmp_path / "flag")]) == 0  # the flag and the variable still choose
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "env"))
    assert serve([]) == 0
    assert [app.state.service.data_dir for app in served[1:]] == [tmp_path / "flag", tmp_path / "env"]


def test_serve_auth_chooses_the_mode_and_the_start_names_it(tmp_path, monkeypatch, no_settings, caplog) -> None:
    """``kitti-eval serve --auth accounts`` (the mode was only a variable, named in prose): the option sets it,
    and the log of the start says the mode, the database and the workers."""
    import logging

    import uvicorn
    from fastapi.testclient import TestClient

    from kitti_eval_server.main import serve

    served = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: served.append(app))
    monkeypatch.setenv("KITTI_EVAL_WARMUP", "false")
    monkeypatch.setenv("KITTI_EVAL_REGISTER_DEMO", "false")
    monkeypatch.setenv("KITTI_EVAL_JOB_THREADS", "1")  # no worker processes in a test
    assert serve(["--auth", "accounts", "--data-dir", str(tmp_path / "data")]) == 0
    with caplog.at_level(logging.INFO, logger="kitti_eval.server"), TestClient(served[-1]) as c:
        assert c.get("/v1/evaluations").status_code == 401  # accounts: a token is needed
    db = (tmp_path / "data" / "kitti-eval.db").resolve()
    started = [r.getMessage() for r in caplog.records if r.getMessage().startswith("auth ")]
    assert started == [f"auth accounts, database {db}, 0 worker processes, 1 job thread"]
    assert serve(["--auth", "open", "--data-dir", str(tmp_path / "open")]) == 0
    with TestClient(served[-1]) as c:
        assert c.get("/v1/evaluations").status_code == 200
    assert serve(["--auth", "everyone"]) == 2  # a usage error


def test_serve_help_names_the_auth_modes(capsys) -> None:
    from kitti_eval_server.main import serve

    assert serve(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--auth {open,accounts} KITTI_EVAL_AUTH: open (default" in text


def test_module_app_is_built_lazily_from_the_environment(tmp_path, monkeypatch) -> None:
    import kitti_eval_server.main as main

    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "lazy"))
    monkeypatch.setattr(main, "_app", None)
    app = main.app
    assert app is main.app and app.state.service.data_dir == (tmp_path / "lazy").resolve()
    assert not (tmp_path / "lazy").exists()  # nothing is created before the lifespan starts


def test_serve_reports_usage_errors(capsys) -> None:
    from kitti_eval_server.main import serve

    assert serve(["--help"]) == 0
    assert serve(["--port", "not-a-number"]) == 2


# ------------------------------------------------------------------------------------------- the cache


def test_ground_truth_cache_is_bounded_and_loads_each_set_once() -> None:
    from kitti_eval.io.loaders import load_ground_truth

    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    size = annotations_nbytes(gt)
    cache = GroundTruthCache(max_entries=2, max_bytes=10 * size)
    calls = []

    def load():
        calls.append(1)
        time.sleep(0.05)
        return gt

    threads = [threading.Thread(target=cache.get_or_load, args=("a", load)) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and cache.get("a") is gt
    cache.put("b", gt)
    cache.put("c", gt)
    assert len(cache) == 2 and cache.get("a") is None  # least recently used went first
    small = GroundTruthCache(max_entries=10, max_bytes=int(2.5 * size))
    for key in "abcd":
        small.put(key, gt)
    assert len(small) == 2 and small.nbytes <= 2.5 * size
    tiny = GroundTruthCache(max_entries=10, max_bytes=size - 1)
    tiny.put("x", gt)
    assert len(tiny) == 0


def test_upload_filenames_are_never_paths(client) -> None:
    for name in ("../../etc/passwd.pkl", "..\\..\\windows\\passwd.pkl", "/abs/passwd.pkl"):
        r = upload(client, DEMO_PRED, name)
        assert r.status_code == 201, r.text
        assert r.json()["evaluation"]["predictions"]["filename"] == "passwd.pkl"


def test_gzip_of_a_pickle_is_read_whatever_its_name(client) -> None:
    data = gzip.compress(golden_bytes("result.pkl"))
    r = upload(client, data, "predictions.bin")
    assert r.status_code == 201, r.text
    assert r.json()["evaluation"]["predictions"]["format"] == "pickle"


def test_registered_files_come_back_from_the_database(tmp_path) -> None:
    """A server whose data folder lost its copies (or a second server on the same database) rebuilds them."""
    data_dir = tmp_path / "data"
    with app_client(data_dir) as c:
        assert register(c, "pkl", golden_bytes("kitti_infos_val.pkl"), "i.pkl").status_code == 201
        assert register(c, "txt", golden_bytes("label_2.tar.gz"), "label_2.tar.gz").status_code == 201
        before = {name: upload(c, golden_bytes("result.pkl"), gt=name).json() for name in ("pkl", "txt", "demo")}
    import shutil

    shutil.rmtree(data_dir / "ground-truths")
    with app_client(data_dir) as c:
        for name, body in before.items():
            again = upload(c, golden_bytes("result.pkl"), gt=name).json()
            assert doc_of(again) == doc_of(body)
    assert sorted(p.name for p in (data_dir / "ground-truths").iterdir()) == sorted(
        [
            f"{before['pkl']['evaluation']['ground_truth']['sha256']}.pkl",
            before["txt"]["evaluation"]["ground_truth"]["sha256"],
            f"{before['demo']['evaluation']['ground_truth']['sha256']}.pkl",
        ]
    )
