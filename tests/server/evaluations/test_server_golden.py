"""The golden small case uploaded returns exactly what the CLI prints, for the pickle and the txt archives."""

from __future__ import annotations

import json
import tarfile
from pathlib import Path

import pytest
from cli_runs import cli_json
from server_helpers import GOLDEN, golden_bytes, golden_txt, register, tar_of, upload, zip_of

META = ("id", "evaluation")


@pytest.fixture(scope="module")
def txt_dirs(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("golden-txt")
    for name in ("label_2.tar.gz", "pred.tar.gz"):
        with tarfile.open(GOLDEN / name) as tf:
            tf.extractall(out, filter="data")
    return {"label_2": out / "label_2", "pred": out / "pred"}


@pytest.fixture(scope="module")
def client(service_client):
    with service_client() as c:
        assert register(c, "small-pkl", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        assert register(c, "small-txt", golden_bytes("label_2.tar.gz"), "label_2.tar.gz").status_code == 201
        yield c


def predictions(kind: str) -> tuple[str, bytes]:
    pred = golden_txt("pred.tar.gz")
    return {
        "pkl": ("result.pkl", golden_bytes("result.pkl")),
        "tar.gz": ("pred.tar.gz", golden_bytes("pred.tar.gz")),
        "tar": ("pred.tar", tar_of(pred, compression="")),
        "tar.xz": ("pred.tar.xz", tar_of(pred, compression="xz")),
        "zip": ("pred.zip", zip_of(pred)),
        "zip-flat": ("pred.zip", zip_of({Path(k).name: v for k, v in pred.items()})),
        "zip-final_result": (
            "final_result.zip",
            zip_of({f"final_result/data/{Path(k).name}": v for k, v in pred.items()}),
        ),
    }[kind]


@pytest.mark.parametrize("protocol", ["official", "openpcdet"])
@pytest.mark.parametrize("kind", ["pkl", "tar.gz", "tar", "tar.xz", "zip", "zip-flat", "zip-final_result"])
def test_upload_equals_the_cli(client, txt_dirs, tmp_path, kind, protocol) -> None:
    filename, data = predictions(kind)
    if kind == "pkl":  # the pickle route: infos against result.pkl
        gt_name, expected = (
            "small-pkl",
            cli_json(GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl", tmp_path, "--protocol", protocol),
        )
    else:  # the txt route: label_2 against the pred folder
        gt_name, expected = (
            "small-txt",
            cli_json(txt_dirs["label_2"], txt_dirs["pred"], tmp_path, "--protocol", protocol),
        )
    r = upload(client, data, filename, gt=gt_name, fields={"protocol": protocol})
    assert r.status_code == 201, r.text
    body = r.json()
    assert {k: v for k, v in body.items() if k not in META} == expected
    fmt = "pickle" if kind == "pkl" else kind.split(".")[0].split("-")[0]
    assert body["evaluation"]["predictions"]["format"] == fmt
    stored = client.get(f"/v1/evaluations/{body['id']}").json()
    assert stored == body


@pytest.mark.parametrize("route", ["pkl", "txt"])
def test_sizes_that_are_not_positive_get_the_devkits_numbers(client, route) -> None:
    """The golden case of boxes whose sizes are not positive, registered and uploaded: accepted, the devkit's
    numbers (1e-6 on txt, 1e-4 on float32 pickles), and the two size warnings in the stored result."""
    sizes = GOLDEN.parent / "sizes"
    gt_file, pred_file = ("kitti_infos_val.pkl", "result.pkl") if route == "pkl" else ("label_2.tar.gz", "pred.tar.gz")
    r = register(client, f"sizes-{route}", (sizes / gt_file).read_bytes(), gt_file)
    assert r.status_code == 201, r.text
    r = upload(client, (sizes / pred_file).read_bytes(), pred_file, gt=f"sizes-{route}")
    assert r.status_code == 201, r.text
    body = r.json()
    official = json.loads((sizes / "expected.json").read_text())["official_cpp"]
    tol = 1e-4 if route == "pkl" else 1e-6
    for cls, metrics in official["classes_evaluated"].items():
        for ref_metric in metrics:
            metric = "bbox" if ref_metric == "2d" else ref_metric
            for d in ("easy", "moderate", "hard"):
                got = body["ap"]["strict"]["R40"][cls][metric][d]
                assert got == pytest.approx(official["ap_r40"][cls][ref_metric][d], abs=tol), (cls, metric, d)
    sizes_said = [w for w in body["warnings"] if "not positive" in w]
    assert len(sizes_said) == 2
    assert "76 ground-truth boxes" in sizes_said[0] and "404 predicted boxes" in sizes_said[1]
