"""kitti_eval.core.geometry: 2D / BEV / 3D overlaps, checked against geometry and against slow shapely twins."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from naive import iou_2d_naive, iou_3d_naive, iou_bev_naive

from kitti_eval.core.geometry import FrameOverlaps, frame_overlaps, iou_2d, iou_3d, iou_bev

PI = math.pi
IMPLS = {
    "kernel": SimpleNamespace(iou_2d=iou_2d, iou_bev=iou_bev, iou_3d=iou_3d),
    "naive": SimpleNamespace(iou_2d=iou_2d_naive, iou_bev=iou_bev_naive, iou_3d=iou_3d_naive),
}


@pytest.fixture(params=sorted(IMPLS))
def impl(request):
    return IMPLS[request.param]


def box(x=0.0, y=0.0, z=0.0, l=1.0, h=1.0, w=1.0, ry=0.0):  # noqa: E741
    return np.array([x, y, z, l, h, w, ry], dtype=np.float64)


def one(fn, a, b, criterion="union"):
    out = fn(np.atleast_2d(a), np.atleast_2d(b), criterion)
    assert out.shape == (1, 1) and out.dtype == np.float64
    return float(out[0, 0])


#: (l, h, w) of KITTI Car, Pedestrian, Cyclist
_SIZES = np.array([[3.9, 1.56, 1.6], [0.8, 1.75, 0.6], [1.76, 1.74, 0.6]])


def random_boxes(rng, n):
    sizes = _SIZES[rng.integers(0, 3, n)] * rng.uniform(0.8, 1.2, (n, 3))
    return np.column_stack(
        [rng.uniform(-30, 30, n), rng.uniform(0.5, 2.5, n), rng.uniform(2, 70, n), sizes, rng.uniform(-PI, PI, n)]
    )


def jitter(rng, boxes, scale=1.0):
    """Boxes near ``boxes``: shifted by about their size, resized, turned; some turned by exactly pi."""
    n = len(boxes)
    out = boxes.copy()
    out[:, 0] += rng.normal(0, 0.4 * scale, n) * boxes[:, 3]
    out[:, 2] += rng.normal(0, 0.4 * scale, n) * boxes[:, 5]
    out[:, 1] += rng.normal(0, 0.2 * scale, n)
    out[:, 3:6] *= rng.uniform(0.8, 1.25, (n, 3))
    out[:, 6] += rng.normal(0, 0.3 * scale, n)
    flip = rng.random(n) < 0.15
    out[flip, 6] += PI
    same_yaw = rng.random(n) < 0.15
    out[same_yaw, 6] = boxes[same_yaw, 6]
    return out


def rigid(boxes, phi, t):
    """Rotate boxes about the camera y axis by ``phi`` (yaw += phi) and translate them by ``t`` (x, y, z)."""
    out = boxes.copy()
    c, s = math.cos(phi), math.sin(phi)
    x, z = boxes[:, 0], boxes[:, 2]
    out[:, 0] = c * x + s * z + t[0]
    out[:, 2] = -s * x + c * z + t[2]
    out[:, 1] += t[1]
    out[:, 6] += phi
    return out


# ------------------------------------------------------------------- geometric properties, both twins


@pytest.mark.parametrize("criterion", ["union", "first"])
def test_identity_is_one(impl, criterion):
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 60)
    for b in boxes:
        assert one(impl.iou_bev, b, b, criterion) == pytest.approx(1, abs=1e-12)
        assert one(impl.iou_3d, b, b, criterion) == pytest.approx(1, abs=1e-12)
    img = np.array([[10.0, 20.0, 110.5, 70.25], [0.0, 0.0, 1.0, 1.0], [700.3, 150.1, 790.9, 320.7]])
    assert np.diag(impl.iou_2d(img, img, criterion)) == pytest.approx([1, 1, 1], abs=1e-15)


def test_symmetry(impl):
    rng = np.random.default_rng(2)
    a = random_boxes(rng, 40)
    b = jitter(rng, a)
    for x, y in zip(a, b):
        for fn in (impl.iou_bev, impl.iou_3d):
            v = one(fn, x, y)
            assert v == pytest.approx(one(fn, y, x), rel=1e-12, abs=1e-15)
    img_a = np.array([[10.0, 20.0, 110.0, 70.0], [5.0, 5.0, 50.0, 60.0]])
    img_b = np.array([[60.0, 30.0, 150.0, 90.0], [0.0, 0.0, 20.0, 20.0]])
    assert np.array_equal(impl.iou_2d(img_a, img_b), impl.iou_2d(img_b, img_a).T)


def test_rigid_motion_invariance(impl):
    rng = np.random.default_rng(3)
    a = random_boxes(rng, 40)
    b = jitter(rng, a)
    bev = [one(impl.iou_bev, x, y) for x, y in zip(a, b)]
    d3 = [one(impl.iou_3d, x, y) for x, y in zip(a, b)]
    assert sum(v > 0.1 for v in bev) > 15  # the pairs do overlap
    for phi, t in ((0.7, (3.0, -0.4, 12.0)), (-2.9, (-40.0, 1.0, 5.5)), (PI / 2, (0.0, 0.0, 0.0))):
        ra, rb = rigid(a, phi, t), rigid(b, phi, t)
        assert [one(impl.iou_bev, x, y) for x, y in zip(ra, rb)] == pytest.approx(bev, rel=1e-9, abs=1e-12)
        assert [one(impl.iou_3d, x, y) for x, y in zip(ra, rb)] == pytest.approx(d3, rel=1e-9, abs=1e-12)


def test_disjoint_is_zero(impl):
    a = box(x=0, z=10, l=4, w=2, ry=0.3)
    far = box(x=20, z=40, l=4, w=2, ry=-1.0)
    # 1 cm gap between two parallel turned boxes
    phi = 0.6
    near = rigid(np.stack([box(l=4, w=2), box(x=4.01, l=4, w=2)]), phi, (1.0, 0.0, 8.0))
    for x, y in ((a, far), (near[0], near[1])):
        for crit in ("union", "first"):
            assert one(impl.iou_bev, x, y, crit) == 0.0
            assert one(impl.iou_3d, x, y, crit) == 0.0
    # same BEV footprint, vertically apart: the box above spans y - h .. y = -3 .. -2
    assert one(impl.iou_3d, box(y=1.5, h=1.5), box(y=-2.0, h=1.0)) == 0.0
    assert one(impl.iou_bev, box(y=1.5, h=1.5), box(y=-2.0, h=1.0)) == 1.0
    assert impl.iou_2d([[0, 0, 10, 10]], [[20, 0, 30, 10]])[0, 0] == 0.0


@pytest.mark.parametrize("ry_small", [0.0, 0.4, -2.0])
def test_containment(impl, ry_small):
    big = box(x=2.0, y=2.0, z=20.0, l=6.0, h=3.0, w=4.0, ry=1.1)
    small = box(x=2.3, y=1.5, z=19.8, l=1.0, h=1.0, w=0.5, ry=ry_small)
    ratio = 0.5 / 24.0
    assert one(impl.iou_bev, small, big) == pytest.approx(ratio, rel=1e-12)
    assert one(impl.iou_bev, big, small) == pytest.approx(ratio, rel=1e-12)
    assert one(impl.iou_bev, small, big, "first") == pytest.approx(1.0, rel=1e-12)
    assert one(impl.iou_bev, big, small, "first") == pytest.approx(ratio, rel=1e-12)
    vol_ratio = 0.5 / 72.0
    assert one(impl.iou_3d, small, big) == pytest.approx(vol_ratio, rel=1e-12)
    assert one(impl.iou_3d, small, big, "first") == pytest.approx(1.0, rel=1e-12)
    assert one(impl.iou_3d, big, small, "first") == pytest.approx(vol_ratio, rel=1e-12)
    img_big, img_small = [[0, 0, 100, 50]], [[10, 10, 20, 20]]
    assert impl.iou_2d(img_small, img_big)[0, 0] == pytest.approx(100 / 5000, rel=1e-15)
    assert impl.iou_2d(img_small, img_big, "first")[0, 0] == 1.0
    assert impl.iou_2d(img_big, img_small, "first")[0, 0] == pytest.approx(100 / 5000, rel=1e-15)


@pytest.mark.parametrize("phi", [0.0, 0.3, PI / 2, -2.2, PI])
def test_collinear_shared_edges(impl, phi):
    t = (5.0, 0.0, 20.0)
    side_by_side = rigid(np.stack([box(), box(x=1.0)]), phi, t)
    half = rigid(np.stack([box(), box(x=0.5)]), phi, t)
    corner = rigid(np.stack([box(), box(x=1.0, z=1.0)]), phi, t)
    for fn in (impl.iou_bev, impl.iou_3d):
        assert one(fn, *side_by_side) == pytest.approx(0, abs=1e-12)
        assert one(fn, *corner) == pytest.approx(0, abs=1e-12)
        assert one(fn, *half) == pytest.approx(1 / 3, rel=1e-12)
        assert one(fn, *half, "first") == pytest.approx(0.5, rel=1e-12)
    assert impl.iou_2d([[0, 0, 1, 1]], [[1, 0, 2, 1]])[0, 0] == 0.0
    assert impl.iou_2d([[0, 0, 1, 1]], [[0.5, 0, 1.5, 1]])[0, 0] == 1 / 3


def test_yaw_pi_and_flips_are_the_same_rectangle(impl):
    for ry in (0.0, 0.5, -1.3, PI / 2, PI, -PI):
        a = box(x=3.0, z=15.0, l=4.2, h=1.5, w=1.8, ry=ry)
        for other in (ry + PI, ry - PI, ry + 2 * PI, -ry if abs(ry) == PI else ry):
            b = a.copy()
            b[6] = other
            assert one(impl.iou_bev, a, b) == pytest.approx(1, abs=1e-12)
            assert one(impl.iou_3d, a, b) == pytest.approx(1, abs=1e-12)
    # yaw near +-pi from both sides: nearly the same rectangle
    a = box(z=10.0, l=4.0, w=1.6, ry=PI - 1e-9)
    b = box(z=10.0, l=4.0, w=1.6, ry=-PI + 1e-9)
    assert one(impl.iou_bev, a, b) == pytest.approx(1, abs=1e-8)
    # a small turn across pi is a real overlap: compare with the same turn about zero
    c, d = box(l=4.0, w=1.6, ry=PI - 0.05), box(l=4.0, w=1.6, ry=-PI + 0.05)
    e, f = box(l=4.0, w=1.6, ry=-0.05), box(l=4.0, w=1.6, ry=0.05)
    assert one(impl.iou_bev, c, d) == pytest.approx(one(impl.iou_bev, e, f), rel=1e-12)
    assert 0.8 < one(impl.iou_bev, c, d) < 0.99


def test_quarter_turns(impl):
    square = box(x=1.0, z=7.0, l=2.0, w=2.0)
    turned = square.copy()
    turned[6] = PI / 2
    assert one(impl.iou_bev, square, turned) == pytest.approx(1, abs=1e-12)
    # a rectangle turned by 90 degrees with l and w swapped is the same rectangle
    rect = box(x=1.0, z=7.0, l=4.0, w=1.5, ry=0.2)
    swapped = box(x=1.0, z=7.0, l=1.5, w=4.0, ry=0.2 + PI / 2)
    assert one(impl.iou_bev, rect, swapped) == pytest.approx(1, abs=1e-12)
    # ... and without the swap it is a cross: overlap 1.5 x 1.5
    cross = box(x=1.0, z=7.0, l=4.0, w=1.5, ry=0.2 + PI / 2)
    assert one(impl.iou_bev, rect, cross) == pytest.approx(2.25 / (12 - 2.25), rel=1e-12)


def test_vertical_offsets(impl):
    a = box(y=2.0, h=1.0, l=3.0, w=2.0)
    half_up = box(y=1.5, h=1.0, l=3.0, w=2.0)  # spans 0.5 .. 1.5 against 1 .. 2
    assert one(impl.iou_3d, a, half_up) == pytest.approx(1 / 3, rel=1e-12)
    assert one(impl.iou_3d, a, half_up, "first") == pytest.approx(0.5, rel=1e-12)
    touching = box(y=1.0, h=1.0, l=3.0, w=2.0)
    assert one(impl.iou_3d, a, touching) == 0.0
    taller = box(y=2.0, h=2.0, l=3.0, w=2.0)
    assert one(impl.iou_3d, a, taller) == pytest.approx(0.5, rel=1e-12)
    assert one(impl.iou_3d, a, taller, "first") == pytest.approx(1.0, rel=1e-12)
    # BEV ignores heights
    assert one(impl.iou_bev, a, box(y=-10.0, h=0.1, l=3.0, w=2.0)) == 1.0


def test_degenerate_boxes_are_zero_never_nan(impl):
    normal = box(z=10.0, l=4.0, h=1.5, w=1.7)
    flat = box(z=10.0, l=4.0, h=0.0, w=1.7)
    thin = box(z=10.0, l=0.0, h=1.5, w=1.7)
    point = box(z=10.0, l=0.0, h=0.0, w=0.0)
    negative_h = box(z=10.0, l=4.0, h=-1.0, w=1.7)
    for crit in ("union", "first"):
        for x, y in (
            (flat, flat),
            (flat, normal),
            (normal, flat),
            (point, point),
            (thin, thin),
            (thin, normal),
            (normal, negative_h),
            (negative_h, negative_h),
        ):
            v = one(impl.iou_3d, x, y, crit)
            assert v == 0.0, (x, y, crit)
        assert one(impl.iou_bev, flat, flat, crit) == pytest.approx(1, abs=1e-12)  # BEV has an area
        for x, y in ((thin, thin), (point, point), (thin, normal), (normal, point)):
            assert one(impl.iou_bev, x, y, crit) == 0.0
        zero_img = [[5.0, 5.0, 5.0, 5.0]]
        assert impl.iou_2d(zero_img, zero_img, crit)[0, 0] == 0.0
        assert impl.iou_2d(zero_img, [[0, 0, 10, 10]], crit)[0, 0] == 0.0


def test_dontcare_dimensions_use_absolute_sizes(impl):
    # a DontCare line carries l = h = w = -1: the BEV rectangle is 1 x 1, the volume is 0
    dc = box(x=2.0, y=1.0, z=10.0, l=-1.0, h=-1.0, w=-1.0, ry=-10.0)
    unit = box(x=2.0, y=1.0, z=10.0, l=1.0, h=1.0, w=1.0, ry=-10.0 + PI / 2)
    assert one(impl.iou_bev, unit, dc) == pytest.approx(1, abs=1e-12)
    assert one(impl.iou_bev, unit, dc, "first") == pytest.approx(1, abs=1e-12)
    assert one(impl.iou_3d, unit, dc) == 0.0
    assert one(impl.iou_3d, unit, dc, "first") == 0.0


def test_tiny_and_huge_boxes_near_the_origin(impl):
    for s in (1e-4, 1.0, 1e4):
        a = box(l=s, h=s, w=s, ry=0.0)
        b = box(x=s / 2, l=s, h=s, w=s, ry=0.0)
        assert one(impl.iou_bev, a, b) == pytest.approx(1 / 3, rel=1e-12)
        assert one(impl.iou_3d, a, b) == pytest.approx(1 / 3, rel=1e-12)
        turned = rigid(np.stack([a, b]), 0.8, (0.0, 0.0, 0.0))
        assert one(impl.iou_bev, *turned) == pytest.approx(1 / 3, rel=1e-9)


# ------------------------------------------------------------------------------ kernel-only precision


def test_kernel_identity_is_exact():
    rng = np.random.default_rng(4)
    boxes = random_boxes(rng, 300)
    assert np.all(np.diag(iou_bev(boxes, boxes)) == 1.0)
    assert np.all(np.diag(iou_bev(boxes, boxes, "first")) == 1.0)
    d3 = np.diag(iou_3d(boxes, boxes))
    assert d3 == pytest.approx(np.ones(len(boxes)), abs=1e-15)
    assert np.all(d3 <= 1.0)


def test_kernel_is_bitwise_symmetric_and_bounded():
    rng = np.random.default_rng(5)
    a = random_boxes(rng, 150)
    b = np.concatenate([jitter(rng, a), a])
    for fn in (iou_bev, iou_3d):
        ab, ba = fn(a, b), fn(b, a)
        assert np.array_equal(ab, ba.T)
        assert ab.min() >= 0.0 and ab.max() <= 1.0
        assert fn(a, b, "first").max() <= 1.0


def test_kernel_tiny_boxes_far_away_and_huge_boxes():
    tiny = 2.0**-20
    far = box(x=48.0, y=1.5, z=30.0, l=tiny, h=tiny, w=tiny, ry=0.7)
    assert one(iou_bev, far, far) == 1.0
    assert one(iou_3d, far, far) == pytest.approx(1, abs=1e-12)
    # exactly representable half-length offset along the length axis
    a = box(x=48.0, z=30.0, l=tiny, w=tiny)
    b = box(x=48.0 + tiny / 2, z=30.0, l=tiny, w=tiny)
    assert one(iou_bev, a, b) == pytest.approx(1 / 3, rel=1e-12)
    # a tiny box inside a big, turned one, 50 m away: the clip happens in the tiny box's frame
    big = box(x=48.0, y=2.0, z=30.0, l=4.0, h=2.0, w=2.0, ry=-0.4)
    assert one(iou_bev, far, big, "first") == 1.0
    assert one(iou_bev, far, big) == pytest.approx(tiny * tiny / 8.0, rel=1e-12)
    huge = box(x=1e5, z=-3e5, l=1e6, h=10.0, w=2e5, ry=2.5)
    assert one(iou_bev, huge, huge) == 1.0
    half = rigid(np.stack([box(l=1e6, w=2e5), box(x=5e5, l=1e6, w=2e5)]), 2.5, (1e5, 0.0, -3e5))
    assert one(iou_bev, *half) == pytest.approx(1 / 3, rel=1e-12)


# ----------------------------------------------------------------------------- kernel vs naive twins


def _pairs(rng, n):
    """Realistic pairs: mostly overlapping neighbours, some exact flips/translations, some far apart."""
    a = random_boxes(rng, n)
    b = jitter(rng, a)
    k = n // 10
    b[:k] = random_boxes(rng, k)  # mostly disjoint
    b[k : 2 * k] = a[k : 2 * k]
    b[k : 2 * k, 0] += rng.choice([-1, 1], k) * a[k : 2 * k, 3] * np.cos(a[k : 2 * k, 6]) / 2  # half along length
    b[k : 2 * k, 2] -= rng.choice([-1, 1], k) * a[k : 2 * k, 3] * np.sin(a[k : 2 * k, 6]) / 2
    return a, b


def test_kernel_matches_naive_on_random_pairs():
    rng = np.random.default_rng(6)
    a, b = _pairs(rng, 3000)
    for crit in ("union", "first"):
        for fast, slow in ((iou_bev, iou_bev_naive), (iou_3d, iou_3d_naive)):
            got = np.array([fast(a[i : i + 1], b[i : i + 1], crit)[0, 0] for i in range(len(a))])
            want = np.array([slow(a[i : i + 1], b[i : i + 1], crit)[0, 0] for i in range(len(a))])
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
            # the set covers real overlaps and misses
            assert (got > 0.3).sum() > 750 and (got == 0).sum() > 100


def test_kernel_matches_naive_matrix_and_2d_bitwise():
    rng = np.random.default_rng(7)
    a = random_boxes(rng, 12)
    b = np.concatenate([jitter(rng, a), random_boxes(rng, 5)])
    np.testing.assert_allclose(iou_bev(a, b), iou_bev_naive(a, b), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(iou_3d(b, a, "first"), iou_3d_naive(b, a, "first"), rtol=1e-9, atol=1e-12)
    x1 = rng.uniform(0, 1200, 300)
    y1 = rng.uniform(0, 370, 300)
    img = np.column_stack([x1, y1, x1 + rng.uniform(1, 300, 300), y1 + rng.uniform(1, 200, 300)])
    img[:100] = np.round(img[:100])  # integer pixel boxes, as in the label files
    for crit in ("union", "first"):
        assert np.array_equal(iou_2d(img, img[::-1], crit), iou_2d_naive(img, img[::-1], crit))


_coord = st.floats(-50, 50, allow_nan=False)
_size = st.one_of(st.just(0.0), st.floats(1e-3, 8.0))  # shapely drops slivers of area ~1e-270
_yaw = st.floats(-2 * PI, 2 * PI, allow_nan=False)
_box = st.tuples(_coord, st.floats(-3, 3), _coord, _size, _size, _size, _yaw)


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(a=_box, b=_box, near=st.booleans())
def test_kernel_matches_naive_property(a, b, near):
    a, b = np.array(a), np.array(b)
    if near:  # bring the centres within reach of each other
        b[[0, 1, 2]] = a[[0, 1, 2]] + (b[[0, 1, 2]] - a[[0, 1, 2]]) / 25
    for crit in ("union", "first"):
        got = one(iou_bev, a, b, crit)
        assert 0.0 <= got <= 1.0
        assert got == pytest.approx(one(iou_bev_naive, a, b, crit), rel=1e-9, abs=1e-11)
        got3 = one(iou_3d, a, b, crit)
        assert 0.0 <= got3 <= 1.0
        assert got3 == pytest.approx(one(iou_3d_naive, a, b, crit), rel=1e-9, abs=1e-11)


# -------------------------------------------------------------------------------------- frame_overlaps


def _frames(rng):
    counts = [(3, 2), (0, 4), (5, 0), (0, 0), (1, 1), (6, 5), (2, 3), (0, 0), (4, 7), (7, 1)]
    dt, gt = [], []
    for n_dt, n_gt in counts:
        g = random_boxes(rng, n_gt)
        g[:, 2] = rng.uniform(8, 14, n_gt)  # a crowded frame: many overlapping pairs
        g[:, 0] = rng.uniform(-3, 3, n_gt)
        d = jitter(rng, g[rng.integers(0, n_gt, n_dt)]) if n_gt else random_boxes(rng, n_dt)
        gt.append(g)
        dt.append(d)
    dt_boxes, gt_boxes = np.concatenate(dt), np.concatenate(gt)

    def image_boxes(n):
        x1 = rng.uniform(0, 300, n)
        y1 = rng.uniform(0, 100, n)
        return np.column_stack([x1, y1, x1 + rng.uniform(20, 200, n), y1 + rng.uniform(20, 100, n)])

    dt_offsets = np.concatenate([[0], np.cumsum([c[0] for c in counts])]).astype(np.int64)
    gt_offsets = np.concatenate([[0], np.cumsum([c[1] for c in counts])]).astype(np.int64)
    gt_first = rng.random(len(gt_boxes)) < 0.3
    gt_boxes[gt_first & (rng.random(len(gt_boxes)) < 0.3), 3:6] = -1.0  # DontCare-like dimensions
    dt_bbox, gt_bbox = image_boxes(len(dt_boxes)), image_boxes(len(gt_boxes))
    return dt_bbox, dt_boxes, dt_offsets, gt_bbox, gt_boxes, gt_offsets, gt_first


def test_frame_overlaps_matches_pairwise_per_frame():
    rng = np.random.default_rng(8)
    args = _frames(rng)
    dt_bbox, dt_boxes, dt_off, gt_bbox, gt_boxes, gt_off, gt_first = args
    copies = [np.copy(x) for x in args]
    res = frame_overlaps(*args)
    for x, c in zip(args, copies):  # inputs untouched
        assert np.array_equal(x, c)
    assert isinstance(res, FrameOverlaps)
    n_dt, n_gt = np.diff(dt_off), np.diff(gt_off)
    assert res.pair_offsets.dtype == np.int64
    assert np.array_equal(res.pair_offsets, np.concatenate([[0], np.cumsum(n_dt * n_gt)]))
    for arr in (res.bbox, res.bev, res.d3):
        assert arr.dtype == np.float64 and arr.shape == (res.pair_offsets[-1],)
    nonzero = 0
    for f in range(len(n_dt)):
        d = slice(dt_off[f], dt_off[f + 1])
        g = slice(gt_off[f], gt_off[f + 1])
        first = gt_first[g]
        block = slice(res.pair_offsets[f], res.pair_offsets[f + 1])
        for name, fn in (("bbox", iou_2d), ("bev", iou_bev), ("d3", iou_3d)):
            src_d = dt_bbox if name == "bbox" else dt_boxes
            src_g = gt_bbox if name == "bbox" else gt_boxes
            want = np.where(first[None, :], fn(src_d[d], src_g[g], "first"), fn(src_d[d], src_g[g], "union"))
            got = getattr(res, name)[block].reshape(n_dt[f], n_gt[f])
            np.testing.assert_array_equal(got, want, err_msg=f"{name} frame {f}")
            nonzero += int((got > 0).sum())
    assert nonzero > 40
    # the "first" criterion was really exercised: some DontCare-scored pairs differ from their IoU
    frames = range(len(n_dt))
    gt_of_pair = np.concatenate([np.tile(np.arange(gt_off[f], gt_off[f + 1]), n_dt[f]) for f in frames])
    dt_of_pair = np.concatenate([np.repeat(np.arange(dt_off[f], dt_off[f + 1]), n_gt[f]) for f in frames])
    scored_first = gt_first[gt_of_pair] & (res.bev > 0)
    iou = np.array([iou_bev(dt_boxes[j : j + 1], gt_boxes[i : i + 1])[0, 0] for j, i in zip(dt_of_pair, gt_of_pair)])
    assert scored_first.sum() >= 3
    assert (res.bev[scored_first] != iou[scored_first]).all()
    assert np.array_equal(res.bev[~gt_first[gt_of_pair]], iou[~gt_first[gt_of_pair]])


def test_frame_overlaps_dontcare_first_criterion_values():
    # one frame: a detection half inside a DontCare region (2D), and a 3D DontCare-scored box
    dt_bbox = np.array([[0.0, 0.0, 10.0, 10.0]])
    gt_bbox = np.array([[5.0, 0.0, 100.0, 10.0], [5.0, 0.0, 100.0, 10.0]])
    dt_boxes = np.array([box(y=1.0, h=1.0, l=2.0, w=2.0)])
    gt_boxes = np.array([box(x=1.0, y=1.0, h=1.0, l=2.0, w=8.0), box(x=1.0, y=1.0, h=1.0, l=2.0, w=8.0)])
    res = frame_overlaps(dt_bbox, dt_boxes, [0, 1], gt_bbox, gt_boxes, [0, 2], np.array([True, False]))
    assert res.bbox[0] == 0.5 and res.bbox[1] == 50 / 1000
    assert res.bev[0] == pytest.approx(0.5, rel=1e-12) and res.bev[1] == pytest.approx(2 / 18, rel=1e-12)
    assert res.d3[0] == pytest.approx(0.5, rel=1e-12) and res.d3[1] == pytest.approx(2 / 18, rel=1e-12)


def test_frame_overlaps_empty_inputs():
    e4, e7 = np.zeros((0, 4)), np.zeros((0, 7))
    res = frame_overlaps(e4, e7, [0, 0, 0], e4, e7, [0, 0, 0], np.zeros(0, bool))
    assert res.pair_offsets.tolist() == [0, 0, 0] and res.bbox.shape == res.bev.shape == res.d3.shape == (0,)
    res = frame_overlaps(e4, e7, [0], e4, e7, [0], np.zeros(0, bool))
    assert res.pair_offsets.tolist() == [0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.bbox = np.zeros(1)  # type: ignore[misc]


# ------------------------------------------------------------------------------------------- validation


@pytest.mark.parametrize("fn,width", [(iou_2d, 4), (iou_bev, 7), (iou_3d, 7)])
def test_pairwise_validation(fn, width):
    good = np.zeros((2, width))
    bad = np.zeros((3, width - 1))
    with pytest.raises(ValueError, match=rf"Expected `a` with shape \(N, {width}\), got \(3, {width - 1}\)"):
        fn(bad, good)
    with pytest.raises(ValueError, match=rf"Expected `b` with shape \(N, {width}\), got \({width},\)"):
        fn(good, np.zeros(width))
    with pytest.raises(ValueError, match="criterion"):
        fn(good, good, "intersection")
    with pytest.raises(ValueError, match="finite"):
        fn(good, np.full((1, width), np.nan))
    with pytest.raises(ValueError, match="numbers"):
        fn(good, np.array([["a"] * width]))
    assert fn(good, np.zeros((0, width))).shape == (2, 0)
    assert fn(np.zeros(0), good).shape == (0, 2)
    # lists, integers and non-contiguous views are fine
    assert fn([[0] * width], np.zeros((2, 2 * width))[:, ::2]).shape == (1, 2)


def test_frame_overlaps_validation():
    rng = np.random.default_rng(9)
    dt_bbox, dt_boxes, dt_off, gt_bbox, gt_boxes, gt_off, gt_first = _frames(rng)

    def call(**kw):
        args = dict(
            dt_bbox=dt_bbox,
            dt_boxes=dt_boxes,
            dt_offsets=dt_off,
            gt_bbox=gt_bbox,
            gt_boxes=gt_boxes,
            gt_offsets=gt_off,
            gt_first=gt_first,
        )
        args.update(kw)
        return frame_overlaps(**args)

    call()
    with pytest.raises(ValueError, match=r"Expected `dt_boxes` with shape \(N, 7\), got \(28, 6\)"):
        call(dt_boxes=dt_boxes[:, :6])
    with pytest.raises(ValueError, match=r"Expected `gt_bbox` with shape \(N, 4\)"):
        call(gt_bbox=gt_bbox[:, :3])
    with pytest.raises(ValueError, match="`dt_bbox` and `dt_boxes` with the same number of rows"):
        call(dt_bbox=dt_bbox[:-1])
    with pytest.raises(ValueError, match="`gt_bbox` and `gt_boxes` with the same number of rows"):
        call(gt_boxes=gt_boxes[:-1], gt_first=gt_first[:-1])
    with pytest.raises(ValueError, match="same shape"):
        call(dt_offsets=np.append(dt_off, dt_off[-1]))
    with pytest.raises(ValueError, match="start at 0"):
        call(gt_offsets=np.concatenate([[1], gt_off[1:]]))
    bad = dt_off.copy()
    bad[2], bad[3] = bad[3], bad[2]
    with pytest.raises(ValueError, match="non-decreasing"):
        call(dt_offsets=bad)
    with pytest.raises(ValueError, match=r"`dt_offsets` to end at the 28 rows"):
        call(dt_offsets=np.append(dt_off[:-1], 27))
    with pytest.raises(ValueError, match="integers"):
        call(gt_offsets=gt_off.astype(float))
    with pytest.raises(ValueError, match=r"Expected `gt_offsets` with shape \(F \+ 1,\)"):
        call(gt_offsets=gt_off[None, :])
    with pytest.raises(ValueError, match="boolean"):
        call(gt_first=gt_first.astype(int))
    with pytest.raises(ValueError, match=r"`gt_first` with shape \(23,\)"):
        call(gt_first=gt_first[:-1])
