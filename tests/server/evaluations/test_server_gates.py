"""POST /v1/gates: the CLI's rules against stored evaluations, 200 on pass and 412 on failure."""

from __future__ import annotations

import pickle
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from server_helpers import assert_error, upload

from kitti_eval.demo import demo_paths


@pytest.fixture(scope="module")
def stored(client):
    """The demo result labelled main, then a worse one (every second Car detection dropped) on a branch."""
    good = demo_paths()[1].read_bytes()
    import gzip

    results = pickle.loads(gzip.decompress(good))  # the project's own bundled demo file
    worse = []
    for r in results:
        n = len(r["score"])
        drop = (np.asarray(r["name"]) == "Car") & (np.arange(n) % 2 == 0) if n else np.zeros(0, bool)
        worse.append({k: (v[~drop] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v) for k, v in r.items()})
    main_id = upload(client, good, "result.pkl.gz", fields={"label": ["branch=main"]}).json()["id"]
    branch = upload(client, pickle.dumps(worse), fields={"label": ["branch=feature"]}).json()
    return main_id, branch["id"], branch


def test_floor_passes_and_fails(client, stored):
    main_id, branch_id, branch = stored
    value = branch["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
    ok = client.post("/v1/gates", json={"evaluation": branch_id, "min": [f"Car/3d/moderate >= {value - 0.01}"]})
    assert ok.status_code == 200 and ok.json()["passed"] is True
    bad = client.post("/v1/gates", json={"evaluation": branch_id, "min": [f"Car/3d/moderate >= {value + 0.01}"]})
    assert bad.status_code == 412 and bad.json()["passed"] is False
    assert bad.json()["checks"][0]["current"] == pytest.approx(value)


def test_max_drop_against_the_latest_evaluation_labelled_main(client, stored):
    main_id, branch_id, _ = stored
    r = client.post(
        "/v1/gates",
        json={"evaluation": branch_id, "baseline_label": "branch=main", "max_drop": ["Car/3d/moderate=0.5"]},
    )
    body = r.json()
    assert r.status_code == 412 and body["baseline"] == main_id
    (check,) = body["checks"]
    assert check["delta"] < -0.5 and "dropped" in check["message"]
    # against itself nothing drops
    r = client.post("/v1/gates", json={"evaluation": main_id, "baseline": main_id, "max_drop": ["0"]})
    assert r.status_code == 200 and r.json()["passed"]


def test_reports_as_junit_and_markdown(client, stored):
    _, branch_id, _ = stored
    r = client.post(
        "/v1/gates",
        params={"format": "junit"},
        json={"evaluation": branch_id, "min": ["Car/3d/moderate >= 100"], "require_classes": ["Car"]},
    )
    assert r.status_code == 412 and r.headers["content-type"].startswith("application/xml")
    root = ET.fromstring(r.text)
    assert root.get("tests") == "2" and root.get("failures") == "1"
    r = client.post(
        "/v1/gates", params={"format": "markdown"}, json={"evaluation": branch_id, "require_classes": ["Car"]}
    )
    assert r.status_code == 200 and "✅ passed" in r.text


@pytest.mark.parametrize(
    "body, status, needle",
    [
        ({"evaluation": "nope", "min": ["Car/3d/easy >= 1"]}, 404, "nope"),
        ({"evaluation": "X"}, 422, "no rules"),
        ({"evaluation": "X", "max_drop": ["0.5"]}, 422, "baseline"),
        ({"evaluation": "X", "min": ["Car/4d/easy >= 1"]}, 422, "unknown metric"),
    ],
)
def test_bad_gate_requests(client, stored, body, status, needle):
    body = {**body, "evaluation": stored[1] if body["evaluation"] == "X" else body["evaluation"]}
    assert_error(client.post("/v1/gates", json=body), status, needle)


def test_no_baseline_with_that_label(client, stored):
    assert_error(
        client.post("/v1/gates", json={"evaluation": stored[1], "baseline_label": "branch=nowhere", "max_drop": ["1"]}),
        404,
        "branch=nowhere",
    )


def test_variants_through_the_service(client):
    r = upload(
        client,
        demo_paths()[1].read_bytes(),
        "result.pkl.gz",
        fields={"ranges": "0,30,inf", "coco": "true", "classes": "Car"},
    )
    body = r.json()
    assert r.status_code == 201 and [x["label"] for x in body["ranges"]] == ["0-30m", "30m+"]
    assert body["coco"]["R40"]["Car"]["3d"]["moderate"] is not None
    r = upload(client, demo_paths()[1].read_bytes(), "result.pkl.gz", fields={"lidar_only": "true"})
    assert r.status_code == 201 and r.json()["ap"]["strict"]["R40"]["Car"]["bbox"]["easy"] is None
    assert_error(
        upload(client, demo_paths()[1].read_bytes(), "result.pkl.gz", fields={"ranges": "5,1"}), 422, "increasing"
    )
