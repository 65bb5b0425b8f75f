"""A benchmark's leaderboard: its published, scored entries ranked by the key on the scores of the board's
phase (the whole test set, its public part, or its private part once revealed), as JSON or CSV."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from typing import Any

from ..errors import BadRequest
from ..policy import Caller
from .catalog import BenchmarkCatalog
from .rules import key_value

__all__ = ["Leaderboard"]


class Leaderboard(BenchmarkCatalog):
    """The boards of the benchmarks."""

    def leaderboard(
        self, name: str, caller: Caller, *, sort: str | None = None, order: str | None = None
    ) -> dict[str, Any]:
        bench = self.get(name, caller)
        phase = bench.phase
        entries: list[dict[str, Any]] = []
        for row in self.store.list_submissions(name, published_only=True):
            if row.status != "scored":
                continue
            scores = (row.scores or {}).get(phase) or {}
            entries.append(
                {
                    "id": row.id,
                    "method": row.method,
                    "participant": None if row.anonymous else row.participant,
                    "affiliation": None if row.anonymous else row.affiliation,
                    "link": None if row.anonymous else row.link,
                    "anonymous": bool(row.anonymous),
                    "date": row.created_at.isoformat(),
                    "key": key_value(scores, bench.key),
                    "columns": {c: scores.get(c) for c in bench.columns},
                    "baseline": bool(row.baseline),
                }
            )
        # the rank: by the key, best first, ties by submission time (the list is oldest first: sort is stable);
        # an admin's baseline stands in its place by the key without a rank of its own
        ranked = sorted(entries, key=lambda e: (e["key"] is None, -(e["key"] or 0.0)))
        rank = 0
        for entry in ranked:
            if not entry["baseline"]:
                rank += 1
            entry["rank"] = None if entry["baseline"] else rank
        sort = sort or "key"
        if sort not in ("key", "rank", "method", "date", *bench.columns):
            raise BadRequest(f"sort by rank, key, method, date or a column: {', '.join(bench.columns)}")
        order = order or ("asc" if sort in ("rank", "method", "date") else "desc")
        if order not in ("asc", "desc"):
            raise BadRequest("order is asc or desc")
        rows = ranked
        if sort not in ("key", "rank") or order != "desc" or sort == "rank":
            rows = self._sorted(ranked, sort, order)
        return {
            "benchmark": bench.name,
            "title": bench.title,
            "board": phase,
            "key": bench.key,
            "columns": bench.columns,
            "sort": sort,
            "order": order,
            "entries": rows,
        }

    @staticmethod
    def _sorted(entries: list[dict[str, Any]], sort: str, order: str) -> list[dict[str, Any]]:
        place = {id(e): i for i, e in enumerate(entries)}  # the key's order: where baselines stand among ranks

        def value(e: dict[str, Any]) -> Any:
            if sort == "rank":
                return place[id(e)]
            if sort in ("key", "method", "date"):
                return e[sort]
            return e["columns"].get(sort)

        present = [e for e in entries if value(e) is not None]
        absent = [e for e in entries if value(e) is None]
        present.sort(key=lambda e: e["date"])  # ties by submission time
        if order == "desc":
            # stable descending sort that keeps earlier submissions first among ties
            present.sort(key=lambda e: _Desc(value(e)))
        else:
            present.sort(key=value)
        return present + absent

    def leaderboard_csv(self, board: Mapping[str, Any]) -> str:
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        key_name = "key (" + " + ".join(board["key"]) + ")" if len(board["key"]) > 1 else board["key"][0]
        writer.writerow(["rank", "method", "participant", "affiliation", "link", "date", key_name, *board["columns"]])
        for e in board["entries"]:
            rank = "baseline" if e["rank"] is None else e["rank"]
            cells = [rank, e["method"], e["participant"], e["affiliation"], e["link"], e["date"], e["key"]]
            cells += [e["columns"].get(c) for c in board["columns"]]
            writer.writerow(["" if c is None else _cell(c) for c in cells])
        return out.getvalue()


class _Desc:
    """Reverses the order of a sort key (for a stable descending sort)."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __lt__(self, other: _Desc) -> bool:
        return bool(other.value < self.value)


def _cell(value: object) -> object:
    """A CSV cell that a spreadsheet does not read as a formula."""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value
