"""Many results ranked by one value, and how sure the order is: the paired bootstrap over frames (the same
resamples for every result, :mod:`.bootstrap`) gives each result's value under each resample, and from
those its 95% interval, the ranks it takes in 95% of the resamples, and whether its lead over the next
result is more than the frames' noise. ``kitti-eval compare`` with several results prints it; a hosted
benchmark's leaderboard computes the same from the values it keeps per entry.

The value a table ranks by is a *key*: one value of the result (``Car/3d/moderate/R40/strict``) or the mean
of several, as a benchmark's ranking key is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.evaluation import Plan, Totals, plan_evaluation, result_from_counts
from ..core.frames import Annotations
from ..core.protocol import EvalConfig, Metric
from ..core.result import EvalResult, ValueKey
from ..errors import ConfigError
from .bootstrap import interval95, resampled_ap

__all__ = [
    "LEVEL",
    "interval95",
    "key_of",
    "resampled_key",
    "evaluate_resampled",
    "Standing",
    "standings",
    "rank_order",
    "Ranked",
    "Ranking",
    "render_ranking",
    "METHOD",
]

#: the level of every interval and rank range here
LEVEL = 0.95
#: how the bootstrap behind every interval here is named (the leaderboard's ``bootstrap.method`` too)
METHOD = "paired bootstrap over frames"
#: the percentiles of every interval (:func:`.bootstrap.interval95`'s) and of the ranks for a rank range
_PERCENTILES = (2.5, 97.5)
_RECALL_COLUMN = {"R11": 0, "R40": 1}


def key_of(doc: Any, keys: Sequence[ValueKey]) -> float | None:
    """The key of a result document: the mean of ``keys``' values (None when one of them is None)."""
    values = [k.read(doc) for k in keys]
    if not values or any(v is None for v in values):
        return None
    return sum(v for v in values if v is not None) / len(values)


def _key_jobs(plan: Plan, keys: Sequence[ValueKey]) -> list[tuple[int, int] | None]:
    """Per key: (the plan's job behind it, its column of :func:`resampled_ap`), None where it is not evaluated."""
    out: list[tuple[int, int] | None] = []
    for key in keys:
        if key.error:
            raise ConfigError(f"{key} is an error type, not an AP: a ranking key is an AP")
        metric = Metric.BBOX.value if key.metric == "aos" else key.metric
        found = [
            s
            for s in plan.slots
            if s.cls == key.cls
            and s.metric.value == metric
            and s.difficulty.label == key.difficulty
            and s.oset == key.oset
        ]
        if not found:
            classes = ", ".join(plan.config.classes)
            raise ConfigError(
                f"{key}: not in this evaluation (classes {classes}; sets {', '.join(plan.config.threshold_sets)})"
            )
        slot = found[0]
        if slot.job is None or (key.metric == "aos" and not slot.with_aos):
            out.append(None)
            continue
        out.append((slot.job, _RECALL_COLUMN[key.recall] + (2 if key.metric == "aos" else 0)))
    return out


def resampled_key(
    plan: Plan, keys: Sequence[ValueKey], weights: npt.ArrayLike, *, workers: int | None = None
) -> npt.NDArray[np.float64]:
    """(B,): the mean of ``keys`` under each row of frame ``weights`` (B, F) (:func:`.bootstrap.frame_weights`),
    NaN throughout when one of them is not evaluated. Only the matchings behind the keys are run, and each
    value is the one :func:`.bootstrap.resampled_values` gives for it."""
    w = np.asarray(weights)
    jobs = _key_jobs(plan, keys)
    if any(j is None for j in jobs):
        return np.full(w.shape[0], np.nan)
    needed = sorted({j[0] for j in jobs if j is not None})
    events = plan.events([plan.jobs[j] for j in needed], workers=workers)
    ap = {j: resampled_ap(ev, w) for j, ev in zip(needed, events)}
    total = np.zeros(w.shape[0])
    for job, column in (j for j in jobs if j is not None):
        total = total + ap[job][:, column]
    return total / len(keys)


def evaluate_resampled(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig | None,
    keys: Sequence[ValueKey],
    weights: npt.ArrayLike,
    *,
    workers: int | None = None,
) -> tuple[EvalResult, npt.NDArray[np.float64]]:
    """The result (as :func:`kitti_eval.evaluate` gives it) and its key under each resample, from one plan."""
    plan = plan_evaluation(gt, dt, config)
    result = result_from_counts(plan, plan.counts(workers=workers), Totals.of(plan))
    return result, resampled_key(plan, keys, weights, workers=workers)


@dataclass(frozen=True)
class Standing:
    """How sure one place of a ranked table is.

    interval : the 95% interval of its key over the resamples
    rank_range : (best, worst): the ranks it takes in the central 95% of the resamples (the 2.5th and 97.5th
        percentiles of its rank, ties ranked as the table ranks them)
    to_next : the 95% interval of its key minus the next one's, from the same resamples (paired)
    differs_from_next : whether ``to_next`` excludes 0
    """

    interval: tuple[float, float] | None
    rank_range: tuple[int, int] | None
    to_next: tuple[float, float] | None
    differs_from_next: bool | None


def standings(values: Sequence[npt.ArrayLike | None]) -> list[Standing]:
    """Each place of a ranked table from its key under each resample (the same resamples for every place).

    ``values``: in the table's order (best first, ties already in the order the table gives them), each
    place's (B,) resampled key, or None while it is not computed. Rank ranges need every place: while one
    is None, they are None for all. A place is compared with the next when both are there."""
    arrays = [None if v is None else np.asarray(v, dtype=np.float64) for v in values]
    lengths = {a.shape[0] for a in arrays if a is not None}
    if len(lengths) > 1:
        raise ValueError(f"every place needs the same resamples, got {sorted(lengths)}")
    ranges: list[tuple[int, int] | None] = [None] * len(arrays)
    complete = [a for a in arrays if a is not None and not np.isnan(a).any()]
    if arrays and len(complete) == len(arrays) and lengths and next(iter(lengths)) > 0:
        stacked = np.stack(complete)  # (N, B)
        order = np.argsort(-stacked, axis=0, kind="stable")  # ties: the table's order
        ranks = np.empty_like(order)
        np.put_along_axis(ranks, order, np.arange(1, len(arrays) + 1)[:, None], axis=0)
        best = np.percentile(ranks, _PERCENTILES[0], axis=1, method="lower")
        worst = np.percentile(ranks, _PERCENTILES[1], axis=1, method="higher")
        ranges = [(int(b), int(w)) for b, w in zip(best, worst)]
    diffs = [None if a is None or b is None else a - b for a, b in zip(arrays, [*arrays[1:], None])]
    out = []
    for interval, rank_range, to_next in zip(_intervals95(arrays), ranges, _intervals95(diffs)):
        out.append(
            Standing(
                interval=interval,
                rank_range=rank_range,
                to_next=to_next,
                differs_from_next=None if to_next is None else bool(to_next[0] > 0 or to_next[1] < 0),
            )
        )
    return out


def _intervals95(rows: Sequence[npt.NDArray[np.float64] | None]) -> list[tuple[float, float] | None]:
    """:func:`.bootstrap.interval95` of each row (None for None, an empty row or one with a NaN), in one call
    of numpy: the same interpolation, row by row, so the same numbers."""
    usable = [i for i, r in enumerate(rows) if r is not None and r.size and not np.isnan(r).any()]
    out: list[tuple[float, float] | None] = [None] * len(rows)
    if usable:
        low, high = np.percentile(np.stack([np.asarray(rows[i]) for i in usable]), _PERCENTILES, axis=1)
        for i, lo, hi in zip(usable, low, high):
            out[i] = (float(lo), float(hi))
    return out


def rank_order(points: Sequence[float | None]) -> list[int]:
    """Indices of ``points`` best first (the highest value), ties and Nones in their given order, Nones last."""
    return sorted(range(len(points)), key=lambda i: (points[i] is None, -(points[i] or 0.0)))


@dataclass(frozen=True)
class Ranked:
    """One result of a ranked table: its name, its key, and its key under each resample (None without a
    bootstrap)."""

    name: str
    key: float | None
    values: npt.NDArray[np.float64] | None = None


@dataclass(frozen=True)
class Ranking:
    """Results ranked by a key (best first, ties in the order given, those without a key last), with their
    standings when they were resampled (``resamples`` > 0, the same draws for every result)."""

    keys: tuple[ValueKey, ...]
    results: tuple[Ranked, ...]
    resamples: int = 0
    seed: int | None = None

    def rows(self) -> list[tuple[int, Ranked, Standing | None]]:
        """(rank, result, standing) best first; the standing is None without a bootstrap or a key."""
        order = rank_order([r.key for r in self.results])
        ranked = [self.results[i] for i in order]
        keyed = [r for r in ranked if r.key is not None]
        places: list[Standing | None] = [None] * len(ranked)
        if self.resamples:
            places[: len(keyed)] = standings([r.values for r in keyed])
        return [(i + 1, r, s) for i, (r, s) in enumerate(zip(ranked, places))]

    def to_dict(self) -> dict[str, Any]:
        """The JSON: the key's columns, the bootstrap (None without one) and the results, best first, with the
        names the hosted leaderboard uses (``key``, ``interval``, ``rank_range``, ``differs_from_next``)."""
        return {
            "schema_version": 1,
            "key": [str(k) for k in self.keys],
            "bootstrap": {"method": METHOD, "resamples": self.resamples, "seed": self.seed, "level": LEVEL}
            if self.resamples
            else None,
            "results": [
                {
                    "rank": rank,
                    "result": r.name,
                    "key": r.key,
                    "interval": list(s.interval) if s and s.interval else None,
                    "rank_range": list(s.rank_range) if s and s.rank_range else None,
                    "differs_from_next": s.differs_from_next if s else None,
                    "difference_to_next": list(s.to_next) if s and s.to_next else None,
                }
                for rank, r, s in self.rows()
            ],
        }


def render_ranking(ranking: Ranking, fmt: str = "table") -> str:
    """The ranked table as text, Markdown or JSON (``kitti-eval compare`` with several results)."""
    import json

    if fmt == "json":
        return json.dumps(ranking.to_dict(), indent=2, allow_nan=False) + "\n"
    key_name = str(ranking.keys[0]) if len(ranking.keys) == 1 else "key"
    legend = "" if len(ranking.keys) == 1 else "key: the mean of " + ", ".join(map(str, ranking.keys))
    booted = bool(ranking.resamples)

    def num(v: float | None) -> str:
        return "-" if v is None else f"{round(v, 4) + 0.0:.4f}"

    def interval(s: Standing | None) -> str:
        return "-" if s is None or s.interval is None else f"[{num(s.interval[0])}, {num(s.interval[1])}]"

    def ranks(s: Standing | None) -> str:
        if s is None or s.rank_range is None:
            return "-"
        best, worst = s.rank_range
        return str(best) if best == worst else f"{best}-{worst}"

    def lead(s: Standing | None) -> str:
        return "*" if s is not None and s.differs_from_next else ""

    rows = ranking.rows()
    note = (
        f"{ranking.resamples} resamples ({METHOD}, seed {ranking.seed}), the same for every result; ranks: those "
        "a result takes in 95% of the resamples; * : its lead over the next is significant (the 95% interval of "
        "the difference excludes 0)"
    )
    if fmt == "markdown":
        head = ["rank", "result", f"`{key_name}`"] + (["95% interval", "ranks", "lead"] if booted else [])
        lines = ["| " + " | ".join(head) + " |", "|---:|---|---:|" + ("---|---|:---:|" if booted else "")]
        for rank, r, s in rows:
            cells = [str(rank), f"`{r.name}`", num(r.key)] + ([interval(s), ranks(s), lead(s)] if booted else [])
            lines.append("| " + " | ".join(cells) + " |")
        notes = [n for n in (legend, note if booted else "") if n]
        return "\n".join(lines) + "\n" + "".join(f"\n{n}.\n" for n in notes)
    table = [["rank", "result", key_name] + (["95% interval", "ranks", "lead"] if booted else [])]
    for rank, r, s in rows:
        table.append([str(rank), r.name, num(r.key)] + ([interval(s), ranks(s), lead(s)] if booted else []))
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    right = {0, 2}
    lines = [
        "  ".join(c.rjust(widths[i]) if i in right else c.ljust(widths[i]) for i, c in enumerate(row)).rstrip()
        for row in table
    ]
    return "\n".join(lines) + "\n" + "".join(f"{n}\n" for n in (legend, note if booted else "") if n)
