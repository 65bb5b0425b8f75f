"""A benchmark defined by one file: the host writes it (TOML), keeps it in version control and applies it with
``kitti-eval admin benchmark apply FILE.toml``; ``kitti-eval admin benchmark export NAME FILE.toml`` writes it back.

Applying the same file again changes nothing; a change of what may change (title, description, public, open to
all, team size, a phase's dates, quota, published cap and late submissions) is applied; a change of how a phase
scores (its ground truth, options, key, columns, split) is applied only while the phase has no submission. A file
that contradicts itself or the service is refused as a whole, before anything is written, with the line it is
refused at: a key the file may not hold, a value of the wrong kind, a split asked of a ground truth that is not
sealed, two phases on one ground truth, a ground truth already another benchmark's test set, dates that overlap.

The keys (:data:`BENCHMARK_KEYS`, :data:`PHASE_KEYS`)::

    name = "kitti-phases"                  # the benchmark's name (at most 40 characters)
    title = "KITTI 3D, two phases"
    description = "Markdown"
    public = true                          # the page and boards are readable without a token
    open_to_all = false                    # every account takes part (else the test set's project's members)
    protocol = "official"                  # or "openpcdet"
    classes = "Car,Pedestrian,Cyclist"
    threshold_sets = "strict,loose"
    key = ["Car/3d/moderate/R40/strict"]   # a column, or several whose mean ranks
    columns = ["Car/3d/moderate"]          # the boards' columns (default: 3D AP of every class and difficulty)
    team_size = 3                          # the most members of a team (1: no teams)

    [[phases]]                             # in order; the first is the benchmark's own
    name = "dev"
    ground_truth = "dev_gt"                # sealed, or open labels (no split) for a development phase
    opens_at = 2026-12-01T00:00:00Z        # default: when the phase is made
    closes_at = 2027-01-31T23:59:00Z       # default: never
    quota = "5/1"                          # N/DAYS, the team's (default 3/1)
    split_percent = 50                     # the public part of a sealed test set
    max_published = 2                      # published entries per participant
    late_submissions = false               # scored after the close, never ranked
"""

from __future__ import annotations

import re
import secrets
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from datetime import date, datetime, timezone
from typing import TYPE_CHECKING, Any, TypeVar

import tomli_w

from kitti_eval.core.protocol import THRESHOLD_SETS

from ..access.accounts import Accounts
from ..access.policy import Caller
from ..errors import BadRequest, Conflict, NotFound, echo
from .catalog import scoring_options
from .lifecycle import PhaseState, check_change, state_of
from .phases import MAX_BENCHMARK_NAME, PhaseOf, check_phase_name, phase_list, phase_row
from .rules import (
    DEFAULT_KEY,
    MAIN_PHASE,
    Benchmark,
    check_max_published,
    check_split_percent,
    check_texts,
    parse_quota,
    parse_time,
)

if TYPE_CHECKING:
    from .catalog import BenchmarkCatalog

__all__ = ["BENCHMARK_KEYS", "PHASE_KEYS", "Applied", "apply_benchmark_file", "export_benchmark_file"]

BENCHMARK_KEYS = (
    "name",
    "title",
    "description",
    "public",
    "open_to_all",
    "protocol",
    "classes",
    "threshold_sets",
    "key",
    "columns",
    "team_size",
    "phases",
)
PHASE_KEYS = (
    "name",
    "ground_truth",
    "opens_at",
    "closes_at",
    "quota",
    "split_percent",
    "max_published",
    "late_submissions",
)
_MAX_PHASES = 10
_MAX_TEAM = 50
_KEY_LINE = re.compile(r"""^\s*("(?:[^"\\]|\\.)*"|'[^']*'|[A-Za-z0-9_-]+)\s*=""")
_PHASES_HEADER = re.compile(r"^\s*\[\[\s*phases\s*\]\]")
_TABLE_HEADER = re.compile(r"^\s*\[")

T = TypeVar("T")


class _Lines:
    """Where each key of the file is: (phase index or None for the benchmark's own keys, key) -> line number."""

    def __init__(self, text: str) -> None:
        self.at: dict[tuple[int | None, str], int] = {}
        self.phase_at: dict[int, int] = {}
        section: int | None = None
        other = False  # inside a table the file may not hold
        phases = -1
        quotes: str | None = None
        for number, line in enumerate(text.splitlines(), 1):
            if quotes is not None:  # inside a multi-line string
                if line.count(quotes) % 2 == 1:
                    quotes = None
                continue
            if _PHASES_HEADER.match(line):
                phases += 1
                section, other = phases, False
                self.phase_at[phases] = number
            elif _TABLE_HEADER.match(line):
                section, other = None, True
                self.at.setdefault((None, line.strip().strip("[] ")), number)
            elif (m := _KEY_LINE.match(line)) and not other:
                self.at.setdefault((section, m.group(1).strip("\"'")), number)
            for q in ('"""', "'''"):
                if line.count(q) % 2 == 1:
                    quotes = q
                    break

    def of(self, key: str, phase: int | None = None) -> int | None:
        found = self.at.get((phase, key))
        if found is None and phase is not None:
            return self.phase_at.get(phase)
        return found


@dataclass
class _Phase:
    index: int
    name: str
    ground_truth: str
    opens_at: datetime | None
    closes_at: datetime | None
    quota: tuple[int, float]
    split_percent: float | None
    max_published: int | None
    late_submissions: bool


@dataclass
class _Spec:
    name: str
    title: str
    description: str
    public: bool
    open_to_all: bool
    scoring: dict[str, Any]
    team_size: int
    phases: list[_Phase] = field(default_factory=list)


@dataclass(frozen=True)
class Applied:
    """What applying a file did: the benchmark's name and one line a phase (``created``, ``changed: ...`` or
    ``unchanged``)."""

    name: str
    lines: tuple[str, ...]

    @property
    def changed(self) -> bool:
        return any(not line.endswith(": unchanged") for line in self.lines)


class _Reader:
    def __init__(self, text: str, source: str) -> None:
        self.source = source
        self.lines = _Lines(text)

    def refuse(self, message: str, key: str | None = None, phase: int | None = None) -> BadRequest:
        line = self.lines.of(key, phase) if key is not None else (self.lines.phase_at.get(phase) if phase else None)
        where = f"{self.source}, line {line}" if line else self.source
        return BadRequest(f"{where}: {message}")

    def checked(self, call: Callable[..., T], *args: Any, key: str, phase: int | None = None) -> T:
        """``call(*args)``, its refusal said at the key's line."""
        try:
            return call(*args)
        except BadRequest as e:
            raise self.refuse(e.message, key, phase) from None

    def value(
        self, table: Mapping[str, Any], key: str, kind: type | tuple[type, ...], phase: int | None, default: Any
    ) -> Any:
        if key not in table:
            return default
        value = table[key]
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            names = {str: "a string", bool: "true or false", int: "a whole number", list: "a list"}
            wanted = " or ".join(names.get(k, k.__name__) for k in (kind if isinstance(kind, tuple) else (kind,)))
            raise self.refuse(f"{key} is {wanted}", key, phase)
        return value


def _time(value: object) -> str | datetime | None:
    if isinstance(value, datetime):
        return value if value.tzinfo else value.replace(tzinfo=timezone.utc)
    if isinstance(value, date):
        return datetime(value.year, value.month, value.day, tzinfo=timezone.utc)
    return None if value is None else str(value)


def _parse(text: str, source: str) -> tuple[_Spec, _Reader]:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise BadRequest(f"{source}: not a TOML file: {e}") from None
    r = _Reader(text, source)
    for key in doc:
        if key not in BENCHMARK_KEYS:
            raise r.refuse(f"{echo(key)} is not a key of a benchmark file ({', '.join(BENCHMARK_KEYS)})", key)
    name = r.value(doc, "name", str, None, None)
    if name is None:
        raise r.refuse('a benchmark file names its benchmark: name = "..."')
    r.checked(Accounts.check_name, name, "benchmark", key="name")
    if len(name) > MAX_BENCHMARK_NAME:
        raise r.refuse(f"a benchmark defined by a file has a name of at most {MAX_BENCHMARK_NAME} characters", "name")
    title = r.value(doc, "title", str, None, name) or name
    description = r.value(doc, "description", str, None, "")
    r.checked(check_texts, title, description, key="description")
    key = r.value(doc, "key", (str, list), None, [DEFAULT_KEY])
    keys = [key] if isinstance(key, str) else key
    columns = r.value(doc, "columns", list, None, [])
    if not all(isinstance(k, str) for k in [*keys, *columns]):
        raise r.refuse("key and columns are strings: CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]]", "key")
    protocol = r.value(doc, "protocol", str, None, "official")
    if protocol not in ("official", "openpcdet"):
        raise r.refuse('protocol is "official" or "openpcdet"', "protocol")
    classes = r.value(doc, "classes", str, None, "Car,Pedestrian,Cyclist")
    sets = r.value(doc, "threshold_sets", str, None, ",".join(THRESHOLD_SETS))
    try:
        scoring = scoring_options(protocol, classes, sets, keys, columns)
    except (BadRequest, ValueError) as e:
        which = "columns" if "column" in str(e) and "columns" in doc else "key" if "column" in str(e) else "classes"
        raise r.refuse(getattr(e, "message", str(e)), which) from None
    team_size = r.value(doc, "team_size", int, None, 1)
    if not 1 <= team_size <= _MAX_TEAM:
        raise r.refuse(f"team_size is 1 (no teams) to {_MAX_TEAM}", "team_size")
    spec = _Spec(
        name=name,
        title=title,
        description=description,
        public=r.value(doc, "public", bool, None, False),
        open_to_all=r.value(doc, "open_to_all", bool, None, False),
        scoring=scoring,
        team_size=team_size,
    )
    phases = doc.get("phases")
    if not isinstance(phases, list) or not phases or not all(isinstance(p, dict) for p in phases):
        raise r.refuse("a benchmark file has one [[phases]] table or more", "phases")
    if len(phases) > _MAX_PHASES:
        raise r.refuse(f"at most {_MAX_PHASES} phases", "phases")
    for i, table in enumerate(phases):
        for key in table:
            if key not in PHASE_KEYS:
                raise r.refuse(f"{echo(key)} is not a key of a phase ({', '.join(PHASE_KEYS)})", key, i)
        phase_name = r.value(table, "name", str, i, None)
        if phase_name is None:
            raise r.refuse("a phase has a name", None, i)
        r.checked(check_phase_name, phase_name, key="name", phase=i)
        if any(p.name == phase_name for p in spec.phases):
            raise r.refuse(f"two phases are named {phase_name!r}", "name", i)
        gt = r.value(table, "ground_truth", str, i, None)
        if gt is None:
            raise r.refuse(f"the phase {phase_name!r} has no ground_truth", None, i)
        opens = r.checked(parse_time, _time(table.get("opens_at")), "opens_at", key="opens_at", phase=i)
        closes = r.checked(parse_time, _time(table.get("closes_at")), "closes_at", key="closes_at", phase=i)
        if opens is not None and closes is not None and closes <= opens:
            raise r.refuse(f"the phase {phase_name!r} closes after it opens", "closes_at", i)
        quota = r.checked(parse_quota, r.value(table, "quota", str, i, "3/1"), key="quota", phase=i)
        split = r.checked(
            check_split_percent, r.value(table, "split_percent", (int, float), i, None), key="split_percent", phase=i
        )
        cap = r.checked(
            check_max_published, r.value(table, "max_published", int, i, None), key="max_published", phase=i
        )
        spec.phases.append(
            _Phase(
                index=i,
                name=phase_name,
                ground_truth=gt,
                opens_at=opens,
                closes_at=closes,
                quota=quota,
                split_percent=split,
                max_published=cap,
                late_submissions=r.value(table, "late_submissions", bool, i, False),
            )
        )
    for before, after in zip(spec.phases, spec.phases[1:]):
        if before.closes_at is not None and after.opens_at is not None and after.opens_at < before.closes_at:
            raise r.refuse(
                f"the phase {after.name!r} opens at {after.opens_at.isoformat()}, before the phase {before.name!r} "
                f"closes ({before.closes_at.isoformat()}): phases follow one another",
                "opens_at",
                after.index,
            )
        if before.opens_at is not None and after.opens_at is not None and after.opens_at < before.opens_at:
            raise r.refuse(f"the phase {after.name!r} opens before the phase {before.name!r}", "opens_at", after.index)
    return spec, r


def _check_against_service(catalog: BenchmarkCatalog, spec: _Spec, r: _Reader) -> None:
    """The refusals that need the service: ground truths that do not exist, are not sealed where a split is
    asked, or are another benchmark's test set; two phases on one ground truth."""
    seen: dict[str, str] = {}
    own_rows = {phase_row(spec.name, p.name, first=p.index == 0) for p in spec.phases}
    first = catalog.benchmark_store.get_benchmark(spec.name)
    if first is not None:
        own_rows |= {row for _, row in phase_list(first)}
    for p in spec.phases:
        try:
            record = catalog.ground_truths.record(p.ground_truth)
        except NotFound:
            raise r.refuse(f"no ground truth named {echo(p.ground_truth)}", "ground_truth", p.index) from None
        if p.ground_truth in seen:
            raise r.refuse(
                f"the phases {seen[p.ground_truth]!r} and {p.name!r} are on one ground truth: each phase has a "
                "set of its own",
                "ground_truth",
                p.index,
            )
        seen[p.ground_truth] = p.name
        if p.split_percent is not None and not record.sealed:
            raise r.refuse(
                f"the phase {p.name!r} asks for a split of {p.ground_truth!r}, which is not sealed: a split hides "
                "a sealed test set's private part (register it with sealed=true, or drop split_percent)",
                "split_percent",
                p.index,
            )
        others = sorted({b.shown_name for b in catalog.using_ground_truth(p.ground_truth) if b.name not in own_rows})
        if others:
            raise r.refuse(
                f"the ground truth {p.ground_truth!r} is already the test set of {', '.join(others)}: a second "
                "benchmark on it gives every participant a second quota on the same labels",
                "ground_truth",
                p.index,
            )


def _wanted(spec: _Spec, p: _Phase, row: Benchmark | None) -> dict[str, Any]:
    """The row's values the file asks for (those a file sets), as the row keeps them."""
    count, days = p.quota
    return {
        "title": spec.title,
        "description": spec.description,
        "public": spec.public,
        "opens_at": p.opens_at or (row.opens_at if row is not None else None),
        "closes_at": p.closes_at,
        "max_published": p.max_published,
        "quota": [count, days],
        "open_to_all": spec.open_to_all,
        "team_size": spec.team_size,
        "late_submissions": p.late_submissions,
        "phase": p.name,
    }


def _scoring_of(bench: Benchmark) -> dict[str, Any]:
    return {k: bench.config.get(k) for k in ("protocol", "classes", "sets", "key", "columns")}


def apply_benchmark_file(catalog: BenchmarkCatalog, text: str, *, caller: Caller, source: str = "the file") -> Applied:
    """Apply the benchmark file ``text`` (named ``source`` in refusals): create the benchmark and its phases, or
    change them to what the file says. Every refusal comes before anything is written."""
    catalog.policy.require_admin(caller)
    spec, r = _parse(text, source)
    _check_against_service(catalog, spec, r)
    first = catalog.benchmark_store.get_benchmark(spec.name)
    stored = phase_list(first) if first is not None else []
    order = tuple((p.name, phase_row(spec.name, p.name, first=p.index == 0)) for p in spec.phases)
    named = {p.name for p in spec.phases}
    row_in_file = dict(order)
    for phase, row in stored:
        if phase in row_in_file and row_in_file[phase] != row:
            index = next(p.index for p in spec.phases if p.name == phase)
            raise r.refuse(
                f"the phase {phase!r} was {'the first' if row == spec.name else 'a later'} phase of {spec.name!r}: "
                "the first phase is the benchmark's own and stays first",
                "name",
                index,
            )
    for phase, row in stored[1:]:
        if phase not in named and catalog.benchmark_store.get_benchmark(row) is not None:
            raise r.refuse(
                f"the phase {phase!r} of {spec.name!r} is not in the file: a phase is never removed (close it instead)"
            )
    rows = {p.name: catalog.benchmark_store.get_benchmark(row) for p, (_, row) in zip(spec.phases, order)}
    plans: list[tuple[_Phase, str, dict[str, Any]]] = []
    for p, (_, row) in zip(spec.phases, order):
        record = rows[p.name]
        if record is None:
            plans.append((p, row, {}))
            continue
        bench = Benchmark.from_record(record)
        changes = _changes(catalog, spec, p, bench, order, r)
        plans.append((p, row, changes))
    lines = []
    for p, row, changes in plans:
        if rows[p.name] is None:
            catalog.create(
                spec.name,
                ground_truth=p.ground_truth,
                title=spec.title,
                description=spec.description,
                protocol=spec.scoring["protocol"],
                classes=spec.scoring["classes"],
                threshold_sets=spec.scoring["sets"],
                key=spec.scoring["key"],
                columns=spec.scoring["columns"],
                quota=f"{p.quota[0]}/{p.quota[1]:g}",
                public=spec.public,
                opens_at=p.opens_at,
                closes_at=p.closes_at,
                split_percent=p.split_percent,
                max_published=p.max_published,
                open_to_all=spec.open_to_all,
                caller=caller,
                phase=PhaseOf(
                    row=row,
                    name=p.name,
                    late_submissions=p.late_submissions,
                    phases=order if p.index == 0 else (),
                    team_size=spec.team_size,
                ),
            )
            lines.append(f"phase {p.name}: created")
        elif changes:
            catalog.benchmark_store.update_benchmark(row, **changes)
            before = rows[p.name]
            detail = _said(changes, Benchmark.from_record(before).config if before is not None else {})
            catalog.audit.record(caller, "benchmark.apply", row, detail=detail)
            lines.append(f"phase {p.name}: changed {detail}")
        else:
            lines.append(f"phase {p.name}: unchanged")
    return Applied(spec.name, tuple(lines))


def _said(changes: dict[str, Any], before: Mapping[str, Any]) -> str:
    """What a phase's row changed, for its line and the audit: the columns, and within ``config`` the settings
    (``config (quota, team_size)``)."""
    said = []
    for column in sorted(changes):
        if column == "config":
            after = changes["config"]
            keys = sorted(k for k in after.keys() | before.keys() if after.get(k) != before.get(k))
            said.append(f"config ({', '.join(keys)})")
        else:
            said.append(column)
    return ", ".join(said)


def _changes(
    catalog: BenchmarkCatalog,
    spec: _Spec,
    p: _Phase,
    bench: Benchmark,
    order: tuple[tuple[str, str], ...],
    r: _Reader,
) -> dict[str, Any]:
    """The columns of the phase's row to write (empty: the row is as the file says)."""
    wanted = _wanted(spec, p, bench)
    config = dict(bench.config)
    row: dict[str, Any] = {}
    for column in ("title", "description", "public", "opens_at", "closes_at", "max_published"):
        if getattr(bench, column) != wanted[column]:
            row[column] = wanted[column]
    # what a row made with ``benchmark add`` holds without saying it: one phase, ``main``, no teams, none late
    unsaid = {"open_to_all": False, "team_size": 1, "late_submissions": False, "phase": MAIN_PHASE}
    for k in ("quota", "open_to_all", "team_size", "late_submissions", "phase"):
        now = config.get(k, unsaid.get(k))
        if k == "quota":
            now = [int(now[0]), float(now[1])] if now else None
        if now != wanted[k]:
            config[k] = wanted[k]
    phases = [list(x) for x in order]
    if p.index == 0 and config.get("phases", [[config.get("phase", MAIN_PHASE), bench.name]]) != phases:
        config["phases"] = phases
    record = catalog.ground_truths.record(p.ground_truth)
    scoring_changed = _scoring_of(bench) != spec.scoring
    split_changed = bench.split_percent != p.split_percent
    gt_changed = bench.gt_name != p.ground_truth
    if scoring_changed or split_changed or gt_changed:
        what = "its ground truth" if gt_changed else "its split" if split_changed else "its scoring"
        if catalog.benchmark_store.list_submissions(bench.name):
            key = "ground_truth" if gt_changed else "split_percent" if split_changed else "key"
            raise r.refuse(
                f"the phase {p.name!r} has submissions: {what} no longer changes (they were scored on it)", key, p.index
            )
        config.update(spec.scoring)
        config["split_percent"] = p.split_percent
        open_labels = p.split_percent is None and not record.sealed
        config.pop("open_labels", None)
        if open_labels:
            config["open_labels"] = True
        if split_changed:
            row["split_seed"] = secrets.token_hex(16) if p.split_percent is not None else None
        row["gt_name"] = record.name
        row["project"] = record.project
    if config != dict(bench.config):
        row["config"] = config
    try:  # the phase's life allows the change of its dates (:mod:`.lifecycle`): a revealed phase stays closed
        check_change(p.name, bench, row)
    except Conflict as e:
        # said at the date the refusal is about: opens_at when it would make the phase scheduled again
        later_opening = "opens_at" in row and state_of(replace(bench, opens_at=row["opens_at"])) is PhaseState.SCHEDULED
        key = "opens_at" if later_opening or "closes_at" not in row else "closes_at"
        raise r.refuse(e.message, key, p.index) from None
    return row


def export_benchmark_file(catalog: BenchmarkCatalog, name: str, *, caller: Caller) -> str:
    """The file that defines the benchmark ``name`` as it is now (applying it changes nothing)."""
    catalog.policy.require_admin(caller)
    first = catalog.benchmark_store.get_benchmark(name)
    if first is None or Benchmark.from_record(first).is_later_phase:
        raise NotFound(f"no benchmark named {echo(name)}")
    bench = Benchmark.from_record(first)
    doc: dict[str, Any] = {"name": bench.name, "title": bench.title}
    if bench.description:
        doc["description"] = bench.description
    doc["public"] = bench.public
    if bench.open_to_all:
        doc["open_to_all"] = True
    doc["protocol"] = bench.config["protocol"]
    doc["classes"] = bench.config["classes"]
    doc["threshold_sets"] = bench.config["sets"]
    doc["key"] = bench.key
    doc["columns"] = bench.columns
    doc["team_size"] = bench.team_size
    phases = []
    for phase, row in phase_list(first):
        record = first if row == first.name else catalog.benchmark_store.get_benchmark(row)
        if record is None:
            continue
        b = Benchmark.from_record(record)
        n, days = b.quota
        out: dict[str, Any] = {"name": phase, "ground_truth": b.gt_name, "opens_at": b.opens_at}
        if b.closes_at is not None:
            out["closes_at"] = b.closes_at
        out["quota"] = f"{n}/{days:g}"
        if b.split_percent is not None:
            out["split_percent"] = int(b.split_percent) if b.split_percent.is_integer() else b.split_percent
        if b.max_published is not None:
            out["max_published"] = b.max_published
        if b.late_submissions:
            out["late_submissions"] = True
        phases.append(out)
    doc["phases"] = phases
    return tomli_w.dumps(doc)
