"""The error decomposition through the service: ``errors=true`` adds what ``kitti-eval --errors`` adds."""

from __future__ import annotations

from pathlib import Path

from cli_runs import cli_json
from server_helpers import assert_error, upload

from kitti_eval.demo import demo_paths

DEMO_PRED = demo_paths()[1].read_bytes()
ERROR_KEYS = ("errors", "errors_r11", "tp_errors")
META = ("id", "evaluation")


def doc_of(body: dict) -> dict:
    return {k: v for k, v in body.items() if k not in META}


def test_errors_equal_the_clis_and_are_kept(client, tmp_path) -> None:
    r = upload(client, DEMO_PRED, "result.pkl.gz", fields={"errors": "true"})
    assert r.status_code == 201, r.text
    expected = cli_json(*demo_paths(), tmp_path, "--errors")
    body = r.json()
    for key in ERROR_KEYS:
        assert body[key] == expected[key], key  # the nested dicts, number for number
    assert doc_of(body) == expected  # and nothing else changes
    assert client.get(f"/v1/evaluations/{body['id']}").json() == body  # the stored record keeps them


def test_errors_follow_the_options_as_the_cli_does(client, tmp_path) -> None:
    fields = {"errors": "true", "classes": "Car,Van", "protocol": "openpcdet", "iou": "Car=0.6,0.5,0.5"}
    r = upload(client, DEMO_PRED, "result.pkl.gz", fields=fields)
    assert r.status_code == 201, r.text
    flags = ("--errors", "--classes", "Car,Van", "--protocol", "openpcdet", "--iou", "Car=0.6,0.5,0.5")
    expected = cli_json(*demo_paths(), tmp_path, *flags)
    assert set(r.json()["errors"]) == {"Car", "Van"}
    assert doc_of(r.json()) == expected


def test_without_errors_the_keys_are_absent(client) -> None:
    for fields in ({}, {"errors": "false"}):
        body = upload(client, DEMO_PRED, "result.pkl.gz", fields=fields).json()
        assert not set(ERROR_KEYS) & set(body)
        assert not set(ERROR_KEYS) & set(client.get(f"/v1/evaluations/{body['id']}").json())


def test_errors_need_the_strict_set(client) -> None:
    """The decomposition is of the strict IoU thresholds: without them the request is refused up front."""
    r = upload(client, DEMO_PRED, "result.pkl.gz", fields={"errors": "true", "threshold_sets": "loose"})
    assert_error(r, 422, "errors=true", "strict")


def test_openapi_documents_the_field_and_the_keys(client) -> None:
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    body = next(v for k, v in schemas.items() if k.startswith("Body_create_evaluation"))
    field = body["properties"]["errors"]
    assert field["type"] == "boolean" and field["default"] is False
    assert "--errors" in field["description"]
    response = schemas["EvaluationResponse"]["properties"]
    for key in ERROR_KEYS:
        assert key in response and response[key]["description"], key
        assert key not in schemas["EvaluationResponse"].get("required", [])


def test_two_evaluations_with_errors_compare_through_the_api_and_the_page(client) -> None:
    data = Path(demo_paths()[1]).read_bytes()
    a = upload(client, data, "result.pkl.gz", fields={"errors": "true"}).json()["id"]
    b = upload(client, data, "result.pkl.gz", fields={"errors": "true", "protocol": "openpcdet"}).json()["id"]
    values = {v["key"]: v for v in client.get(f"/v1/evaluations/{a}/compare/{b}").json()["values"]}
    loc = values["Car/3d/moderate/localization/R40"]
    assert loc["delta"] == loc["b"] - loc["a"] and "Car/3d/moderate/R40/strict" in values
    page = client.get(f"/compare?a={a}&b={b}")
    assert page.status_code == 200 and "Car" in page.text
