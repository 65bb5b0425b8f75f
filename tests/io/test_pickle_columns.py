"""Detections read straight from a checked pickle's bytes (kitti_eval.io.pickle_columns) are the detections the
objects give: the same arrays (values, dtypes, shapes), the same warnings; and whatever that reader leaves
(another layout, a refused frame or value) is read from the objects, with the same refusal as ever."""

from __future__ import annotations

import io
import pickle
from collections import OrderedDict
from typing import Any

import numpy as np
import pytest

from kitti_eval.core.frames import Annotations
from kitti_eval.errors import InputError
from kitti_eval.io.calib import Calib
from kitti_eval.io.camera import calibs_from_object
from kitti_eval.io.pickle_columns import read_detections, read_ground_truth
from kitti_eval.io.reading import LoadOptions, read_ground_truth_and_calibs, read_object, read_pickle
from kitti_eval.io.safe_pickle import check_pickle, load_pickle
from kitti_eval.synth import generate

FIELDS = ("name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score")


def _results(frames: int = 12, seed: int = 3, **kwargs: Any) -> list[dict[str, Any]]:
    return generate(frames, seed=seed, **kwargs)[1]


def _outcome(read: Any) -> tuple[str, Any, Any]:
    try:
        loaded = read()
    except InputError as e:
        return "refused", type(e).__name__, str(e)
    return "read", loaded.annotations, loaded.warnings


def _both(obj: object, protocol: int = 4, **options: Any) -> tuple[tuple[str, Any, Any], tuple[str, Any, Any], bool]:
    """(the read from the bytes, the read from the objects, whether the bytes' reader took it)."""
    return _routes(pickle.dumps(obj, protocol=protocol), **options)


def _routes(data: bytes, **options: Any) -> tuple[tuple[str, Any, Any], tuple[str, Any, Any], bool]:
    opts = LoadOptions(**options)
    fast = _outcome(lambda: read_pickle(io.BytesIO(data), "detections", "r.pkl", opts))
    lim = opts.with_limits()  # as read_annotations read a pickle before: load_pickle with the limits, read_object
    slow = _outcome(
        lambda: read_object(
            load_pickle(io.BytesIO(data), source="r.pkl", max_bytes=lim.max_bytes, max_entries=lim.max_frames),
            "detections",
            "r.pkl",
            lim,
        )
    )
    took = read_detections(
        check_pickle(io.BytesIO(data), source="r.pkl"),
        max_frames=lim.max_frames or 0,
        keep_lidar=opts.keep_lidar,
        known_frames=opts.known_frames,
        calibs=opts.calibs,
        warnings=[],
    )
    return fast, slow, took is not None


def _same(a: Annotations, b: Annotations) -> None:
    assert a.frame_ids == b.frame_ids and a.kind == b.kind and a.source == b.source
    assert dict(a.missing_fields) == dict(b.missing_fields)
    for f in ("offsets", *FIELDS, "boxes_lidar"):
        x, y = getattr(a, f), getattr(b, f)
        if y is None:
            assert x is None, f
            continue
        assert (x.dtype, x.shape, x.flags.writeable) == (y.dtype, y.shape, y.flags.writeable), f
        # bit for bit: both are the same float32 or float64 inputs converted to float64 once
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f


def _assert_parity(obj: object, *, taken: bool, protocol: int = 4, **options: Any) -> tuple[str, Any, Any]:
    fast, slow, took = _both(obj, protocol, **options)
    assert took is taken
    assert fast[0] == slow[0]
    if fast[0] == "read":
        _same(fast[1], slow[1])
        assert fast[2] == slow[2]
    else:
        assert fast[1:] == slow[1:]
    return fast


# ---------------------------------------------------------------------------------- read from the bytes


@pytest.mark.parametrize("protocol", [2, 3, 4])
@pytest.mark.parametrize("numpy_ids", [True, False])
def test_a_result_pkl_read_from_its_bytes_is_the_one_read_from_its_objects(protocol, numpy_ids):
    results = _results(40, empty_pred_frac=0.2, numpy_frame_ids=numpy_ids)
    assert any(len(r["name"]) == 0 for r in results) and any(len(r["name"]) for r in results)
    # protocol 2 writes array bytes as latin-1 text: taken only where that text is the bytes themselves
    fast = _assert_parity(results, taken=protocol > 2, protocol=protocol)
    assert fast[1].num_frames == 40 and fast[1].num_boxes == sum(len(r["name"]) for r in results)


def test_the_fields_and_ids_of_other_shapes_and_dtypes_it_takes():
    results = _results(9)
    for i, r in enumerate(results):
        # ints, numpy ints, str and numpy str (from a wider array: its bytes end in NULs)
        r["frame_id"] = [i, np.int64(i), f"{i:06d}", np.array([f" {i}", "a wider id"])[0]][i % 4]
        if i % 2:
            for f in ("bbox", "location", "score"):
                r[f] = r[f].astype(np.float64)  # float32 and float64 frames in one column
        r["truncated"] = np.zeros(len(r["name"]), np.int16)
        r["name"] = r["name"].astype(f"<U{12 + i}")  # names of many widths
    results[4] = {k: np.zeros((0, 4) if k == "bbox" else 0) for k in (*FIELDS, "boxes_lidar")} | {"frame_id": "4"}
    fast = _assert_parity(results, taken=True, keep_lidar=True)
    assert fast[1].name.dtype == np.dtype("<U20") and fast[1].frame_ids[4] == "000004"
    assert not np.isnan(fast[1].boxes_lidar).any()


def test_fields_no_frame_has_are_filled_and_said_as_from_the_objects():
    results = _results(6)
    for r in results:
        for f in ("bbox", "alpha", "truncated", "occluded", "boxes_lidar"):
            del r[f]
    fast = _assert_parity(results, taken=True, keep_lidar=True)
    assert dict(fast[1].missing_fields) == {"alpha": "000000", "bbox": "000000"}
    assert np.isnan(fast[1].boxes_lidar).all() and (fast[1].alpha == -10).all()


def test_the_camera_and_lidar_boxes_are_compared_on_the_same_frames_with_the_same_warning():
    results = _results(30, empty_pred_frac=0.1)
    calib = Calib(np.eye(4), np.eye(4)[:3].copy(), None)
    calibs = {f"{i:06d}": calib for i in range(30)}  # not the frames' own: most boxes disagree
    fast = _assert_parity(results, taken=True, calibs=calibs)
    assert len(fast[2]) == 1 and "camera fields and boxes_lidar disagree" in fast[2][0]


def test_the_ground_truths_frames_and_the_limits_apply_as_from_the_objects():
    results = _results(5)
    known = {f"{i:06d}": i for i in range(5)}
    _assert_parity(results, taken=True, known_frames=known)
    refused = _assert_parity(results, taken=False, known_frames={k: v for k, v in known.items() if k != "000003"})
    assert refused[1:] == ("InputError", "r.pkl, frame 000003: predictions for a frame that is not in the ground truth")
    too_many = _assert_parity(results, taken=False, max_frames=4)
    assert "more than the limit of 4" in too_many[2]


# ---------------------------------------------------------------------------------- left to the objects


def _with(change: Any) -> list[dict[str, Any]]:
    results = _results(6)
    change(results)
    return results


def _set(i: int, field: str, value: Any) -> Any:
    return lambda rs: rs[i].__setitem__(field, value)


LEFT = {
    "a repeated frame": lambda rs: rs[3].__setitem__("frame_id", rs[1]["frame_id"]),
    "a negative frame id": _set(2, "frame_id", -2),
    "a bool frame id": _set(2, "frame_id", True),
    "a missing frame id": lambda rs: rs[2].pop("frame_id"),
    "a missing field": lambda rs: rs[2].pop("score"),
    "a field in some frames only": lambda rs: rs[2].pop("alpha"),
    "a key of another format": _set(0, "sample_idx", 0),
    "NaN": lambda rs: rs[1]["location"].__setitem__((0, 2), np.nan),
    "an infinite lidar box": lambda rs: rs[1]["boxes_lidar"].__setitem__((0, 2), np.inf),
    "names as bytes": lambda rs: rs[1].__setitem__("name", rs[1]["name"].astype("S")),
    "names as a list": lambda rs: rs[1].__setitem__("name", list(rs[1]["name"])),
    "a code point past U+10FFFF": lambda rs: rs[1]["name"].view("<u4").__setitem__(0, 0x110000),
    "a short field": lambda rs: rs[1].__setitem__("score", rs[1]["score"][:-1]),
    "a wide field": lambda rs: rs[1].__setitem__("rotation_y", rs[1]["rotation_y"][:, None]),
    "bools": lambda rs: rs[1].__setitem__("score", rs[1]["score"] > 0.5),
    "big-endian numbers": lambda rs: rs[1].__setitem__("bbox", rs[1]["bbox"].astype(">f4")),
    "a Fortran-ordered field": lambda rs: rs[1].__setitem__("bbox", np.asfortranarray(rs[1]["bbox"])),
    "a list of numbers": lambda rs: rs[1].__setitem__("score", rs[1]["score"].tolist()),
    "boxes in a frame without names": lambda rs: rs[1].__setitem__("name", np.zeros(0)),
    "an OrderedDict frame": lambda rs: rs.__setitem__(1, OrderedDict(rs[1])),
    "a tuple of frames": lambda rs: None,  # made a tuple below
}


@pytest.mark.parametrize("case", list(LEFT))
def test_what_the_bytes_reader_leaves_is_read_or_refused_as_from_the_objects(case):
    results = _with(LEFT[case])
    obj: object = tuple(results) if case == "a tuple of frames" else results
    fast = _assert_parity(obj, taken=False, keep_lidar=True)
    refused = {"a repeated frame", "a negative frame id", "a bool frame id", "a missing frame id", "a missing field"}
    refused |= {"NaN", "an infinite lidar box", "a code point past U+10FFFF", "a short field", "a wide field", "bools"}
    refused |= {"boxes in a frame without names"}
    assert (fast[0] == "refused") == (case in refused)


# ---------------------------------------------------------------------------------- the scan's record


def test_the_scans_record_of_items_is_what_pickle_builds_and_grows_past_its_first_room():
    """Every item put into a list or dict, in order, with its container: 30,000 one-byte-ish items in a pickle
    of 60 kB need more rows than the record is first given (the scan is run again with more)."""
    obj = [list(range(200)) for _ in range(150)] + [{"a": 1, "b": [2, 3]}]
    data = pickle.dumps(obj, protocol=4)
    scan = check_pickle(io.BytesIO(data), source="x").scan
    nodes, root, items = scan[5], scan[7], scan[8]
    assert len(items) > len(data) // 64 + 1024  # past the first room
    frames = items[items[:, 0] == root, 1]
    assert len(frames) == 151 and (items[:, 2][items[:, 0] == root] == -1).all()
    inner = items[items[:, 0] == frames[3]]
    assert [int(nodes[n, 1]) for n in inner[:, 1]] == list(range(200))  # the ints' values, in order
    pairs = items[items[:, 0] == frames[-1]]
    assert len(pairs) == 2 and (pairs[:, 2] >= 0).all()
    assert pickle.loads(data) == load_pickle(io.BytesIO(data), source="x")


def test_corrupted_result_pkls_read_from_their_bytes_as_from_their_objects():
    """Bytes of a small result.pkl changed one at a time (800 seeded changes, protocol 4 and 3): whatever the
    scan accepts is read the same way by both routes, or refused by both with the same words."""
    rng = np.random.default_rng(7)
    results = _results(4, empty_pred_frac=0.3)
    taken = 0
    for protocol in (4, 3):
        data = bytearray(pickle.dumps(results, protocol=protocol))
        for _ in range(400):
            bad = bytearray(data)
            at = int(rng.integers(len(bad)))
            bad[at] = int(rng.integers(256)) if rng.random() < 0.5 else (bad[at] + int(rng.choice([-1, 1]))) % 256
            try:
                load_pickle(io.BytesIO(bytes(bad)), source="r.pkl")
            except InputError:
                continue  # the scan (or the unpickler) refuses it: neither route reads it
            fast, slow, _ = _routes(bytes(bad))
            assert fast[0] == slow[0], (protocol, at)
            if fast[0] == "read":
                _same(fast[1], slow[1])
                assert fast[2] == slow[2]
                taken += 1
            else:
                assert fast[1:] == slow[1:], (protocol, at)
    assert taken > 100  # most changes land in array data, which both read as the same numbers


# ---------------------------------------------------------------------------------- ground truth


def _gt_routes(infos: object, protocol: int = 4) -> tuple[Any, Any, bool]:
    """(ground truth and calibrations read from the bytes, the same from the objects, whether the bytes' reader
    took it); a refusal as (type, message)."""
    return _gt_routes_of_bytes(pickle.dumps(infos, protocol=protocol))


def _gt_routes_of_bytes(data: bytes) -> tuple[Any, Any, bool]:

    def outcome(read: Any) -> Any:
        try:
            return read()
        except InputError as e:
            return type(e).__name__, str(e)

    path = _file(data)
    fast = outcome(lambda: read_ground_truth_and_calibs(path))
    obj = load_pickle(io.BytesIO(data), source=str(path))
    slow = outcome(lambda: (read_object(obj, "ground_truth", str(path), LoadOptions()), calibs_from_object(obj)))
    took = read_ground_truth(check_pickle(io.BytesIO(data), source="gt.pkl"), max_frames=200_000) is not None
    return fast, slow, took


def _file(data: bytes) -> Any:
    path = _file.folder / "gt.pkl"  # type: ignore[attr-defined]
    path.write_bytes(data)
    return path


def _assert_gt_parity(infos: object, *, taken: bool, protocol: int = 4) -> Any:
    fast, slow, took = _gt_routes(infos, protocol)
    assert took is taken
    if isinstance(slow[0], str):
        assert fast == slow
        return fast
    (loaded, calibs), (loaded_slow, calibs_slow) = fast, slow
    _same(loaded.annotations, loaded_slow.annotations)
    assert loaded.warnings == loaded_slow.warnings
    assert sorted(calibs) == sorted(calibs_slow)
    for fid in calibs_slow:
        mine, theirs = calibs.get(fid), calibs_slow.get(fid)
        assert (mine is None) == (theirs is None), fid
        if theirs is not None:
            assert np.array_equal(mine.velo_to_rect, theirs.velo_to_rect) and np.array_equal(mine.p2, theirs.p2)
            assert mine.image_shape == theirs.image_shape
    return fast


@pytest.fixture(autouse=True)
def _folder(tmp_path):
    _file.folder = tmp_path  # type: ignore[attr-defined]


def _infos(frames: int = 10, **kwargs: Any) -> list[dict[str, Any]]:
    return generate(frames, seed=5, **kwargs)[0]


@pytest.mark.parametrize("protocol", [3, 4])
def test_infos_read_from_their_bytes_are_the_ones_read_from_their_objects_with_their_calibrations(protocol):
    infos = _infos(30, empty_gt_frac=0.2)
    assert any(len(i["annos"]["name"]) == 0 for i in infos)
    (loaded, calibs) = _assert_gt_parity(infos, taken=True, protocol=protocol)
    assert loaded.annotations.num_frames == 30 and len(calibs) == 30


GT_LEFT = {
    "an entry without image_idx (lidar_idx is used, and said)": lambda es: es[2]["image"].pop("image_idx"),
    "an entry without annos": lambda es: es[2].pop("annos"),
    "an entry of another key": lambda es: es[2].__setitem__("velodyne", 1),
    "a calibration as lists": lambda es: es[2]["calib"].__setitem__("P2", es[2]["calib"]["P2"].tolist()),
    "a calibration without P2": lambda es: es[2]["calib"].pop("P2"),
    "a repeated frame": lambda es: es[3]["image"].__setitem__("image_idx", es[2]["image"]["image_idx"]),
    "NaN": lambda es: es[1]["annos"]["location"].__setitem__((0, 0), np.nan),
}


@pytest.mark.parametrize("case", list(GT_LEFT))
def test_what_the_bytes_reader_leaves_of_infos_is_read_or_refused_as_from_the_objects(case):
    infos = _infos(6)
    GT_LEFT[case](infos)
    outcome = _assert_gt_parity(infos, taken=False)
    assert isinstance(outcome[0], str) == (case in {"an entry without annos", "a repeated frame", "NaN"})


def test_infos_without_calibration_in_some_entries_are_read_from_their_bytes():
    infos = _infos(6)
    del infos[2]["calib"], infos[4]["image"]["image_shape"]
    (_, calibs) = _assert_gt_parity(infos, taken=True)
    assert "000002" not in calibs and calibs["000004"].image_shape is None


def test_infos_read_with_known_frames_are_refused_as_from_their_objects():
    data = pickle.dumps(_infos(5), protocol=4)
    options = LoadOptions(known_frames={f"{i:06d}" for i in range(5) if i != 3})
    refusals = []
    for read in (
        lambda: read_pickle(io.BytesIO(data), "ground_truth", "gt.pkl", options),
        lambda: read_object(load_pickle(io.BytesIO(data), source="gt.pkl"), "ground_truth", "gt.pkl", options),
    ):
        with pytest.raises(InputError) as caught:
            read()
        refusals.append(str(caught.value))
    assert refusals[0] == refusals[1] == "gt.pkl, frame 000003: predictions for a frame that is not in the ground truth"
    whole = read_pickle(
        io.BytesIO(data), "ground_truth", "gt.pkl", LoadOptions(known_frames={f"{i:06d}" for i in range(5)})
    )
    assert whole.annotations.num_frames == 5


def test_corrupted_infos_read_from_their_bytes_as_from_their_objects():
    """Bytes of small infos changed one at a time (400 seeded changes): whatever the scan and the unpickler
    accept is read, calibrations included, the same way by both routes, or refused by both in the same words."""
    rng = np.random.default_rng(11)
    data = bytearray(pickle.dumps(_infos(3, empty_gt_frac=0.3), protocol=4))
    read = 0
    for _ in range(400):
        bad = bytearray(data)
        at = int(rng.integers(len(bad)))
        bad[at] = int(rng.integers(256)) if rng.random() < 0.5 else (bad[at] + int(rng.choice([-1, 1]))) % 256
        try:
            load_pickle(io.BytesIO(bytes(bad)), source="gt.pkl")
        except InputError:
            continue  # the scan (or the unpickler) refuses it: neither route reads it
        fast, slow, _ = _gt_routes_of_bytes(bytes(bad))
        if isinstance(slow[0], str):
            assert fast == slow, at
            continue
        _same(fast[0].annotations, slow[0].annotations)
        assert fast[0].warnings == slow[0].warnings
        assert sorted(fast[1]) == sorted(slow[1])
        for fid in slow[1]:
            mine, theirs = fast[1].get(fid), slow[1].get(fid)
            assert (mine is None) == (theirs is None), (at, fid)
            if theirs is not None:
                assert np.array_equal(mine.velo_to_rect, theirs.velo_to_rect, equal_nan=True), (at, fid)
        read += 1
    assert read > 100


# ---------------------------------------------------------------------------------- keys as pickle compares them


class _NumpyStrKey(str):
    """A dict key that pickles as ``numpy.str_(text)`` and is, until then, a key of its own beside its str: how a
    dict with both 'location' and numpy.str_('location') is written (pickle.loads keeps the last one's value)."""

    __hash__ = str.__hash__

    def __eq__(self, other: object) -> bool:
        return self is other

    def __reduce__(self) -> Any:
        return np.str_(str(self)).__reduce__()


def _twice(d: dict[str, Any], key: str, value: Any) -> None:
    """``d`` gets ``key`` again as a numpy.str_ with ``value``, after its str: the objects keep ``value``."""
    d[_NumpyStrKey(key)] = value


def test_the_helper_writes_a_numpy_str_key_after_its_str_and_pickle_keeps_the_last_value():
    d = {"location": 1}
    _twice(d, "location", 2)
    loaded = pickle.loads(pickle.dumps(d, protocol=4))
    assert loaded == {"location": 2} and type(next(iter(loaded))) is str


def test_a_numpy_str_key_after_its_str_in_annos_gives_the_objects_numbers():
    infos = _infos(1, empty_gt_frac=0.0)
    annos = infos[0]["annos"]
    other = annos["location"] + np.float32(40.0)  # the boxes pickle keeps: far from the detections
    _twice(annos, "location", other)
    (loaded, _) = _assert_gt_parity(infos, taken=False)
    assert np.array_equal(loaded.annotations.location, other.astype(np.float64))


def test_numpy_str_image_ids_after_their_str_give_each_frame_its_own_labels():
    infos = _infos(2, empty_gt_frac=0.0)
    _twice(infos[0]["image"], "image_idx", infos[1]["image"]["image_idx"])
    _twice(infos[1]["image"], "image_idx", infos[0]["image"]["image_idx"])
    (loaded, _) = _assert_gt_parity(infos, taken=False)
    annos = loaded.annotations
    assert annos.frame_ids == ("000001", "000000")  # the ids pickle keeps: the first entry is frame 000001
    first = annos.offsets[1]
    assert np.array_equal(annos.location[:first], infos[0]["annos"]["location"].astype(np.float64))


def test_a_numpy_str_calibration_key_converts_lidar_only_detections_with_the_matrix_pickle_keeps():
    infos = _infos(2, empty_gt_frac=0.0)
    calib = infos[0]["calib"]
    shifted = calib["Tr_velo_to_cam"].copy()
    shifted[:3, 3] += 5.0
    _twice(calib, "Tr_velo_to_cam", shifted)
    (_, calibs) = _assert_gt_parity(infos, taken=False)
    objects = calibs_from_object(pickle.loads(pickle.dumps(infos, protocol=4)))
    assert np.array_equal(calibs["000000"].velo_to_rect, objects["000000"].velo_to_rect)
    results = _results(2)
    for r in results:
        for f in ("location", "dimensions", "rotation_y"):
            del r[f]
    read = read_object(results, "detections", "r.pkl", LoadOptions(calibs=calibs))
    expected = read_object(results, "detections", "r.pkl", LoadOptions(calibs=objects))
    _same(read.annotations, expected.annotations)


def test_numpy_str_keys_alone_are_the_fields_as_the_objects_read_them():
    infos = _infos(3, empty_gt_frac=0.0)
    occluded = [info["annos"]["occluded"] for info in infos]
    for info in infos:  # in every entry: no frame lacks them, none has them as plain str
        for field in ("occluded", "alpha"):
            _twice(info["annos"], field, info["annos"].pop(field))
    (loaded, _) = _assert_gt_parity(infos, taken=False)
    a = loaded.annotations
    assert "alpha" not in dict(a.missing_fields)
    assert np.array_equal(a.occluded, np.concatenate(occluded))


def test_a_numpy_str_key_in_a_frame_of_detections_gives_the_objects_numbers():
    results = _results(3)
    _twice(results[1], "score", results[1]["score"] * 0 + 0.5)
    fast = _assert_parity(results, taken=False)
    assert (fast[1].score[fast[1].offsets[1] : fast[1].offsets[2]] == 0.5).all()
