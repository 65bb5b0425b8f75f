"""Geometry for the inline SVG charts of the web pages: precision-recall curves, bird's-eye views and the bar
charts of the error decomposition.

Pure functions from numbers to screen coordinates; the templates draw the shapes. Screen coordinates
have their origin at the top left corner and grow to the right and down, as SVG's do.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "Plot",
    "PRChart",
    "pr_chart",
    "bev_corners",
    "BevBox",
    "BevView",
    "bev_view",
    "points_attr",
    "Bar",
    "BarGroup",
    "BarChart",
    "bar_chart",
    "points_text",
]

Point = tuple[float, float]


def points_attr(points: Sequence[Point]) -> str:
    """The ``points`` attribute of a ``<polyline>``/``<polygon>``: ``"x,y x,y ..."`` to 0.01 px."""
    return " ".join(f"{x:.2f},{y:.2f}" for x, y in points)


# ------------------------------------------------------------------------------------- precision-recall


@dataclass(frozen=True)
class Plot:
    """A ``width`` × ``height`` SVG whose chart area (axes 0..1 on both sides) leaves the given margins."""

    width: int = 240
    height: int = 190
    left: int = 34
    right: int = 8
    top: int = 8
    bottom: int = 28

    @property
    def x0(self) -> float:
        return float(self.left)

    @property
    def x1(self) -> float:
        return float(self.width - self.right)

    @property
    def y0(self) -> float:
        """Screen y of value 0 (the bottom of the chart area)."""
        return float(self.height - self.bottom)

    @property
    def y1(self) -> float:
        """Screen y of value 1 (the top of the chart area)."""
        return float(self.top)

    def point(self, recall: float, precision: float) -> Point:
        """Screen position of (recall, precision): (0, 0) is the bottom-left corner, (1, 1) the top-right."""
        return (self.x0 + recall * (self.x1 - self.x0), self.y0 - precision * (self.y0 - self.y1))


@dataclass(frozen=True)
class PRLine:
    difficulty: str
    points: str  # the polyline's ``points`` attribute
    count: int
    ap: float | None  # R40 AP (percent) for the legend


@dataclass(frozen=True)
class PRChart:
    plot: Plot
    lines: list[PRLine]
    ticks: list[tuple[str, float, float]] = field(default_factory=list)  # (label, screen x, screen y) per 0.2


def sample_recalls(n: int) -> list[float]:
    """The recall positions of the devkit's ``n`` sample points: ``0, 1/(n-1), ..., 1``."""
    return [i / (n - 1) for i in range(n)] if n > 1 else [0.0] * n


def pr_chart(
    curves: Mapping[str, Mapping[str, Sequence[float]]],
    ap: Mapping[str, float | None] | None = None,
    plot: Plot | None = None,
) -> PRChart:
    """The precision-recall lines of one class and metric, one per difficulty.

    Parameters
    ----------
    curves : ``{difficulty: {"precision": [...], ...}}`` as the JSON document's ``curves[set][class][metric]``;
        the i-th of the n precision values is the devkit's sampled point at recall ``i / (n - 1)`` (41 points:
        what R40 averages), so that is where it is drawn. The document's ``recall`` list is the envelope of
        the recall reached at each threshold, not an axis.
    ap : R40 AP per difficulty, shown in the legend
    plot : the chart's size; the default is :class:`Plot` ()
    """
    plot = plot or Plot()
    lines = []
    for difficulty, curve in curves.items():
        precision = [float(p) for p in curve["precision"]]
        xs = sample_recalls(len(precision))
        lines.append(
            PRLine(
                difficulty,
                points_attr([plot.point(r, p) for r, p in zip(xs, precision)]),
                len(precision),
                (ap or {}).get(difficulty),
            )
        )
    ticks = [(f"{v:.1f}", *plot.point(v, v)) for v in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)]
    return PRChart(plot, lines, ticks)


# ------------------------------------------------------------------------------------------ bird's eye


def bev_corners(location: Sequence[float], dimensions: Sequence[float], rotation_y: float) -> list[Point]:
    """Ground-plane corners ``(x, z)`` of a camera-frame box, in order around the box.

    Parameters
    ----------
    location : (x, y, z) in the camera frame: x right, y down, z forward (y is not used)
    dimensions : (l, h, w): length along the heading, height, width
    rotation_y : yaw about the camera's y axis; 0 points the length along +x

    A corner at offsets ``a = ±l/2`` (along the length) and ``b = ±w/2`` (across) lies at
    ``(x + a cos r + b sin r, z - a sin r + b cos r)``. The first corner is front-left (a = +l/2, b = +w/2),
    then front-right, back-right, back-left.
    """
    x, _, z = (float(v) for v in location)
    length, _, width = (float(v) for v in dimensions)
    cos_r, sin_r = math.cos(rotation_y), math.sin(rotation_y)
    return [
        (x + a * cos_r + b * sin_r, z - a * sin_r + b * cos_r)
        for a, b in (
            (length / 2, width / 2),
            (length / 2, -width / 2),
            (-length / 2, -width / 2),
            (-length / 2, width / 2),
        )
    ]


@dataclass(frozen=True)
class BevBox:
    kind: str  # "gt" or a detection label (tp, fp, ignored, ...)
    points: str  # the polygon's ``points`` attribute
    heading: tuple[Point, Point]  # from the centre to the middle of the front edge
    title: str


@dataclass(frozen=True)
class BevView:
    width: int
    height: int
    boxes: list[BevBox]
    grid: list[tuple[str, float, float, float, float]]  # (label, x1, y1, x2, y2) every ``step`` metres
    step: float
    origin: Point  # the camera, on screen


@dataclass(frozen=True)
class _Frame:
    """Ground plane (x, z) → screen: x to the right, z up, one scale for both axes."""

    xmin: float
    zmin: float
    scale: float
    height: int
    pad: float

    def __call__(self, p: Point) -> Point:
        return (self.pad + (p[0] - self.xmin) * self.scale, self.height - self.pad - (p[1] - self.zmin) * self.scale)


def _fit(corners: Sequence[Point], width: int, height: int, pad: float, margin_m: float) -> _Frame:
    xs = [p[0] for p in corners] + [0.0]  # the camera is always in view
    zs = [p[1] for p in corners] + [0.0]
    xmin, xmax = min(xs) - margin_m, max(xs) + margin_m
    zmin, zmax = min(zs) - margin_m, max(zs) + margin_m
    scale = min((width - 2 * pad) / (xmax - xmin), (height - 2 * pad) / (zmax - zmin))
    # centre the content along the axis with room to spare
    xmin -= ((width - 2 * pad) / scale - (xmax - xmin)) / 2
    zmin -= ((height - 2 * pad) / scale - (zmax - zmin)) / 2
    return _Frame(xmin, zmin, scale, height, pad)


def _has_box(row: Mapping[str, Any]) -> bool:
    """Rows without a 3D box (DontCare regions: dimensions -1, location -1000) are not drawn."""
    dims, loc = row.get("dimensions"), row.get("location")
    return dims is not None and loc is not None and all(float(d) > 0 for d in dims)


def _grid_step(span: float) -> float:
    """Metres between grid lines: 5, 10, 20, 50, ... so that about ten lines cross the view."""
    for step in (5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0):
        if span / step <= 12:
            return step
    return 10.0 ** math.ceil(math.log10(span / 10))


def bev_view(
    ground_truth: Sequence[Mapping[str, Any]],
    detections: Sequence[Mapping[str, Any]],
    *,
    missed: Collection[int] = (),
    extent: Sequence[Mapping[str, Any]] = (),
    width: int = 360,
    height: int = 360,
) -> BevView:
    """Ground truth (kind ``gt``, or ``gt missed``) and detections (kind = their ``label``) seen from above,
    z up, x right.

    Parameters
    ----------
    ground_truth, detections : rows with ``location``, ``dimensions`` (l, h, w), ``rotation_y`` and ``index``
        (detections also ``label`` and ``score``); rows without a 3D box (DontCare) are skipped
    missed : indices of the ground truth the detections missed
    extent : more rows that only widen the view (the other evaluations' detections, so that several views
        of one frame share a scale)
    """

    def corners(row: Mapping[str, Any]) -> list[Point]:
        return bev_corners(row["location"], row["dimensions"], float(row["rotation_y"]))

    placed = [r for r in ground_truth if _has_box(r)]
    found = [r for r in detections if _has_box(r)]
    everything = [c for r in (*placed, *found, *(r for r in extent if _has_box(r))) for c in corners(r)]
    frame = _fit(everything, width, height, pad=6.0, margin_m=2.0)

    def box(row: Mapping[str, Any], kind: str, title: str) -> BevBox:
        cs = corners(row)
        x, _, z = row["location"]
        front = ((cs[0][0] + cs[1][0]) / 2, (cs[0][1] + cs[1][1]) / 2)
        return BevBox(kind, points_attr([frame(c) for c in cs]), (frame((float(x), float(z))), frame(front)), title)

    boxes = [
        box(
            r,
            "gt missed" if r["index"] in missed else "gt",
            f"GT {r['index']} {r.get('name', '')}{' (missed)' if r['index'] in missed else ''}",
        )
        for r in placed
    ]
    boxes += [
        box(
            r,
            str(r.get("label", "")),
            f"detection {r['index']} {r.get('name', '')} {r.get('label', '')} score {float(r['score']):.3f}",
        )
        for r in found
    ]
    left, bottom = frame.xmin, frame.zmin
    right, top = left + (width - 2 * frame.pad) / frame.scale, bottom + (height - 2 * frame.pad) / frame.scale
    step = _grid_step(max(right - left, top - bottom))
    grid = []
    for v in range(math.ceil(left / step), math.floor(right / step) + 1):
        (sx, sy0), (_, sy1) = frame((v * step, bottom)), frame((v * step, top))
        grid.append((f"x {v * step:g}", sx, sy0, sx, sy1))
    for v in range(math.ceil(bottom / step), math.floor(top / step) + 1):
        (sx0, sy), (sx1, _) = frame((left, v * step)), frame((right, v * step))
        grid.append((f"z {v * step:g}", sx0, sy, sx1, sy))
    return BevView(width, height, boxes, grid, step, frame((0.0, 0.0)))


# ------------------------------------------------------------------------------------------------- bars


def points_text(value: float | None, digits: int = 2) -> str:
    """A number as the CLI's error table prints it (``kitti-eval errors``): ``digits`` decimals, ``-`` for
    none, and never ``-0.00``."""
    if value is None:
        return "-"
    text = f"{value:.{digits}f}"
    return text[1:] if text == f"-{0:.{digits}f}" else text


@dataclass(frozen=True)
class Bar:
    kind: str
    value: float | None
    x: float  # the rectangle: left edge, width (0 without a value), top, height
    width: float
    y: float
    height: float
    text: str  # the value as printed, at ``text_x`` on the bar's ``baseline``
    text_x: float
    baseline: float


@dataclass(frozen=True)
class BarGroup:
    name: str
    y: float  # the heading's baseline
    bars: list[Bar]


@dataclass(frozen=True)
class BarChart:
    width: int
    height: int
    left: float  # the bars' area: screen x of the axis' ends, top and bottom
    right: float
    top: float
    bottom: float
    x0: float  # screen x of the value 0
    groups: list[BarGroup]
    ticks: list[tuple[str, float]]  # (label, screen x)


_LABEL_W = 86  # the column of the bars' labels
_VALUE_W = 38  # room for the value right of the longest bar
_ROW = 13  # one bar's row
_BAR = 9
_HEAD = 15  # a group's heading
_TOP = 4
_AXIS = 28  # below the bars: the ticks' labels and the axis' name


def _nice_step(span: float) -> float:
    """A step of 1, 2, 2.5 or 5 times a power of ten giving at most five intervals over ``span`` (> 0)."""
    power = 10.0 ** math.floor(math.log10(span / 5))
    return next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if span / (m * power) <= 5 + 1e-9)


def bar_chart(
    groups: Mapping[str, Mapping[str, float | None]],
    *,
    lo: float = 0.0,
    hi: float | None = None,
    width: int = 340,
) -> BarChart:
    """Horizontal bars, in groups, on one axis from 0.

    Parameters
    ----------
    groups : ``{group: {kind: value}}`` in the order they are drawn (None: no bar, the value shows ``-``)
    lo, hi : the range the axis must cover besides 0 and the values (several charts on one scale pass the
        extremes of them all); the axis ends at multiples of its tick step
    width : the chart's width; its height follows from the number of bars
    """
    values = [v for kinds in groups.values() for v in kinds.values() if v is not None]
    low = min(0.0, lo, *values)
    high = max(0.0, hi or 0.0, *values)
    if high - low <= 0:
        high = low + 1.0
    step = _nice_step(high - low)
    low, high = math.floor(low / step + 1e-9) * step, math.ceil(high / step - 1e-9) * step
    left, right = float(_LABEL_W), float(width - _VALUE_W)

    def x(value: float) -> float:
        return left + (value - low) / (high - low) * (right - left)

    x0 = x(0.0)
    out, y = [], float(_TOP)
    for name, kinds in groups.items():
        head = y + _HEAD - 4
        y += _HEAD
        bars = []
        for kind, value in kinds.items():
            top = y + (_ROW - _BAR) / 2
            if value is None:
                start, length = x0, 0.0
            else:
                start, end = sorted((x0, x(value)))
                length = end - start
            bars.append(
                Bar(
                    kind,
                    value,
                    start,
                    length,
                    top,
                    float(_BAR),
                    points_text(value),
                    max(x0, start + length) + 3,
                    top + _BAR - 1,
                )
            )
            y += _ROW
        out.append(BarGroup(name, head, bars))
    n_ticks = round((high - low) / step)
    ticks = [(f"{low + i * step:g}", x(low + i * step)) for i in range(n_ticks + 1)]
    return BarChart(width, math.ceil(y + _AXIS), left, right, float(_TOP), y, x0, out, ticks)
