"""The frames an evaluation's job stores: its frame listings and frame views answered from them are exactly the
answers of its kept predictions read whole (the path of evaluations stored before), for any question, and the
process that answers reads no kept file to give them."""

from __future__ import annotations

import gzip
import pickle
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from server_helpers import app_client, upload

from kitti_eval.demo import demo_paths
from kitti_eval.io.loaders import load_ground_truth
from kitti_eval.io.safe_pickle import load_pickle
from kitti_eval_server.evaluations.evaluations import EvaluationFrames
from kitti_eval_server.store import EvaluationStore, GroundTruthStore

GT_PATH, PRED_PATH = demo_paths()
DEMO_PRED = PRED_PATH.read_bytes()
FRAME_IDS = load_ground_truth(GT_PATH).frame_ids


def varied_predictions() -> bytes:
    """The demo predictions with a third of the boxes dropped, the scores shuffled within each frame and some
    alphas -10 (no orientation for the openpcdet rule), so that frames differ from the demo's."""
    rng = np.random.default_rng(7)
    out = []
    for anno in load_pickle(PRED_PATH, source="demo"):
        n = len(anno["name"])
        keep = rng.random(n) > 0.33
        anno = {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v) for k, v in anno.items()}
        anno["score"] = rng.permutation(anno["score"])
        out.append(anno)
    out[0]["alpha"] = np.full_like(out[0]["alpha"], -10.0)
    return gzip.compress(pickle.dumps(out))


@contextmanager
def read_whole() -> Iterator[None]:
    """Answer as for an evaluation stored without its frames: from the kept predictions read whole."""
    with (
        mock.patch.object(EvaluationStore, "has_frames", lambda self, evaluation_id: False),
        mock.patch.object(EvaluationFrames, "_stored_frame", lambda self, records, fid, cls: None),
    ):
        yield


@pytest.fixture(scope="module")
def service(tmp_path_factory: Any) -> Iterator[tuple[Any, list[str], Path]]:
    data = tmp_path_factory.mktemp("rows") / "data"
    with app_client(data) as c:
        ids = []
        for content, fields in (
            (DEMO_PRED, {"model": "demo"}),
            (varied_predictions(), {"model": "varied"}),
            (varied_predictions(), {"protocol": "openpcdet", "classes": "Car,Pedestrian,Cyclist,Van"}),
            (DEMO_PRED, {"threshold_sets": "loose", "classes": "Pedestrian,Car", "ranges": "0,30,inf"}),
            (DEMO_PRED, {"lidar_only": "true", "errors": "true"}),
        ):
            r = upload(c, content, "result.pkl.gz", fields=fields)
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
        yield c, ids, data


def _answer(response: Any) -> tuple[int, Any]:
    """The status and body (without a refusal's request id, which is each request's own)."""
    body = response.json()
    if isinstance(body.get("error"), dict):
        body["error"].pop("request_id", None)
    return response.status_code, body


QUESTION = st.fixed_dictionaries(
    {
        "class": st.sampled_from(["Car", "Pedestrian", "Cyclist", "Van", "car"]),
        "metric": st.sampled_from(["bbox", "bev", "3d", "aos"]),
        "difficulty": st.sampled_from(["easy", "moderate", "hard"]),
        "set": st.sampled_from(["strict", "loose"]),
        "score_threshold": st.one_of(
            st.just(0.0), st.floats(-2, 2, allow_nan=False), st.sampled_from([0.5, 0.9, -1e9, 1e9])
        ),
    }
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(question=QUESTION, worst=st.sampled_from([1, 5, 20, 10_000]), which=st.integers(0, 4))
def test_a_listing_from_the_stored_frames_is_the_listing_of_the_predictions_read_whole(
    service: Any, question: dict[str, Any], worst: int, which: int
) -> None:
    c, ids, _ = service
    url = f"/v1/evaluations/{ids[which]}/frames"
    stored = _answer(c.get(url, params={**question, "worst": worst}))
    with read_whole():
        whole = _answer(c.get(url, params={**question, "worst": worst}))
    assert stored == whole


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    question=QUESTION,
    frame=st.sampled_from([*FRAME_IDS[:6], "999999"]),
    which=st.lists(st.integers(0, 4), min_size=1, max_size=3),
    thresholded=st.booleans(),
)
def test_a_frame_view_from_the_stored_frames_is_the_view_of_the_predictions_read_whole(
    service: Any, question: dict[str, Any], frame: str, which: list[int], thresholded: bool
) -> None:
    c, ids, _ = service
    params = {**question, "evaluation": [ids[k] for k in which]}
    if not thresholded:
        del params["score_threshold"]
    stored = _answer(c.get(f"/v1/frames/{frame}", params=params))
    with read_whole():
        whole = _answer(c.get(f"/v1/frames/{frame}", params=params))
    assert stored == whole


def test_the_job_stores_a_row_per_frame_and_the_answers_read_no_kept_file(service: Any) -> None:
    _, ids, data = service
    db = sqlite3.connect(data / "kitti-eval.db")
    counts = dict(db.execute("SELECT evaluation_id, count(*) FROM evaluation_frames GROUP BY evaluation_id"))
    db.close()
    assert counts == dict.fromkeys(ids, len(FRAME_IDS))
    read = GroundTruthStore.prediction_content
    with mock.patch.object(GroundTruthStore, "prediction_content", autospec=True, side_effect=read) as kept:
        with app_client(data) as fresh:  # nothing cached
            assert fresh.get(f"/v1/evaluations/{ids[1]}/frames", params={"worst": 3}).status_code == 200
            r = fresh.get(f"/v1/frames/{FRAME_IDS[2]}", params={"evaluation": ids[:2]})
            assert r.status_code == 200, r.text
            worst = fresh.get(f"/v1/evaluations/{ids[1]}/frames", params={"worst": 1}).json()["frames"][0]["frame"]
            page = fresh.get(f"/evaluations/{ids[1]}")  # its worst frames, from the same rows
            assert page.status_code == 200 and f"/frames/{worst}?" in page.text, page.text[-2000:]
            assert fresh.get(f"/frames/{worst}", params={"e": ids[1]}).status_code == 200
            assert kept.call_count == 0
            # a class the evaluation did not evaluate is answered the old way, from the kept file
            van = fresh.get(f"/v1/evaluations/{ids[0]}/frames", params={"class": "Van"})
            assert van.status_code == 422 and "Van is not evaluated in 3d" in van.text
            assert kept.call_count == 1
