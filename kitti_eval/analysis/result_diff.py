"""Two results side by side: every value of A and B, B - A, and (with a paired bootstrap) a 95% interval of
B - A; what makes them hard to compare. ``kitti-eval compare`` prints it, the service serves it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..core.result import ValueKey
from ..errors import InputError

__all__ = ["Comparison", "compare_documents", "render_comparison"]


@dataclass(frozen=True)
class Comparison:
    """Two results side by side: per value A, B, B - A, and (with a bootstrap) a 95% interval of B - A."""

    a: Mapping[str, Any]
    b: Mapping[str, Any]
    intervals: Mapping[ValueKey, tuple[float, float]]
    resamples: int
    seed: int | None
    #: the table shows the error types only (the JSON keeps every value)
    errors_only: bool = False
    #: what the table heads A's and B's columns with (the command line: the files' names)
    names: tuple[str, str] = ("A", "B")

    def rows(self) -> list[tuple[ValueKey, float | None, float | None, float | None, tuple[float, float] | None]]:
        """Every AP value, then (when both results hold an error decomposition) every error type's."""
        from .gate import error_keys_of, keys_of

        out = []
        shared = set(self.b.get("classes", ()))
        keys = list(keys_of(self.a))
        if "errors" in self.a and "errors" in self.b:
            keys += error_keys_of(self.a)
        for key in keys:
            if key.cls not in shared:  # said in the notes
                continue
            va = key.read(self.a)
            try:
                vb = key.read(self.b)
            except InputError:  # a class only A has
                vb = None
            delta = None if va is None or vb is None else vb - va
            out.append((key, va, vb, delta, self.intervals.get(key)))
        return out

    @property
    def notes(self) -> list[str]:
        """What makes the two hard to compare: another protocol, other IoU thresholds, classes in one only."""
        a, b = self.a, self.b
        out = []
        if a.get("protocol") != b.get("protocol"):
            out.append(f"different protocols: {a.get('protocol')} and {b.get('protocol')}")
        only = sorted(set(a.get("classes", ())).symmetric_difference(b.get("classes", ())))
        if only:
            out.append(f"classes in only one of them are not compared: {', '.join(only)}")
        for cls in (c for c in a.get("classes", ()) if c in b.get("classes", ())):
            for oset in (s for s in a.get("threshold_sets", ()) if s in b.get("threshold_sets", ())):
                if a["overlaps"][cls][oset] != b["overlaps"][cls][oset]:
                    out.append(f"{cls}/{oset}: different IoU thresholds")
        return out

    def to_dict(self) -> dict[str, Any]:
        """``values``: every value of A with B's and B - A (and the interval with a bootstrap); ``num_det``
        and ``frames``: B - A of the counts; ``notes``: see :attr:`notes`."""
        shared = [c for c in self.a.get("classes", ()) if c in self.b.get("classes", ())]
        return {
            "schema_version": 1,
            "resamples": self.resamples,
            "seed": self.seed,
            "notes": self.notes,
            "values": [
                {"key": str(k), "a": va, "b": vb, "delta": d, "interval95": list(iv) if iv is not None else None}
                for k, va, vb, d, iv in self.rows()
            ],
            "num_det": {
                c: self.b["num_det"][c] - self.a["num_det"][c]
                for c in shared
                if c in self.a.get("num_det", {}) and c in self.b.get("num_det", {})
            },
            "frames": self.b["frames"] - self.a["frames"] if "frames" in self.a and "frames" in self.b else None,
        }


def compare_documents(
    a: Mapping[str, Any],
    b: Mapping[str, Any],
    intervals: Mapping[ValueKey, tuple[float, float]] | None = None,
    resamples: int = 0,
    seed: int | None = None,
    *,
    errors_only: bool = False,
    names: tuple[str, str] = ("A", "B"),
) -> Comparison:
    """``names``: the headers of A's and B's columns in the table and Markdown (default ``A`` and ``B``)."""
    return Comparison(a, b, dict(intervals or {}), resamples, seed, errors_only, names)


def render_comparison(cmp: Comparison, fmt: str = "table", *, every_value: bool = False) -> str:
    """The comparison as a table (R40 strict values unless ``every_value``), Markdown, or JSON."""
    import json

    if fmt == "json":
        return json.dumps(cmp.to_dict(), indent=2, allow_nan=False) + "\n"
    rows = [r for r in cmp.rows() if every_value or (r[0].recall == "R40" and r[0].oset == "strict")]
    if cmp.errors_only:
        rows = [r for r in rows if r[0].error]

    def num(v: float | None, sign: bool = False) -> str:
        if v is None:
            return "-"
        v = round(v, 4) + 0.0  # -0.00001 prints as +0.0000, not -0.0000
        return f"{v:+.4f}" if sign else f"{v:.4f}"

    def interval(iv: tuple[float, float] | None) -> str:
        return "" if iv is None else f"[{num(iv[0], True)}, {num(iv[1], True)}]"

    def significant(iv: tuple[float, float] | None) -> str:
        return "*" if iv is not None and (iv[0] > 0 or iv[1] < 0) else ""

    name_a, name_b = cmp.names
    if fmt == "markdown":
        out = [f"| value | {name_a} | {name_b} | B − A | 95% interval |", "|---|---:|---:|---:|---|"]
        out += [
            f"| `{k}` | {num(a)} | {num(b)} | {num(d, True)}{significant(iv)} | {interval(iv)} |"
            for k, a, b, d, iv in rows
        ]
        note = (
            f"\n{cmp.resamples} paired bootstrap resamples over frames (seed {cmp.seed}); * : the interval "
            "excludes 0.\n"
            if cmp.resamples
            else "\n"
        )
        return "\n".join(out) + "\n" + note + "".join(f"> note: {n}\n" for n in cmp.notes)
    width = max([34, *(len(str(r[0])) for r in rows)])
    wa, wb = max(9, len(name_a)), max(9, len(name_b))
    head = f"{'value':<{width}} {name_a:>{wa}} {name_b:>{wb}} {'B - A':>10}  {'95% interval' if cmp.resamples else ''}"
    out = [head.rstrip()]
    out += [
        f"{str(k):<{width}} {num(a):>{wa}} {num(b):>{wb}} {num(d, True) + significant(iv):>10}  {interval(iv)}".rstrip()
        for k, a, b, d, iv in rows
    ]
    if cmp.resamples:
        out.append(
            f"{cmp.resamples} paired bootstrap resamples over frames (seed {cmp.seed}); "
            "* marks an interval that excludes 0"
        )
    return "\n".join(out) + "\n"
