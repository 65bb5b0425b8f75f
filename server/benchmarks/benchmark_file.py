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
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any, TypeVar

import tomli_w

from ..access.accounts import Accounts
from ..access.policy import Caller
from ..errors import BadRequest, Conflict, NotFound, echo
from .benchmark import Benchmark
from .lifecycle import PhaseState, check_change, state_of
from .phase_settings import BENCHMARK_SETTINGS, PHASE_SETTINGS, PhaseSettings, SettingRefused, field_of
from .phases import MAX_BENCHMARK_NAME, PhaseOf, check_phase_name, phase_list, phase_row
from .rules import MAIN_PHASE

if TYPE_CHECKING:
    from .catalog import BenchmarkCatalog

__all__ = ["BENCHMARK_KEYS", "PHASE_KEYS", "Applied", "apply_benchmark_file", "export_benchmark_file"]

#: the keys of a benchmark file: the benchmark's name, its settings (:mod:`.phase_settings`) and its phases
BENCHMARK_KEYS = ("name", *BENCHMARK_SETTINGS, "phases")
#: the keys of a phase's table
PHASE_KEYS = PHASE_SETTINGS
_MAX_PHASES = 10
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


@dataclass(frozen=True)
class _Phase:
    index: int
    settings: PhaseSettings

    @property
    def name(self) -> str:
        return self.settings.phase


@dataclass
class _Spec:
    name: str
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
    shared = {field_of("benchmark", k): doc[k] for k in BENCHMARK_SETTINGS if k in doc}
    spec = _Spec(name=name)
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
        if "ground_truth" not in table:
            raise r.refuse(f"the phase {phase_name!r} has no ground_truth", None, i)
        own = {field_of("phase", k): v for k, v in table.items()}
        try:  # the settings' checks, once (:class:`.phase_settings.PhaseSettings`)
            settings = PhaseSettings.parse({**shared, **own}, benchmark=name)
        except SettingRefused as e:
            at = i if e.setting in own else None
            raise r.refuse(e.message, PhaseSettings.file_key(e.setting), at) from None
        spec.phases.append(_Phase(index=i, settings=settings))
    for before, after in zip(spec.phases, spec.phases[1:]):
        was, then = before.settings, after.settings
        if was.closes_at is not None and then.opens_at is not None and then.opens_at < was.closes_at:
            raise r.refuse(
                f"the phase {after.name!r} opens at {then.opens_at.isoformat()}, before the phase {before.name!r} "
                f"closes ({was.closes_at.isoformat()}): phases follow one another",
                "opens_at",
                after.index,
            )
        if was.opens_at is not None and then.opens_at is not None and then.opens_at < was.opens_at:
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
        gt = p.settings.ground_truth
        try:
            record = catalog.ground_truths.record(gt)
        except NotFound:
            raise r.refuse(f"no ground truth named {echo(gt)}", "ground_truth", p.index) from None
        if gt in seen:
            raise r.refuse(
                f"the phases {seen[gt]!r} and {p.name!r} are on one ground truth: each phase has a set of its own",
                "ground_truth",
                p.index,
            )
        seen[gt] = p.name
        if p.settings.split_percent is not None and not record.sealed:
            raise r.refuse(
                f"the phase {p.name!r} asks for a split of {gt!r}, which is not sealed: a split hides "
                "a sealed test set's private part (register it with sealed=true, or drop split_percent)",
                "split_percent",
                p.index,
            )
        others = sorted({b.shown_name for b in catalog.using_ground_truth(gt) if b.name not in own_rows})
        if others:
            raise r.refuse(
                f"the ground truth {gt!r} is already the test set of {', '.join(others)}: a second "
                "benchmark on it gives every participant a second quota on the same labels",
                "ground_truth",
                p.index,
            )


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
        if record is None:  # made opening now unless the file says when: refused here if it closed before
            opening = p.settings.opens_at or datetime.now(timezone.utc)
            plans.append((replace(p, settings=_settings(r, p, opens_at=opening)), row, {}))
            continue
        bench = Benchmark.from_record(record)
        changes = _changes(catalog, spec, p, bench, order, r)
        plans.append((p, row, changes))
    lines = []
    for p, row, changes in plans:
        if rows[p.name] is None:
            listed = order if p.index == 0 else ()
            catalog.create(spec.name, p.settings, caller=caller, phase=PhaseOf(row=row, phases=listed))
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


def _settings(r: _Reader, p: _Phase, *, opens_at: datetime) -> PhaseSettings:
    """The phase's settings opening at ``opens_at`` (the file's, or when the file does not say: now for a phase
    made, its row's for one that exists), refused at the file's line when it closes before."""
    try:
        return replace(p.settings, opens_at=opens_at)
    except SettingRefused as e:
        raise r.refuse(e.message, PhaseSettings.file_key(e.setting), p.index) from None


def _changes(
    catalog: BenchmarkCatalog,
    spec: _Spec,
    p: _Phase,
    bench: Benchmark,
    order: tuple[tuple[str, str], ...],
    r: _Reader,
) -> dict[str, Any]:
    """The columns of the phase's row to write (empty: the row is as the file says): the settings that differ
    from the row's, stored by their rule (:meth:`.phase_settings.PhaseSettings.stored`)."""
    wanted = _settings(r, p, opens_at=p.settings.opens_at or bench.opens_at)  # its opening stays unless said
    changed = set(wanted.changed(PhaseSettings.of_row(bench)))
    row, settings_config = wanted.stored(changed)
    config = {**bench.config, **settings_config}
    phases = [list(x) for x in order]
    if p.index == 0 and config.get("phases", [[config.get("phase", MAIN_PHASE), bench.name]]) != phases:
        config["phases"] = phases
    gt_changed, split_changed = "ground_truth" in changed, "split_percent" in changed
    scoring_changed = bool(changed & {"protocol", "classes", "threshold_sets", "key", "columns"})
    if scoring_changed or split_changed or gt_changed:
        what = "its ground truth" if gt_changed else "its split" if split_changed else "its scoring"
        if catalog.benchmark_store.list_submissions(bench.name):
            key = "ground_truth" if gt_changed else "split_percent" if split_changed else "key"
            raise r.refuse(
                f"the phase {p.name!r} has submissions: {what} no longer changes (they were scored on it)", key, p.index
            )
        record = catalog.ground_truths.record(wanted.ground_truth)
        config.pop("open_labels", None)
        if wanted.split_percent is None and not record.sealed:
            config["open_labels"] = True
        if split_changed:
            row["split_seed"] = secrets.token_hex(16) if wanted.split_percent is not None else None
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
    """The file that defines the benchmark ``name`` as it is now (applying it changes nothing): its settings as
    :meth:`.phase_settings.PhaseSettings.file_keys` says them, the benchmark's from its first row."""
    catalog.policy.require_admin(caller)
    first = catalog.benchmark_store.get_benchmark(name)
    if first is None or Benchmark.from_record(first).is_later_phase:
        raise NotFound(f"no benchmark named {echo(name)}")
    doc: dict[str, Any] = {"name": first.name, **PhaseSettings.of_row(first).file_keys("benchmark")}
    phases = []
    for _, row in phase_list(first):
        record = first if row == first.name else catalog.benchmark_store.get_benchmark(row)
        if record is not None:
            phases.append(PhaseSettings.of_row(record).file_keys("phase"))
    doc["phases"] = phases
    return tomli_w.dumps(doc)
