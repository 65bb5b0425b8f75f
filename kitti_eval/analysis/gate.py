"""Regression gates on AP: floors, maximum drops against a baseline, required classes.

Rules address values of the JSON document by ``Class/metric/difficulty[/recall[/set]]`` (recall R40 and
the strict threshold set by default), e.g. ``Car/3d/moderate/R40 >= 78.5``, or an error type of the error
decomposition (:mod:`kitti_eval.analysis.decomposition`: the AP points that type costs, at the strict set) by
``Class/metric/difficulty/type[/recall]``, e.g. ``Car/3d/moderate/localization <= 5``. A value that is
``null`` (not evaluated) fails any rule that reads it: a gate must never pass on a number that is not there.

Rules come from flags or from a TOML file (docs/cli/gates.md, "A rules file"; a test runs its example)::

    require_classes = ["Car", "Pedestrian"]   # first: after [max_drop] it would be one of its limits

    [[floor]]
    value = "Car/3d/moderate"       # R40, strict
    min = 78.5

    [max_drop]
    all = 0.5                       # every value, against the baseline
    "Pedestrian/3d/moderate" = 1.0  # a per-value override
"""

from __future__ import annotations

import math
import operator
import re
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core.protocol import (
    DIFFICULTIES,
    METRICS,
    RECALL_MODES,
    THRESHOLD_SETS,
)
from ..core.result import ValueKey
from ..errors import ConfigError, InputError
from .decomposition import AOS_TYPES

__all__ = [
    "Floor",
    "MaxDrop",
    "GateRules",
    "Check",
    "Verdict",
    "run_gate",
    "parse_floor",
    "parse_max_drop",
    "rules_from_options",
    "rules_from_toml",
    "render_verdict",
    "render_verdict_markdown",
    "render_junit",
]

_OPS = {">=": operator.ge, ">": operator.gt, "<=": operator.le, "<": operator.lt}


@dataclass(frozen=True)
class Floor:
    """``key op bound``, e.g. Car/3d/moderate/R40 >= 78.5."""

    key: ValueKey
    op: str
    bound: float

    def __str__(self) -> str:
        return f"{self.key} {self.op} {self.bound:g}"


@dataclass(frozen=True)
class MaxDrop:
    """``baseline - current <= limit`` for one value, or for every value when ``key`` is None."""

    limit: float
    key: ValueKey | None = None


@dataclass(frozen=True)
class GateRules:
    floors: tuple[Floor, ...] = ()
    max_drops: tuple[MaxDrop, ...] = ()
    require_classes: tuple[str, ...] = ()

    def merged(self, other: GateRules) -> GateRules:
        return GateRules(
            self.floors + other.floors,
            self.max_drops + other.max_drops,
            self.require_classes + tuple(c for c in other.require_classes if c not in self.require_classes),
        )

    @property
    def empty(self) -> bool:
        return not (self.floors or self.max_drops or self.require_classes)

    @property
    def needs_errors(self) -> bool:
        """Whether a rule reads the error decomposition (the result must be evaluated with it)."""
        return any(f.key.error for f in self.floors)


_FLOOR_RE = re.compile(r"^\s*(?P<key>[^<>=\s]+)\s*(?P<op>>=|<=|>|<)\s*(?P<bound>[-+0-9.eE]+)\s*$")


def parse_floor(text: str) -> Floor:
    """``Car/3d/moderate/R40 >= 78.5``."""
    m = _FLOOR_RE.match(text)
    if not m:
        raise ConfigError(f"expected a rule like 'Car/3d/moderate/R40 >= 78.5', got {text!r}")
    try:
        bound = float(m["bound"])
    except ValueError:
        raise ConfigError(f"not a number: {m['bound']!r} in {text!r}") from None
    if not math.isfinite(bound):
        raise ConfigError(f"the bound of {text!r} must be finite")
    return Floor(ValueKey.parse(m["key"]), m["op"], bound)


def parse_max_drop(text: str) -> MaxDrop:
    """``0.5`` (every value) or ``Car/3d/moderate=0.5``."""
    key_text, _, limit_text = text.rpartition("=")
    try:
        limit = float(limit_text)
    except ValueError:
        raise ConfigError(f"expected --max-drop N or --max-drop Class/metric/difficulty=N, got {text!r}") from None
    if not math.isfinite(limit) or limit < 0:
        raise ConfigError(f"a maximum drop must be a finite number >= 0, got {text!r}")
    key = ValueKey.parse(key_text) if key_text else None
    if key is not None and key.error:
        raise ConfigError(
            f"a maximum drop is for AP values; bound an error type with a rule such as '{key} <= 5' ({text!r})"
        )
    return MaxDrop(limit, key)


def rules_from_options(
    floors: Sequence[str] = (),
    max_drops: Sequence[str] = (),
    require_classes: Sequence[str] = (),
    *,
    also: GateRules | None = None,
    baseline: bool,
) -> GateRules:
    """Gate rules as the CLI's flags and the service's request give them (floors such as
    ``Car/3d/moderate >= 78.5``, drops such as ``0.5`` or ``Car/3d/moderate=1.0``, class names), merged with
    ``also`` (a rules file's). ``baseline``: whether a baseline is given (a maximum drop needs one).

    Raises ConfigError: a malformed rule, no rule at all, or a maximum drop without a baseline.
    """
    rules = GateRules(
        tuple(parse_floor(r) for r in floors), tuple(parse_max_drop(d) for d in max_drops), tuple(require_classes)
    )
    if also is not None:
        rules = rules.merged(also)
    if rules.empty:
        raise ConfigError(
            "no rules: give a floor (--min), a maximum drop (--max-drop) or a required class "
            "(--require-class), or a rules file"
        )
    if rules.max_drops and not baseline:
        raise ConfigError("a maximum drop (--max-drop) needs a baseline")
    return rules


def rules_from_toml(path: str | Path) -> GateRules:
    """Rules from a TOML file (see the module docstring)."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"cannot read gate rules {p}: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: not valid TOML: {e}") from None
    unknown = set(data) - {"floor", "max_drop", "require_classes"}
    if unknown:
        raise ConfigError(f"{p}: unknown keys {sorted(unknown)}; expected floor, max_drop, require_classes")
    floors = []
    for i, entry in enumerate(data.get("floor", [])):
        if not isinstance(entry, dict) or "value" not in entry or not ({"min", "max"} & set(entry)):
            raise ConfigError(f"{p}: floor #{i + 1} needs 'value' and 'min' (or 'max')")
        if "require_classes" in entry:  # written after a [[floor]] header, TOML put it in that floor
            raise ConfigError(
                f"{p}: require_classes is inside floor #{i + 1}; write it before the first [table] header"
            )
        if set(entry) - {"value", "min", "max"}:
            extra = sorted(set(entry) - {"value", "min", "max"})
            raise ConfigError(f"{p}: floor #{i + 1} has unknown keys {extra}; expected value, min, max")
        key = ValueKey.parse(str(entry["value"]))
        if "min" in entry:
            floors.append(Floor(key, ">=", _number(entry["min"], p, f"floor #{i + 1} min")))
        if "max" in entry:
            floors.append(Floor(key, "<=", _number(entry["max"], p, f"floor #{i + 1} max")))
    drops = []
    md = data.get("max_drop", {})
    if isinstance(md, (int, float)):
        md = {"all": md}
    if not isinstance(md, dict):
        raise ConfigError(f"{p}: max_drop must be a number or a table")
    if "require_classes" in md:  # written after the [max_drop] header, TOML put it in that table
        raise ConfigError(
            f"{p}: require_classes is inside the [max_drop] table; write it before the first [table] header"
        )
    for name, limit in md.items():
        value = _number(limit, p, f"max_drop {name}")
        if value < 0:
            raise ConfigError(f"{p}: max_drop {name} must be >= 0")
        drops.append(MaxDrop(value, None if name == "all" else ValueKey.parse(name)))
    classes = data.get("require_classes", [])
    if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
        raise ConfigError(f"{p}: require_classes must be a list of class names")
    return GateRules(tuple(floors), tuple(drops), tuple(classes))


def _number(value: object, path: Path, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ConfigError(f"{path}: {what} must be a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Check:
    """One rule applied to one value."""

    rule: str
    key: str
    passed: bool
    current: float | None = None
    baseline: float | None = None
    delta: float | None = None
    interval: tuple[float, float] | None = None
    message: str = ""


@dataclass(frozen=True)
class Verdict:
    checks: tuple[Check, ...] = field(default_factory=tuple)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failures(self) -> tuple[Check, ...]:
        return tuple(c for c in self.checks if not c.passed)


def _all_keys(doc: Mapping[str, Any]) -> Iterable[ValueKey]:
    for oset in doc.get("threshold_sets", THRESHOLD_SETS):
        for recall in RECALL_MODES:
            for cls in doc["classes"]:
                for metric in METRICS:
                    for d in DIFFICULTIES:
                        yield ValueKey(cls, metric, d, recall, oset)


def run_gate(
    current: Mapping[str, Any],
    rules: GateRules,
    baseline: Mapping[str, Any] | None = None,
    intervals: Mapping[ValueKey, tuple[float, float]] | None = None,
) -> Verdict:
    """Apply ``rules`` to a result document (``EvalResult.to_dict()`` or its JSON).

    ``intervals`` (optional): 95% bootstrap intervals of ``current - baseline`` per value. When given, a
    drop fails only if it exceeds the limit *and* its interval lies entirely below zero (a significant
    drop); otherwise it passes with a note.
    """
    if rules.empty:
        raise ConfigError("no gate rules: give --min, --max-drop, --require-class or --rules")
    checks: list[Check] = []
    for cls in rules.require_classes:
        present = cls in current.get("classes", [])
        evaluated = present and any(
            current["ap"][oset][recall][cls][m][d] is not None
            for oset in current["threshold_sets"]
            for recall in RECALL_MODES
            for m in METRICS
            for d in DIFFICULTIES
        )
        msg = (
            ""
            if evaluated
            else f"class {cls} is not in the result"
            if not present
            else f"class {cls} was not evaluated (no detections of it?)"
        )
        checks.append(Check(f"require class {cls}", cls, evaluated, message=msg))
    for floor in rules.floors:
        value = _read_or_none(current, floor.key)
        if value is None:
            checks.append(Check(str(floor), str(floor.key), False, message="value is null (not evaluated)"))
            continue
        ok = _OPS[floor.op](value, floor.bound)
        checks.append(
            Check(
                str(floor),
                str(floor.key),
                ok,
                current=value,
                message="" if ok else f"{value:.4f} is not {floor.op} {floor.bound:g}",
            )
        )
    if rules.max_drops:
        if baseline is None:
            raise ConfigError("a --max-drop rule needs a baseline (--baseline)")
        per_key = {d.key: d.limit for d in rules.max_drops if d.key is not None}
        blanket = [d.limit for d in rules.max_drops if d.key is None]
        keys = list(_all_keys(current)) if blanket else []
        keys += [k for k in per_key if k not in keys]
        for key in keys:
            limit = per_key.get(key, min(blanket) if blanket else None)
            if limit is None:
                continue
            checks.append(_drop_check(key, limit, current, baseline, intervals, explicit=key in per_key))
    return Verdict(tuple(checks))


def _read_or_none(doc: Mapping[str, Any], key: ValueKey) -> float | None:
    return key.read(doc)


def _drop_check(
    key: ValueKey,
    limit: float,
    current: Mapping[str, Any],
    baseline: Mapping[str, Any],
    intervals: Mapping[ValueKey, tuple[float, float]] | None,
    explicit: bool,
) -> Check:
    rule = f"{key} drop <= {limit:g}"
    now = _read_or_none(current, key)
    try:
        before = _read_or_none(baseline, key)
    except InputError:
        before = None
        if explicit:
            return Check(rule, str(key), False, current=now, message="the baseline has no such value")
    if before is None and now is None:
        if explicit:
            return Check(rule, str(key), False, message="value is null in both results")
        return Check(rule, str(key), True, message="not evaluated in either result")
    if now is None:
        return Check(rule, str(key), False, baseline=before, message="value is null now but was evaluated before")
    if before is None:
        if explicit:
            return Check(rule, str(key), False, current=now, message="value is null in the baseline")
        return Check(rule, str(key), True, current=now, message="new value (null in the baseline)")
    delta = now - before
    interval = intervals.get(key) if intervals else None
    ok = -delta <= limit + 1e-12
    message = "" if ok else f"dropped {-delta:.4f} > {limit:g}"
    if not ok and interval is not None and interval[1] >= 0:
        ok = True
        message = f"dropped {-delta:.4f} > {limit:g}, but not significantly (95% interval reaches {interval[1]:+.4f})"
    elif not ok and interval is not None:  # the interval that made the drop count
        message += f", significantly (95% interval of the change [{interval[0]:+.4f}, {interval[1]:+.4f}])"
    return Check(rule, str(key), ok, current=now, baseline=before, delta=delta, interval=interval, message=message)


def render_verdict(verdict: Verdict, *, show_passed: bool = False) -> str:
    """A readable table: failures always, passing checks when asked (or when there are few)."""
    rows = [c for c in verdict.checks if show_passed or not c.passed or len(verdict.checks) <= 20]
    head = f"{'':4} {'rule':<48} {'now':>9} {'base':>9} {'delta':>9}  note"
    lines = [head] if rows else []  # no header over an empty table
    for c in rows:
        lines.append(
            f"{'ok' if c.passed else 'FAIL':<4} {c.rule:<48} {_f(c.current):>9} {_f(c.baseline):>9} "
            f"{_f(c.delta, sign=True):>9}  {c.message}"
        )
    hidden = len(verdict.checks) - len(rows)
    if hidden:
        more = f"     ... and {hidden} passing checks not shown" if rows else f"all {hidden} checks passed"
        lines.append(f"{more} (--show-passed lists them)")
    n_fail = len(verdict.failures)
    lines.append(
        f"gate: {'PASSED' if verdict.passed else 'FAILED'} ({len(verdict.checks) - n_fail} passed, {n_fail} failed)"
    )
    return "\n".join(lines) + "\n"


def render_verdict_markdown(verdict: Verdict) -> str:
    status = "✅ passed" if verdict.passed else "❌ failed"
    shown = [c for c in sorted(verdict.checks, key=lambda c: c.passed) if not c.passed or len(verdict.checks) <= 40]
    out = [f"### KITTI AP gate: {status}", ""]
    if shown:  # no table of nothing when every one of many checks passed
        out += ["| | rule | now | baseline | delta | note |", "|---|---|---:|---:|---:|---|"]
    for c in shown:
        out.append(
            f"| {'✅' if c.passed else '❌'} | `{c.rule}` | {_f(c.current)} | {_f(c.baseline)} | "
            f"{_f(c.delta, sign=True)} | {c.message} |"
        )
    n_fail = len(verdict.failures)
    if shown:
        out.append("")
    out.append(f"{len(verdict.checks) - n_fail} passed, {n_fail} failed.")
    return "\n".join(out) + "\n"


def render_junit(verdict: Verdict, name: str = "kitti-eval gate") -> str:
    """JUnit XML: one test case per check, failures as <failure>."""
    suite = ET.Element(
        "testsuite",
        name=name,
        tests=str(len(verdict.checks)),
        failures=str(len(verdict.failures)),
        errors="0",
        skipped="0",
    )
    for c in verdict.checks:
        case = ET.SubElement(suite, "testcase", classname="kitti_eval.analysis.gate", name=c.rule)
        if not c.passed:
            failure = ET.SubElement(case, "failure", message=c.message or "failed")
            failure.text = f"current={_f(c.current)} baseline={_f(c.baseline)} delta={_f(c.delta, sign=True)}"
    return ET.tostring(suite, encoding="unicode", xml_declaration=True) + "\n"


def _f(value: float | None, sign: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:+.4f}" if sign else f"{value:.4f}"


def keys_of(doc: Mapping[str, Any]) -> Sequence[ValueKey]:
    """Every value key of a result document."""
    return list(_all_keys(doc))


def error_keys_of(doc: Mapping[str, Any]) -> list[ValueKey]:
    """Every error-type key of a result document's error decomposition (none without one), R40 then R11."""
    out = []
    for recall, name in (("R40", "errors"), ("R11", "errors_r11")):
        table = doc.get(name)
        if not isinstance(table, Mapping):
            continue
        for cls, by_metric in table.items():
            for metric, by_diff in by_metric.items():
                for d, types in by_diff.items():
                    for kind in AOS_TYPES if types else ():
                        if kind in types:
                            out.append(ValueKey(cls, metric, d, recall, "strict", kind))
    return out
