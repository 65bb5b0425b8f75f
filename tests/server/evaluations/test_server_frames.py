"""Frames of stored evaluations over HTTP: the same per-frame counts and labels as the library, kept across
restarts, and clear refusals where the inputs were not kept."""

from __future__ import annotations

import gzip
import pickle
import sqlite3

import numpy as np
import pytest
from server_helpers import app_client, assert_error, golden_bytes, register, upload
from unversioned import as_unversioned

from kitti_eval.analysis.diagnostics import FrameQuestion, frame_stats, frames_document
from kitti_eval.analysis.inspection import inspect_frame
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.demo import demo_paths
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.io.safe_pickle import load_pickle

GT_PATH, PRED_PATH = demo_paths()
DEMO_PRED = PRED_PATH.read_bytes()


def worse_predictions() -> bytes:
    """The demo predictions with every other Car dropped and the scores of the rest halved."""
    frames = load_pickle(PRED_PATH, source="demo")
    out = []
    for anno in frames:
        keep = np.ones(len(anno["name"]), dtype=bool)
        cars = np.flatnonzero(anno["name"] == "Car")
        keep[cars[::2]] = False
        anno = {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == keep.shape else v) for k, v in anno.items()}
        anno["score"] = anno["score"] * 0.5
        out.append(anno)
    return gzip.compress(pickle.dumps(out))


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    data = tmp_path_factory.mktemp("frames") / "data"
    with app_client(data) as c:
        a = upload(
            c, DEMO_PRED, "output/kitti_models/pointpillar/default/result.pkl.gz", fields={"model": "pointpillar"}
        )
        b = upload(c, worse_predictions(), "result.pkl.gz")
        assert a.status_code == b.status_code == 201, (a.text, b.text)
        yield c, data, a.json()["id"], b.json()["id"]


@pytest.fixture(scope="module")
def demo():
    return load_ground_truth(GT_PATH), load_detections(PRED_PATH, keep_lidar=True)


def test_worst_frames_equal_the_library(service, demo) -> None:
    c, _, a, _ = service
    gt, dt = demo
    r = c.get(
        f"/v1/evaluations/{a}/frames", params={"class": "Pedestrian", "metric": "bev", "difficulty": "hard", "worst": 5}
    )
    assert r.status_code == 200, r.text
    want = frames_document(frame_stats(gt, dt, EvalConfig(), FrameQuestion("Pedestrian", "bev", "hard")), worst=5)
    assert r.json() == {**want, "evaluation": a}
    assert len(r.json()["frames"]) == 5 and r.json()["frames"][0]["fp"] + r.json()["frames"][0]["fn"] > 0
    every = c.get(f"/v1/evaluations/{a}/frames", params={"worst": 10_000}).json()["frames"]
    stats = frame_stats(gt, dt, EvalConfig())
    assert sum(f["tp"] for f in every) == stats.tp.sum() and sum(f["fn"] for f in every) == stats.fn.sum()


def test_one_frame_for_two_evaluations_equals_the_library(service, demo) -> None:
    c, _, a, b = service
    gt, dt = demo
    fid = gt.frame_ids[3]
    r = c.get(f"/v1/frames/{int(fid)}", params={"evaluation": [a, b], "metric": "bbox", "score_threshold": 0.2})
    assert r.status_code == 200, r.text
    body = r.json()
    assert list(body["models"]) == ["pointpillar", "result"]
    want = inspect_frame(gt, [("pointpillar", dt)], fid, EvalConfig(), metric="bbox", score_threshold=0.2)
    got_a = body["models"]["pointpillar"]
    assert got_a["evaluation"] == a and got_a["source"] == "result.pkl.gz"
    assert {k: v for k, v in got_a.items() if k not in ("evaluation", "source")} == {
        k: v for k, v in want["models"]["pointpillar"].items() if k != "source"
    }
    assert body["ground_truth"] == want["ground_truth"]
    got_b = body["models"]["result"]
    assert len(got_b["detections"]) < len(got_a["detections"])
    assert all(d["score"] <= 0.5 for d in got_b["detections"])


def test_frames_survive_a_restart(service, demo) -> None:
    _, data, a, _ = service
    gt, dt = demo
    with app_client(data) as c:  # a new process's view: nothing cached, the kept file comes from the database
        r = c.get(f"/v1/frames/{gt.frame_ids[0]}", params={"evaluation": a})
        assert r.status_code == 200, r.text
        assert r.json()["frame"] == gt.frame_ids[0] and list(r.json()["models"]) == ["pointpillar"]
        want = inspect_frame(gt, [("pointpillar", dt)], gt.frame_ids[0], EvalConfig())
        assert r.json()["models"]["pointpillar"]["detections"] == want["models"]["pointpillar"]["detections"]


def test_refusals(service, tmp_path) -> None:
    c, _, a, _ = service
    assert_error(c.get("/v1/evaluations/nope/frames"), 404, "no evaluation")
    assert_error(c.get("/v1/frames/000001", params={"evaluation": "nope"}), 404, "no evaluation")
    assert_error(c.get("/v1/frames/999999", params={"evaluation": a}), 404, "no frame 999999")
    assert_error(c.get(f"/v1/evaluations/{a}/frames", params={"metric": "2d"}), 422)
    assert_error(c.get(f"/v1/evaluations/{a}/frames", params={"worst": 0}), 422)
    assert_error(c.get("/v1/frames/000001"), 422)
    inline = upload(c, golden_bytes("result.pkl"), gt=None, gt_file=("infos.pkl", golden_bytes("kitti_infos_val.pkl")))
    assert inline.status_code == 201
    assert_error(c.get(f"/v1/evaluations/{inline.json()['id']}/frames"), 409, "uploaded with the request")
    register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl")
    small = upload(c, golden_bytes("result.pkl"), gt="small").json()["id"]
    assert c.get(f"/v1/evaluations/{small}/frames").status_code == 200
    assert_error(c.get("/v1/frames/000001", params={"evaluation": [a, small]}), 409, "different ground truths")


def test_predictions_not_kept_when_switched_off(tmp_path) -> None:
    with app_client(tmp_path / "data", keep_predictions=False) as c:
        r = upload(c, DEMO_PRED)
        assert r.status_code == 201
        assert_error(c.get(f"/v1/evaluations/{r.json()['id']}/frames"), 409, "not kept")
        db = sqlite3.connect(tmp_path / "data" / "kitti-eval.db")
        assert db.execute("SELECT count(*) FROM prediction_files").fetchone() == (0,)


def test_a_database_from_before_options_were_stored_is_upgraded(tmp_path) -> None:
    data = tmp_path / "data"
    with app_client(data) as c:
        old = upload(c, DEMO_PRED).json()["id"]
    db = sqlite3.connect(data / "kitti-eval.db")
    db.execute("ALTER TABLE evaluations DROP COLUMN options")
    as_unversioned(db.execute)  # an unversioned release's: upgraded at start, as told
    db.commit()
    db.close()
    with app_client(data, db_upgrade=True) as c:
        assert c.get(f"/v1/evaluations/{old}").status_code == 200
        assert_error(c.get(f"/v1/evaluations/{old}/frames"), 409, "without its options")
        new = upload(c, DEMO_PRED).json()["id"]
        assert c.get(f"/v1/evaluations/{new}/frames").status_code == 200


def forget_frames(data_dir) -> None:
    """The evaluations of ``data_dir`` as stored before their jobs stored their frames: answered from the kept
    predictions, read whole."""
    db = sqlite3.connect(data_dir / "kitti-eval.db")
    db.execute("DELETE FROM evaluation_frames")
    db.commit()
    db.close()


def test_kept_predictions_past_the_limits_on_work_are_refused_not_read_whole(tmp_path, monkeypatch) -> None:
    """Predictions kept under larger limits (by an evaluation stored without its frames) are looked at under the
    limits in force: the web process refuses
    them at the first frame past a limit (413, the frame named), instead of reading them whole and answering a
    frame of any size."""
    import io
    import tarfile
    import time

    line = b"Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59 0.95\n"
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for i in range(4):
            data = line * (3000 if i == 1 else 10)
            info = tarfile.TarInfo(f"pred/{i:06d}.txt")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    data_dir = tmp_path / "data"
    monkeypatch.delenv("KITTI_EVAL_MAX_BOXES_PER_FRAME", raising=False)
    with app_client(data_dir) as c:
        r = upload(c, buf.getvalue(), "pred.tar.gz")
        assert r.status_code == 201, r.text
        evaluation = r.json()["id"]
    forget_frames(data_dir)
    monkeypatch.setenv("KITTI_EVAL_MAX_BOXES_PER_FRAME", "500")
    with app_client(data_dir) as c:  # nothing cached: the kept file is read from the database
        started = time.monotonic()
        for response in (
            c.get(f"/v1/evaluations/{evaluation}/frames", params={"worst": 5}),
            c.get("/v1/frames/000000", params={"evaluation": evaluation}),
        ):
            err = assert_error(response, 413, "3000 boxes in one frame, more than the limit of 500")
            assert err["code"] == "over_work_limit" and err["frame"] == "000001"
        assert time.monotonic() - started < 10


def test_kept_predictions_of_more_boxes_than_a_frame_view_reads_are_refused(tmp_path, monkeypatch) -> None:
    """Frames of an evaluation stored without its frames are looked at from kept predictions read whole by the
    process that answers: past KITTI_EVAL_FRAMES_MAX_BOXES they are refused 413 at the frame that passes it,
    though they were evaluated."""
    monkeypatch.delenv("KITTI_EVAL_MAX_BOXES", raising=False)
    data_dir = tmp_path / "data"
    with app_client(data_dir) as c:
        r = upload(c, DEMO_PRED, "result.pkl.gz")
        assert r.status_code == 201, r.text
        evaluation = r.json()["id"]
    forget_frames(data_dir)
    boxes = load_detections(PRED_PATH).counts
    most = int(boxes[:3].sum())  # the fourth frame passes it
    with app_client(data_dir, frames_max_boxes=most) as c:
        err = assert_error(c.get(f"/v1/evaluations/{evaluation}/frames", params={"worst": 5}), 413)
        assert err["code"] == "over_work_limit" and err["frame"] == "000003"
        assert f"more than the limit of {most} in one input (KITTI_EVAL_FRAMES_MAX_BOXES)" in err["message"]
    with app_client(data_dir, frames_max_boxes=int(boxes.sum())) as c:
        assert c.get(f"/v1/evaluations/{evaluation}/frames", params={"worst": 5}).status_code == 200
