"""A benchmark's rules, which its record (:class:`.benchmark.Benchmark`) and its settings use: the board's key
and columns, the public/private split of the test frames, and the parsing of its options (quota, columns, times)."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from typing import Any

from kitti_eval.core.protocol import DEFAULT_OSET, DEFAULT_RECALL, DIFFICULTIES, METRICS, RECALL_MODES
from kitti_eval.core.result import ValueKey

from ..errors import BadRequest, echo

__all__ = [
    "DEFAULT_KEY",
    "PHASE_SEPARATOR",
    "MAIN_PHASE",
    "DIFFICULTIES",
    "parse_quota",
    "check_quota",
    "check_split_percent",
    "check_max_published",
    "check_texts",
    "MAX_PUBLISHED",
    "quota_words",
    "parse_column",
    "parse_time",
    "in_public_part",
    "part_frames",
    "key_value",
    "scores_of",
]

DEFAULT_KEY = "Car/3d/moderate/R40/strict"
#: a later phase of a benchmark is stored as a benchmark named ``NAME~PHASE`` (a name no one can give: ``~`` is
#: not in a benchmark's name); a benchmark's first phase is the benchmark's own row
PHASE_SEPARATOR = "~"
#: the phase of a benchmark made with ``benchmark add`` (one phase)
MAIN_PHASE = "main"
#: the recall modes as a column's help names them, the default first
_RECALLS = tuple(reversed(RECALL_MODES))


#: the most published entries a participant may be capped at
MAX_PUBLISHED = 1000
#: the longest title and description of a benchmark
MAX_TITLE, MAX_DESCRIPTION = 200, 20000


def check_split_percent(value: float | None) -> float | None:
    """A phase's public part of its test frames, in percent (None: no split): more than 0, less than 100."""
    if value is not None and not 0 < value < 100:
        raise BadRequest("split_percent is the public part of the test frames: more than 0, less than 100")
    return None if value is None else float(value)


def check_max_published(value: int | None) -> int | None:
    """A phase's cap on the entries a participant has published (None: no cap)."""
    if value is not None and not 1 <= value <= MAX_PUBLISHED:
        raise BadRequest(f"max_published is 1 to {MAX_PUBLISHED} published entries a participant (or none)")
    return value


def check_texts(title: str, description: str) -> None:
    """A benchmark's title and description fit."""
    if len(description) > MAX_DESCRIPTION or len(title) > MAX_TITLE:
        raise BadRequest(f"a title is at most {MAX_TITLE} characters, a description at most {MAX_DESCRIPTION}")


def quota_words(count: int, days: float, what: str = "submission") -> str:
    """A quota as it is said: ``1 submission per day``, ``3 submissions per 2 days``."""
    return f"{count} {what}{'s' if count != 1 else ''} per {'day' if days == 1 else f'{days:g} days'}"


def parse_quota(text: str) -> tuple[int, float]:
    """``N/DAYS`` (e.g. ``3/1``: three accepted submissions a participant per day)."""
    n, sep, days = text.partition("/")
    try:
        count, span = int(n), float(days) if sep else 1.0
    except ValueError:
        raise BadRequest(f"a quota is N/DAYS, e.g. 3/1; got {echo(text)}") from None
    return check_quota(count, span)


def check_quota(count: int, days: float) -> tuple[int, float]:
    """A quota's range: 1 to 100000 submissions per more than 0 and at most 3650 days."""
    if not 1 <= count <= 100_000 or not math.isfinite(days) or not 0 < days <= 3650:
        raise BadRequest("a quota is 1 to 100000 submissions per more than 0 and at most 3650 days")
    return int(count), float(days)


def parse_column(text: str, classes: Sequence[str], sets: Sequence[str]) -> str:
    """``CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]]`` normalised to its five parts."""
    parts = text.strip().split("/")
    if not 3 <= len(parts) <= 5:
        raise BadRequest(f"a column is CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]], e.g. {DEFAULT_KEY}; got {echo(text)}")
    parts += [DEFAULT_RECALL, sets[0] if DEFAULT_OSET not in sets else DEFAULT_OSET][len(parts) - 3 :]
    cls, metric, difficulty, recall, oset = parts
    known = {c.lower(): c for c in classes}
    if cls.lower() not in known:
        raise BadRequest(f"column {echo(text)}: the class is one of {', '.join(classes)}")
    if metric not in METRICS or difficulty not in DIFFICULTIES or recall not in _RECALLS or oset not in sets:
        raise BadRequest(
            f"column {echo(text)}: metric {'/'.join(METRICS)}, difficulty {'/'.join(DIFFICULTIES)}, "
            f"recall {'/'.join(_RECALLS)}, set {'/'.join(sets)}"
        )
    return str(ValueKey(known[cls.lower()], metric, difficulty, recall, oset))


def in_public_part(seed: str, frame_id: str, percent: float) -> bool:
    digest = hashlib.sha256(f"{seed}:{frame_id}".encode()).digest()
    return int.from_bytes(digest[:8], "big") < percent / 100 * 2**64


def part_frames(seed: str | None, frame_ids: Sequence[str], percent: float | None) -> dict[str, list[str]]:
    """The frames of each part a board may rank on, in the test set's order: ``public`` and ``private`` with a
    split (``percent`` and its ``seed``), else ``all``."""
    if percent is None or not seed:
        return {"all": list(frame_ids)}
    parts: dict[str, list[str]] = {"public": [], "private": []}
    for f in frame_ids:
        parts["public" if in_public_part(seed, f, percent) else "private"].append(f)
    return parts


def parse_time(value: str | datetime | None, what: str) -> datetime | None:
    if value is None or value == "":
        return None
    if isinstance(value, datetime):
        moment = value
    else:
        try:
            moment = datetime.fromisoformat(value.strip().replace("Z", "+00:00"))
        except ValueError:
            raise BadRequest(f"{what}: an ISO 8601 time, e.g. 2026-12-31T23:59:00+00:00; got {echo(value)}") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


def key_value(scores: Mapping[str, float | None], key: Sequence[str]) -> float | None:
    values = [scores.get(c) for c in key]
    if any(v is None for v in values):
        return None
    return round(sum(v for v in values if v is not None) / len(values), 4)


def scores_of(doc: Mapping[str, Any], columns: Sequence[str]) -> dict[str, float | None]:
    """The AP of each column in an evaluation document, rounded to 4 places."""
    out: dict[str, float | None] = {}
    for column in columns:
        value = ValueKey(*column.split("/")).find(doc)
        out[column] = None if value is None else round(value, 4)
    return out
