"""The columns route (kitti_eval.io.pickle_columns) against the objects route, on pickles written by opcodes.

Hypothesis writes result.pkl and infos files with every choice a pickler or a hand could make (the writer:
tests/helpers/pickle_opcodes.py): protocols 0-5, memo writes and reads, DUP, dicts by SETITEM, SETITEMS or
DICT, keys written as numpy.str_ or with escapes and keys given twice, arrays shared between frames, numpy 1.x
and 2.x module names, ``_frombuffer`` arrays, dtypes and byte orders, Fortran order, frame ids as str, ints and
numpy scalars. Whatever it writes, both routes read the same arrays and warnings, or refuse it in the same
words. A bounded number of examples in the quick tests; the slow half runs more.
"""

from __future__ import annotations

import io
import pickle
import random
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from pickle_opcodes import Dict, Key, dumps
from test_pickle_columns import _routes, _same

from kitti_eval.errors import InputError
from kitti_eval.io.camera import calibs_from_object
from kitti_eval.io.reading import LoadOptions, read_ground_truth_and_calibs, read_object
from kitti_eval.io.safe_pickle import load_pickle
from kitti_eval.synth import generate

#: a failure is reported as drawn: shrinking an example of hundreds of draws takes minutes
_NO_SHRINK = (Phase.explicit, Phase.reuse, Phase.generate)
QUICK = settings(
    max_examples=100, deadline=None, derandomize=True, phases=_NO_SHRINK, suppress_health_check=list(HealthCheck)
)
SLOW = settings(max_examples=2000, deadline=None, phases=_NO_SHRINK, suppress_health_check=list(HealthCheck))


class _Choices:
    """The example's choices: ``choose`` one of some options, and a ``rare`` change (a key written otherwise or
    given twice, a cast, a shared array, a big-endian or Fortran-ordered array), as rare as the example says:
    from most values changed to none (a file the columns route takes). Hypothesis draws the protocol, how rare
    a change is and a seed of the many small choices (a draw each would cost more than the reads)."""

    def __init__(self, data: st.DataObject, keys_only: bool = False) -> None:
        self.data = data
        self.changes = ["form", "twice", "twice", "twice"] if keys_only else ["cast", "widen", "share", "form", "twice"]
        self.protocols = [3, 4] if keys_only else [4, 3, 4, 3, 0, 1, 2, 5]
        odds = [30, 100, 300] if keys_only else [3, 10, 40, 150, 600, 0]
        self.odds = data.draw(st.sampled_from(odds), label="one change in")
        self.rng = random.Random(data.draw(st.integers(0, 2**32 - 1), label="seed of the choices"))

    def choose(self, options: Any) -> Any:
        return self.rng.choice(list(options))

    def rare(self) -> bool:
        return self.odds > 0 and self.rng.randrange(self.odds + 1) == 0

    def rarer(self) -> bool:
        """A layout the columns route leaves to the objects (big-endian, Fortran order): rarer still."""
        return self.rare() and self.rare()

    def protocol(self) -> int:
        return int(self.data.draw(st.sampled_from(self.protocols), label="protocol"))


def _frame_id(c: _Choices, i: int) -> Any:
    forms = [str(i), i, np.str_(f"{i:06d}"), np.str_(str(i)), np.int64(i), np.int32(i), np.uint8(i)]
    return c.choose(forms) if c.rare() or c.rare() else f"{i:06d}"


def _fields(c: _Choices, d: dict[str, Any], others: list[dict[str, Any]]) -> Dict:
    """``d`` as pairs, now and then a key written in another form or given twice, an array cast, widened or
    shared with one of ``others``, a key added."""
    pairs: list[tuple[Any, Any]] = []
    for key, value in d.items():
        numeric = isinstance(value, np.ndarray) and value.dtype.kind in "fiu"
        change = c.choose(c.changes) if c.rare() else ""
        if change == "cast" and numeric:
            value = value.astype(c.choose(["<f8", "<f2", "<i2", "<u1", "<i8", "<f4"]))
        elif change == "widen" and isinstance(value, np.ndarray) and value.dtype.kind == "U":
            value = value.astype(f"<U{value.dtype.itemsize // 4 + 5}")
        elif change == "share" and isinstance(value, np.ndarray):
            same = [o[key] for o in others if key in o and np.shape(o[key]) == value.shape]
            if same:
                value = same[0]  # the same array object as another frame's: written once, then read from the memo
        form = c.choose(["numpy", "numpy", "escaped"]) if change == "form" else "str"
        pairs.append((Key(key, form) if form != "str" else key, value))
        if change == "twice":  # the key again, with another value: pickle keeps the last
            other = value
            if numeric or (isinstance(value, np.ndarray) and value.dtype.kind == "U"):
                other = (value + 7).astype(value.dtype) if numeric else value[::-1].copy()
            elif isinstance(value, (str, int)) and not isinstance(value, bool):
                other = _frame_id(c, int(value) + 50)  # another frame's id
            again = (Key(key, c.choose(["numpy", "numpy", "numpy", "str", "escaped"])), other)
            pairs.insert(c.choose([len(pairs), len(pairs), len(pairs), len(pairs) - 1]), again)
    if c.rare():
        pairs.append((c.choose(["sample_idx", "extra", Key("extra", "numpy")]), 0))
    return Dict(pairs)


def _results(data: st.DataObject, keys_only: bool = False) -> bytes:
    c = _Choices(data, keys_only)
    frames = data.draw(st.integers(1, 4))
    results = generate(frames, seed=data.draw(st.integers(0, 2**16)), empty_pred_frac=0.2)[1]
    written: list[dict[str, Any]] = []
    out = []
    for i, r in enumerate(results):
        r = dict(r, frame_id=_frame_id(c, i))
        out.append(_fields(c, r, written))
        written.append(r)
    return dumps(out, c.protocol(), c.choose, c.rarer)


def _infos(data: st.DataObject, keys_only: bool = False) -> bytes:
    c = _Choices(data, keys_only)
    frames = data.draw(st.integers(1, 4))
    infos = generate(frames, seed=data.draw(st.integers(0, 2**16)), empty_gt_frac=0.2)[0]
    out = []
    annos: list[dict[str, Any]] = []
    calibs: list[dict[str, Any]] = []
    for i, info in enumerate(infos):
        entry = {
            "point_cloud": _fields(c, info["point_cloud"], []),
            "image": _fields(c, dict(info["image"], image_idx=_frame_id(c, i)), []),
            "calib": _fields(c, info["calib"], calibs),
            "annos": _fields(c, info["annos"], annos),
        }
        annos.append(info["annos"])
        calibs.append(info["calib"])
        out.append(_fields(c, entry, []))
    return dumps(out, c.protocol(), c.choose, c.rarer)


def _assert_detections_agree(data: bytes) -> None:
    fast, slow, _ = _routes(data, keep_lidar=True)
    assert fast[0] == slow[0], (fast, slow)
    if fast[0] == "read":
        _same(fast[1], slow[1])
        assert fast[2] == slow[2]
    else:
        assert fast[1:] == slow[1:]


def _outcome(read: Any) -> Any:
    try:
        return read()
    except InputError as e:
        return type(e).__name__, str(e)


def _assert_ground_truth_agrees(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "gt.pkl"
        path.write_bytes(data)
        fast = _outcome(lambda: read_ground_truth_and_calibs(path))

        def slow() -> Any:
            obj = load_pickle(io.BytesIO(data), source=str(path))
            return read_object(obj, "ground_truth", str(path), LoadOptions()), calibs_from_object(obj)

        objects = _outcome(slow)
    if isinstance(objects[0], str) or isinstance(fast[0], str):
        assert fast == objects
        return
    (loaded, calibs), (loaded_slow, calibs_slow) = fast, objects
    _same(loaded.annotations, loaded_slow.annotations)
    assert loaded.warnings == loaded_slow.warnings
    assert sorted(calibs) == sorted(calibs_slow)
    for fid in calibs_slow:
        mine, theirs = calibs.get(fid), calibs_slow.get(fid)
        assert (mine is None) == (theirs is None), fid
        if theirs is not None:
            assert np.array_equal(mine.velo_to_rect, theirs.velo_to_rect, equal_nan=True), fid
            assert np.array_equal(mine.p2, theirs.p2, equal_nan=True) and mine.image_shape == theirs.image_shape


@QUICK
@given(st.data())
def test_results_written_by_opcodes_read_the_same_from_their_bytes_and_their_objects(data):
    _assert_detections_agree(_results(data))


@QUICK
@given(st.data())
def test_infos_written_by_opcodes_read_the_same_from_their_bytes_and_their_objects(data):
    _assert_ground_truth_agrees(_infos(data))


@QUICK
@given(st.data())
def test_infos_with_keys_written_otherwise_or_twice_read_the_same_from_their_bytes_and_their_objects(data):
    """Only keys changed (a numpy.str_, an escaped str, a key given twice), at protocols 3 and 4: files the
    columns route would otherwise take."""
    _assert_ground_truth_agrees(_infos(data, keys_only=True))


@pytest.mark.slow
@SLOW
@given(st.data())
def test_many_results_written_by_opcodes_read_the_same_from_their_bytes_and_their_objects(data):
    _assert_detections_agree(_results(data))


@pytest.mark.slow
@SLOW
@given(st.data())
def test_many_infos_written_by_opcodes_read_the_same_from_their_bytes_and_their_objects(data):
    _assert_ground_truth_agrees(_infos(data, keys_only=data.draw(st.booleans())))


# ---------------------------------------------------------------------------------- the writer itself


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.data())
def test_the_writer_writes_what_pickle_reads_back(data):
    """Without keys given twice or written as numpy.str_, pickle.loads of what the writer writes is the value
    (arrays of the same numbers and dtype, in either byte order)."""
    choose = _Choices(data).choose
    protocol = data.draw(st.integers(0, 5))
    shared = np.arange(6, dtype=np.float32).reshape(2, 3)
    value = [
        {"a": shared, "b": np.array(["Car", "Pedestrian"]), "c": np.int64(-3), "d": np.str_("0012"), "e": b""},
        {"a": shared, "b": np.zeros((0, 4), "<f8"), "f": b"raw"},
        (1, (2,)),
        [1, 2**40, -5, True, None, "x\\y\n"],
        np.asfortranarray(np.arange(6.0).reshape(3, 2)),
    ]
    got = pickle.loads(dumps(value, protocol, choose))
    assert got[2:4] == value[2:4]
    for mine, theirs in [*zip(got[:2], value[:2]), ({"x": got[4]}, {"x": value[4]})]:
        assert mine.keys() == theirs.keys()
        for k, v in theirs.items():
            assert np.array_equal(mine[k], v), k
            assert np.asarray(mine[k]).dtype.str[1:] == np.asarray(v).dtype.str[1:], k
