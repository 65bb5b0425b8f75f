"""The JSON document as a dict (kitti_eval.report.render.json_document), which the service scores with, is what
``json.loads`` of the written document (render_json) gives back, value for value and type for type: it skips the
text in between, and must not differ from it in anything (a tuple, a key, a NaN)."""

from __future__ import annotations

import json
from enum import Enum
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kitti_eval.analysis.decomposition import errors_document, evaluate_with_errors
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.protocol import EvalConfig, config_from_options
from kitti_eval.core.result import EvalResult
from kitti_eval.demo import demo_paths
from kitti_eval.io.loaders import load_pair
from kitti_eval.report.render import json_document, render_json

GT, DT = load_pair(*demo_paths())
#: the demo's result, the one every generated extra is added to
RESULT = evaluate(GT, DT, EvalConfig())


def _typed(value: Any) -> Any:
    """``value`` with each leaf paired with its type, so that ``==`` tells 1 from 1.0 and True, and a list from a
    tuple."""
    if isinstance(value, dict):
        return ("dict", {(type(k).__name__, k): _typed(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, [_typed(v) for v in value])
    return (type(value).__name__, value)


def _same_as_written(result: EvalResult, **options: Any) -> None:
    doc = json_document(result, **options)
    assert _typed(doc) == _typed(json.loads(render_json(result, **options)))


class _Name(str, Enum):
    CAR = "Car"


_leaves = (
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.floats(width=32).map(np.float64)
    | st.text(max_size=4)
    | st.just(_Name.CAR)
)
_keys = (
    st.text(max_size=4)
    | st.integers(-5, 5)
    | st.booleans()
    | st.none()
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.just(_Name.CAR)
)
_values = st.recursive(
    _leaves,
    lambda inner: (
        st.lists(inner, max_size=3) | st.lists(inner, max_size=3).map(tuple) | st.dictionaries(_keys, inner, max_size=3)
    ),
    max_leaves=12,
)


@given(extra=st.dictionaries(st.text(max_size=6), _values, max_size=3))
@settings(max_examples=300, deadline=None)
def test_any_extra_keys_come_out_as_the_written_document_reads_back(extra: dict[str, Any]) -> None:
    """Property: whatever the extra keys hold (NaN and infinities, tuples, keys that are not strings, numpy
    floats, a string enum), the dict is the written document read back."""
    written = render_json(RESULT, extra=extra)
    assert _typed(json_document(RESULT, extra=extra)) == _typed(json.loads(written))


def test_an_evaluation_s_document_with_curves_ranges_coco_and_errors_is_the_written_one() -> None:
    """The documents the service keeps: with curves, distance ranges (an open one: null), COCO-style AP, AP that
    is not a number (a class without ground truth), and the error decomposition's keys."""
    config = config_from_options(classes="Car,Pedestrian,Cyclist,Van", ranges="0,30,inf", coco=True)
    result, decomposition = evaluate_with_errors(GT, DT, config, keep_curves=True, oset="strict")
    _same_as_written(result, include_curves=True, extra=errors_document(decomposition, full=False))
    doc = json_document(result, include_curves=True)
    assert doc["ranges"][1]["max"] is None and doc["coco"] is not None and "curves" in doc
    assert None in doc["ap"]["strict"]["R40"]["Van"]["3d"].values()  # no Van in the demo: AP is no number
    _same_as_written(RESULT)
