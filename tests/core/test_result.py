"""EvalResult (kitti_eval.core.result): lookups, the JSON form and its round trip, stated on a small record."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from kitti_eval.core.ap import Curve
from kitti_eval.core.protocol import Difficulty, Metric
from kitti_eval.core.result import SCHEMA_VERSION, EvalResult


def _ap(value: float | None) -> dict:
    def metrics() -> dict:
        return {m: dict.fromkeys(("easy", "moderate", "hard"), value) for m in ("bbox", "bev", "3d", "aos")}

    return {"strict": {r: {"Car": metrics()} for r in ("R11", "R40")}}


def _result(**changes: object) -> EvalResult:
    ap = _ap(50.0)
    ap["strict"]["R40"]["Car"]["3d"]["moderate"] = 61.25
    fields: dict = dict(
        protocol="official",
        classes=("Car",),
        threshold_sets=("strict",),
        overlaps={"Car": {"strict": {"bbox": 0.7, "bev": 0.7, "3d": 0.7}}},
        ap=ap,
        num_gt={"Car": {"easy": 3, "moderate": 5, "hard": 6}},
        num_det={"Car": 9},
        frames=4,
        frames_without_predictions=("000003",),
        aos_evaluated=True,
        ranges=({"label": "30-inf", "min": 30.0, "max": math.inf, "ap": _ap(None), "num_gt": {"Car": {}}},),
    )
    fields.update(changes)
    return EvalResult(**fields)


def test_get_reads_one_value_with_r40_strict_by_default() -> None:
    r = _result()
    assert r.get("Car", "3d", "moderate") == 61.25
    assert r.get("Car", Metric.THREE_D, Difficulty.MODERATE) == 61.25
    assert r.get("Car", "3d", "moderate", recall="R11") == 50.0
    with pytest.raises(KeyError):
        r.get("Car", "3d", "moderate", oset="loose")


def test_the_json_form_has_every_key_and_survives_json() -> None:
    doc = _result().to_dict()
    assert doc["schema_version"] == SCHEMA_VERSION == 1
    assert doc["metrics"] == ["bbox", "bev", "3d", "aos"] and doc["difficulties"] == ["easy", "moderate", "hard"]
    assert doc["ranges"][0]["max"] is None  # an open range: null in JSON, inf in Python
    assert doc["coco"] is None and "curves" not in doc
    assert json.loads(json.dumps(doc, allow_nan=False)) == doc


def test_round_trip_through_the_json_form() -> None:
    r = _result(warnings=("a warning",))
    back = EvalResult.from_dict(json.loads(json.dumps(r.to_dict())))
    assert back == r  # timings and curves are not part of the comparison
    assert back.ranges[0]["max"] == math.inf
    with pytest.raises(ValueError, match="schema_version"):
        EvalResult.from_dict({**r.to_dict(), "schema_version": 2})


def test_to_dict_does_not_share_the_records_tables() -> None:
    r = _result()
    doc = r.to_dict()
    doc["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] = 0.0
    assert r.get("Car", "3d", "moderate") == 61.25


def test_curves_in_the_json_form_when_asked() -> None:
    curve = Curve(
        precision=np.linspace(1, 0, 41),
        recall=np.linspace(0, 1, 41),
        orientation=np.full(41, 0.5),
        thresholds=np.array([0.9, 0.5]),
        num_valid_gt=5,
    )
    r = _result(curves={"strict": {"Car": {"bbox": {"easy": curve}, "aos": {"easy": curve}}}})
    doc = r.to_dict(include_curves=True)
    assert doc["curves"]["strict"]["Car"]["bbox"]["easy"]["precision"][0] == 1.0
    assert doc["curves"]["strict"]["Car"]["aos"]["easy"]["precision"] == [0.5] * 41  # AOS shows orientation
    assert doc["curves"]["strict"]["Car"]["bbox"]["easy"]["thresholds"] == [0.9, 0.5]
    assert "curves" not in r.to_dict()
