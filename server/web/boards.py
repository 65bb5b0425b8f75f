"""What the benchmark pages show of a board and a submission, read from the JSON the API serves: the columns'
grouped header (class, metric, difficulty; the recall mode and IoU set said once when they are common), the
entries with their intervals, rank ranges and the marks between neighbours that no test tells apart, and a
submission's state and its comparison with the participant's previous best and the leader.

The intervals, rank ranges and comparisons are optional in the documents: a key that is absent shows
nothing, a key whose value is still ``None`` shows "computing".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime
from typing import Any

__all__ = [
    "METRIC_NAMES",
    "board_header",
    "board_entries",
    "bootstrap_line",
    "column_label",
    "comparison_rows",
    "number",
    "interval_text",
    "short_date",
]

METRIC_NAMES = {"bbox": "2D", "bev": "BEV", "3d": "3D", "aos": "AOS"}
_SETS = {"strict": "strict IoU", "loose": "loose IoU"}
COMPUTING = "computing"


def number(value: float | None) -> str:
    """An AP on a board: two decimals (the intervals show what the decimals after them are worth)."""
    return "-" if value is None else f"{value:.2f}"


def signed_number(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f}".replace("-", "−")


def interval_text(interval: Sequence[float] | None) -> str:
    """``[77.90, 78.70]``; "computing" for None."""
    if interval is None:
        return COMPUTING
    low, high = interval
    return f"[{low:.2f}, {high:.2f}]".replace("-", "−")


def short_date(iso: str) -> str:
    """The day of an ISO time (the full time goes in a title)."""
    return iso[:10]


def full_time(iso: str) -> str:
    """An ISO time as a reader reads it: ``2026-05-01 14:03:22 UTC``."""
    try:
        moment = datetime.fromisoformat(iso)
    except ValueError:
        return iso
    zone = "UTC" if moment.utcoffset() is not None and not moment.utcoffset() else (moment.tzname() or "")
    return f"{moment:%Y-%m-%d %H:%M:%S} {zone}".strip()


def _tail(recall: str, oset: str) -> str:
    return f"{recall}, {_SETS.get(oset, oset)}"


def column_label(column: str, *, common: str | None = None) -> str:
    """``Car/3d/moderate/R40/strict`` as ``Car 3D moderate`` (with ``R40, strict IoU`` unless it is the
    board's common one)."""
    cls, metric, difficulty, recall, oset = column.split("/")
    label = f"{cls} {METRIC_NAMES.get(metric, metric)} {difficulty}"
    tail = _tail(recall, oset)
    return label if tail == common else f"{label} ({tail})"


def board_header(columns: Sequence[str]) -> dict[str, Any]:
    """The columns' header in three rows: classes (each spanning its columns), metrics, then difficulties;
    neighbours of one class (and metric) share a cell. ``common``: the recall mode and IoU set of every
    column, said once, or None (then each difficulty cell names its own)."""
    parts = [c.split("/") for c in columns]
    tails = {_tail(p[3], p[4]) for p in parts}
    common = tails.pop() if len(tails) == 1 else None
    classes: list[dict[str, Any]] = []
    metrics: list[dict[str, Any]] = []
    cells: list[dict[str, Any]] = []
    for column, (cls, metric, difficulty, recall, oset) in zip(columns, parts):
        if classes and classes[-1]["name"] == cls:
            classes[-1]["span"] += 1
        else:
            classes.append({"name": cls, "span": 1})
        if metrics and metrics[-1]["key"] == (cls, metric) and classes[-1]["span"] > 1:
            metrics[-1]["span"] += 1
        else:
            metrics.append({"key": (cls, metric), "name": METRIC_NAMES.get(metric, metric), "span": 1})
        tail = _tail(recall, oset)
        cells.append(
            {
                "column": column,
                "metric": metric,
                "label": difficulty if common is not None else f"{difficulty} ({tail})",
                "title": column_label(column),
            }
        )
    return {"classes": classes, "metrics": metrics, "cells": cells, "common": common}


def _rank_range(entry: Mapping[str, Any]) -> str | None:
    """``1–3`` (or ``2`` when it is one rank other than the entry's); "computing"; None when the board has no
    rank ranges, or when the range is the entry's own rank alone (a lone ``1`` under rank 1 says nothing)."""
    if "rank_range" not in entry:
        return None
    value = entry["rank_range"]
    if value is None:
        return COMPUTING
    best, worst = value
    if best == worst:
        return None if best == entry.get("rank") else str(best)
    return f"{best}–{worst}"


def board_entries(board: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The board's entries as the page shows them. ``tie``: the difference to the next entry is not
    significant (marked only in the key's order, where "next" is the neighbour below)."""
    in_key_order = (board.get("sort"), board.get("order")) in (("key", "desc"), ("rank", "asc"))
    out = []
    for entry in board["entries"]:
        interval = None
        if "interval" in entry:
            interval = interval_text(entry["interval"])
        out.append(
            {
                "entry": entry,
                "baseline": bool(entry.get("baseline")),
                "rank": "" if entry.get("rank") is None else str(entry["rank"]),
                "rank_range": None if entry.get("baseline") else _rank_range(entry),
                "key": number(entry.get("key")),
                "interval": interval,
                "tie": in_key_order and entry.get("differs_from_next") is False,
                "date": short_date(entry["date"]),
                "time": full_time(entry["date"]),
            }
        )
    return out


def bootstrap_line(board: Mapping[str, Any]) -> str | None:
    """The sentence that says how the intervals were drawn (None when the board has none)."""
    boot = board.get("bootstrap")
    if not isinstance(boot, Mapping):
        return None
    level = boot.get("level")
    shown = ""
    if isinstance(level, (int, float)) and not isinstance(level, bool):
        shown = f" ({level * 100 if level <= 1 else level:g} %)"
    part = boot.get("part")
    where = f", on the {part} part of the test frames" if part in ("public", "private") else ""
    text = (
        f"Intervals{shown}: {boot.get('method') or 'bootstrap'}, {boot.get('resamples')} resamples, "
        f"seed {boot.get('seed')}{where}."
    )
    pending = boot.get("pending")
    if pending:
        if isinstance(pending, int) and not isinstance(pending, bool):
            text += f" Still computing those of {pending} {'entry' if pending == 1 else 'entries'}."
        else:
            text += " Some are still being computed."
    return text


def comparison_rows(comparison: Mapping[str, Any] | None, own_id: str | None = None) -> list[dict[str, Any]] | None:
    """A submission's ``comparison`` as the page's rows: against the participant's previous best and against
    the leader, each the difference of the key with its interval and whether it is told apart from zero. When
    the leader is the submission ``own_id`` itself, its row says so instead of comparing it with itself."""
    if comparison is None:
        return None
    rows: list[dict[str, Any]] = []
    for name, label, none in (
        ("previous_best", "your previous best", "no earlier scored submission of yours to compare with"),
        ("leader", "the board's leader", "no entry on the board to compare with"),
    ):
        found = comparison.get(name)
        if found is None:
            rows.append({"name": name, "label": label, "none": none})
            continue
        if name == "leader" and own_id is not None and found.get("id") == own_id:
            rows.append({"name": name, "label": label, "none": None, "lead": "you lead the board", "id": own_id})
            continue
        interval = found.get("interval")
        difference = found.get("difference")
        if interval is None:
            verdict = COMPUTING
        elif interval[0] > 0 or interval[1] < 0:
            verdict = "a real difference: the interval leaves out 0"
        else:
            verdict = "within the noise: the interval holds 0"
        row: dict[str, Any] = {
            "name": name,
            "label": label,
            "id": found.get("id"),
            "difference": COMPUTING if difference is None else signed_number(difference),
            "interval": interval_text(interval),
            "verdict": verdict,
            "none": None,
            "lead": None,
        }
        rows.append(row)
    return rows
