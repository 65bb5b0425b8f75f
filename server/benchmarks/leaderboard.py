"""A benchmark's leaderboard: its published, scored entries ranked by the key on the scores of the board's
phase (the whole test set, its public part, or its private part once revealed), with how sure each place is
(:mod:`.intervals`), as JSON or CSV."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from typing import Any

from kitti_eval.analysis.ranking import standings

from ..access.policy import Caller
from ..errors import BadRequest
from ..store import BenchmarkStore
from .catalog import BenchmarkCatalog
from .intervals import Intervals, ranked_submissions, rounded
from .teams import entry_teams
from .views import BOARD_FIELDS, ENTRY_FIELDS, pick

__all__ = ["Leaderboard"]


class Leaderboard:
    """The boards of the benchmarks."""

    def __init__(self, catalog: BenchmarkCatalog, intervals: Intervals, benchmark_store: BenchmarkStore) -> None:
        """``catalog``: who sees which benchmark; ``intervals``: the entries' resampled keys."""
        self.catalog = catalog
        self.intervals = intervals
        self.benchmark_store = benchmark_store

    def leaderboard(
        self, row: str, caller: Caller, *, sort: str | None = None, order: str | None = None
    ) -> dict[str, Any]:
        """The published, scored entries ranked by the key (best first; ties by submission time), each with
        its 95% ``interval``, its ``rank_range`` and whether it ``differs_from_next`` (:mod:`.intervals`:
        from the kept resampled keys; None while an entry's are being computed, counted in
        ``bootstrap.pending``), then sorted as asked."""
        bench = self.catalog.get(row, caller)
        part = bench.board_part
        ranked = ranked_submissions(bench, self.benchmark_store.list_submissions(row, published_only=True))
        values = self.intervals.resampled(bench, [submission for submission, key in ranked if key is not None])
        # the participants are ranked among themselves (1, 2, 3, ... without a gap); an admin's baseline stands
        # in its place by the key without a rank, and its interval is its own
        ranked_ids = [submission.id for submission, _ in ranked if not submission.baseline]
        rank_of = {sid: i for i, sid in enumerate(ranked_ids, 1)}
        keyed = [submission.id for submission, key in ranked if key is not None and not submission.baseline]
        standing = dict(zip(keyed, standings([values.get(i) for i in keyed])))
        team_of = entry_teams(bench, [submission for submission, _ in ranked])
        for submission, key in ranked:
            if submission.baseline and key is not None:
                standing[submission.id] = standings([values.get(submission.id)])[0]
        entries: list[dict[str, Any]] = []
        for submission, key in ranked:
            scores = (submission.scores or {}).get(part) or {}
            place = standing.get(submission.id)
            entries.append(
                pick(
                    {
                        "id": submission.id,
                        "method": submission.method,
                        "participant": None if submission.anonymous else submission.participant,
                        "team": None if submission.anonymous else team_of.get(submission.id),
                        "affiliation": None if submission.anonymous else submission.affiliation,
                        "link": None if submission.anonymous else submission.link,
                        "anonymous": bool(submission.anonymous),
                        "date": submission.created_at.isoformat(),
                        "key": key,
                        "columns": {c: scores.get(c) for c in bench.columns},
                        "baseline": bool(submission.baseline),
                        "rank": None if submission.baseline else rank_of[submission.id],
                        "interval": rounded(place.interval) if place else None,
                        "rank_range": list(place.rank_range)
                        if place and place.rank_range and not submission.baseline
                        else None,
                        "differs_from_next": place.differs_from_next if place and not submission.baseline else None,
                    },
                    ENTRY_FIELDS,
                )
            )
        pending = sum(1 for submission, key in ranked if key is not None and submission.id not in values)
        sort = sort or "key"
        if sort not in ("key", "rank", "method", "date", *bench.columns):
            raise BadRequest(f"sort by rank, key, method, date or a column: {', '.join(bench.columns)}")
        order = order or ("asc" if sort in ("rank", "method", "date") else "desc")
        if order not in ("asc", "desc"):
            raise BadRequest("order is asc or desc")
        shown = entries
        if sort not in ("key", "rank") or order != "desc" or sort == "rank":
            shown = self._sorted(entries, sort, order)
        board = {
            "benchmark": bench.shown_name,
            "phase": bench.phase_name,
            "title": bench.title,
            "board": part,
            "key": bench.key,
            "columns": bench.columns,
            "sort": sort,
            "order": order,
            "entries": shown,
            "bootstrap": {**self.intervals.bootstrap_of(bench), "pending": pending},
        }
        return pick(board, BOARD_FIELDS)

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
        # "key (...)" even for one value: the key is often one of the columns too, whose name would repeat
        key_name = "key (" + " + ".join(board["key"]) + ")"
        writer.writerow(
            [
                "rank",
                "method",
                "participant",
                "team",
                "affiliation",
                "link",
                "date",
                key_name,
                *board["columns"],
                "interval_low",
                "interval_high",
                "rank_best",
                "rank_worst",
            ]
        )
        for e in board["entries"]:
            rank = "baseline" if e["rank"] is None else e["rank"]
            cells = [rank, e["method"], e["participant"], e["team"], e["affiliation"], e["link"], e["date"], e["key"]]
            cells += [e["columns"].get(c) for c in board["columns"]]
            cells += e["interval"] or [None, None]
            cells += e["rank_range"] or [None, None]
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
