"""A phase's settings: one frozen type (:class:`PhaseSettings`), checked once when it is made, whichever door it
comes through (the HTTP route's body, ``kitti-eval admin benchmark add``'s options, a benchmark file's tables),
stored in its row by one rule, and read back and written to a benchmark file from the same type.

Where a setting is kept: a setting the first release's ``benchmarks`` table has a column for keeps that column
(the ground truth, the title, the description, ``public``, the dates and the cap on published entries: the store
queries the ground truth, the phase's life is read from its dates); every other setting, and every setting added
since, is a key of the row's ``config`` (a JSON object), so that a new setting needs no migration. Each field
says which in its metadata (:func:`_setting`); a row written before a setting existed reads its default.

What a row holds beside its settings is the service's, not the host's: its name, the ground truth's project, the
split's seed, whether it is on open labels, its phases' list (on a benchmark's first row), its state (closed by
hand, revealed) and when it was made.

A new setting touches this module (its field: default, kind, where it is kept, its file key; its check in
:meth:`PhaseSettings.__post_init__`) and its view (:mod:`.views`, and a door's field where a door takes it: the
route's body, the admin command's option).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import date, datetime, timezone
from typing import Any

from kitti_eval.core.protocol import THRESHOLD_SETS
from kitti_eval.errors import ConfigError

from ..errors import BadRequest, echo
from ..scoring.evaluator import EvalOptions
from .rules import (
    DEFAULT_KEY,
    DIFFICULTIES,
    MAIN_PHASE,
    check_max_published,
    check_quota,
    check_split_percent,
    check_texts,
    parse_column,
    parse_quota,
    parse_time,
)

__all__ = [
    "PhaseSettings",
    "SettingRefused",
    "scoring_options",
    "check_phase_name",
    "BENCHMARK_SETTINGS",
    "PHASE_SETTINGS",
    "MAX_TEAM",
]

#: the most columns a board has; the most members a team may have
MAX_COLUMNS, MAX_TEAM = 60, 50
_PROTOCOLS = ("official", "openpcdet")


class SettingRefused(BadRequest):
    """A setting refused: ``setting`` names its field (a benchmark file says the line of its key)."""

    def __init__(self, message: str, setting: str) -> None:
        super().__init__(message)
        self.setting = setting


def scoring_options(
    protocol: str, classes: str, threshold_sets: str, key: Sequence[str], columns: Sequence[str]
) -> dict[str, Any]:
    """A phase's scoring as its row keeps it (``protocol``, ``classes``, ``sets``, ``key``, ``columns``),
    checked and normalised: the library's checks of the options, each column to its five parts."""
    options = EvalOptions(protocol=protocol, classes=classes, threshold_sets=threshold_sets)
    config = options.config()  # the library's checks of the options
    class_names, sets = list(config.classes), list(config.threshold_sets)
    if not sets:
        raise ConfigError(f"no threshold set to evaluate; expected one of {list(THRESHOLD_SETS)}")
    keys = [parse_column(k, class_names, sets) for k in key if k.strip()] or [DEFAULT_KEY]
    wanted = list(columns) or [f"{c}/3d/{d}" for c in class_names for d in DIFFICULTIES]
    cols = list(dict.fromkeys(parse_column(c, class_names, sets) for c in wanted if c.strip()))
    if len(cols) > MAX_COLUMNS:
        raise BadRequest(f"at most {MAX_COLUMNS} columns")
    return {
        "protocol": protocol,
        "classes": ",".join(class_names),
        "sets": ",".join(sets),
        "key": keys,
        "columns": cols,
    }


_PHASE_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,19}$")


def check_phase_name(name: object) -> str:
    """A phase's name: 1-20 lower-case letters, digits, '_' or '-', starting with a letter or digit."""
    if not isinstance(name, str) or not _PHASE_NAME.fullmatch(name):
        raise BadRequest(
            f"a phase's name is 1-20 lower-case letters, digits, '_' or '-', starting with a letter or digit; got "
            f"{echo(str(name))}"
        )
    return name


def _setting(
    kind: type | tuple[type, ...],
    *,
    scope: str,
    column: str | None = None,
    config: str | None = None,
    file_key: str | None = None,
    said: str = "default",
    default: Any = dataclasses.MISSING,
) -> Any:
    """A field of :class:`PhaseSettings`: the ``kind`` of value a door gives (checked by :meth:`PhaseSettings.
    parse`), its ``scope`` in a benchmark file (``benchmark``: one value for every phase; ``phase``: a phase's
    table), where its row keeps it (a ``column``, else the ``config`` key, the field's name unless given), its
    key in a file (the field's name unless given) and when an exported file says it (``always``, or when not the
    ``default``)."""
    meta = {"kind": kind, "scope": scope, "column": column, "config": config, "file_key": file_key, "said": said}
    return field(default=default, metadata=meta)


_STR, _INT, _NUMBER, _TIME = str, int, (int, float), (str, datetime, date)


@dataclass(frozen=True, kw_only=True)
class PhaseSettings:
    """Everything a host sets of one phase's row, normalised and checked (:meth:`__post_init__`): an instance is
    a valid setting, however it was made. The benchmark's settings (title to ``team_size``) are the same on each
    of its phases' rows; a phase's own follow."""

    # the benchmark's
    title: str = _setting(_STR, scope="benchmark", column="title", said="always")
    description: str = _setting(_STR, scope="benchmark", column="description", default="")
    public: bool = _setting(bool, scope="benchmark", column="public", default=False, said="always")
    open_to_all: bool = _setting(bool, scope="benchmark", default=False)
    protocol: str = _setting(_STR, scope="benchmark", default="official", said="always")
    classes: str = _setting(_STR, scope="benchmark", default="Car,Pedestrian,Cyclist", said="always")
    threshold_sets: str = _setting(
        _STR, scope="benchmark", config="sets", default=",".join(THRESHOLD_SETS), said="always"
    )
    key: tuple[str, ...] = _setting((str, list, tuple), scope="benchmark", default=(DEFAULT_KEY,), said="always")
    columns: tuple[str, ...] = _setting((list, tuple), scope="benchmark", default=(), said="always")
    team_size: int = _setting(_INT, scope="benchmark", default=1, said="always")
    # the phase's
    phase: str = _setting(_STR, scope="phase", file_key="name", default=MAIN_PHASE, said="always")
    ground_truth: str = _setting(_STR, scope="phase", column="gt_name", said="always")
    opens_at: datetime | None = _setting(_TIME, scope="phase", column="opens_at", default=None, said="always")
    closes_at: datetime | None = _setting(_TIME, scope="phase", column="closes_at", default=None)
    quota: tuple[int, float] = _setting(_STR, scope="phase", default=(3, 1.0), said="always")  # N/DAYS
    split_percent: float | None = _setting(_NUMBER, scope="phase", default=None)
    max_published: int | None = _setting(_INT, scope="phase", column="max_published", default=None)
    late_submissions: bool = _setting(bool, scope="phase", default=False)

    def __post_init__(self) -> None:
        """Every check of a setting, and its normal form (the columns to their five parts, times in UTC)."""
        set_ = object.__setattr__
        check = _Checking()
        if self.protocol not in _PROTOCOLS:
            raise SettingRefused('protocol is "official" or "openpcdet"', "protocol")
        try:
            scoring = scoring_options(self.protocol, self.classes, self.threshold_sets, self.key, self.columns)
        except BadRequest as e:  # said at the list that holds the column refused
            listed = "columns" if any(echo(c) in e.message for c in self.columns) or "columns" in e.message else "key"
            raise SettingRefused(e.message, listed if "column" in e.message else "classes") from None
        except (ConfigError, ValueError) as e:  # the library's refusal of an option
            said = "threshold_sets" if "threshold set" in str(e) else "classes"
            raise SettingRefused(str(e), said) from None
        set_(self, "classes", scoring["classes"])
        set_(self, "threshold_sets", scoring["sets"])
        set_(self, "key", tuple(scoring["key"]))
        set_(self, "columns", tuple(scoring["columns"]))
        with check("title" if len(self.title) > len(self.description) else "description"):
            check_texts(self.title, self.description)
        if not 1 <= self.team_size <= MAX_TEAM:
            raise SettingRefused(f"team_size is 1 (no teams) to {MAX_TEAM}", "team_size")
        with check("phase"):
            check_phase_name(self.phase)
        with check("quota"):
            set_(self, "quota", check_quota(int(self.quota[0]), float(self.quota[1])))
        with check("split_percent"):
            set_(self, "split_percent", check_split_percent(self.split_percent))
        with check("max_published"):
            check_max_published(self.max_published)
        for name in ("opens_at", "closes_at"):
            with check(name):
                set_(self, name, parse_time(getattr(self, name), name))
        if self.opens_at is not None and self.closes_at is not None and self.closes_at <= self.opens_at:
            what = "a benchmark" if self.phase == MAIN_PHASE else f"the phase {self.phase!r}"
            raise SettingRefused(f"{what} closes after it opens", "closes_at")

    # -- from a door ---------------------------------------------------------------------------------------
    @classmethod
    def parse(cls, values: Mapping[str, Any], *, benchmark: str) -> PhaseSettings:
        """The settings a door gives (by field name; a value None or missing: the default), each of the kind its
        field takes (:class:`SettingRefused` naming it otherwise); the title defaults to the ``benchmark``'s
        name."""
        given: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            value = values.get(f.name)
            if value is None:
                continue
            kind = f.metadata["kind"]
            if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
                raise SettingRefused(f"{_file_key(f)} is {_kind_words(kind)}", f.name)
            given[f.name] = value
        if isinstance(given.get("key"), str):
            given["key"] = (given["key"],)
        for name in ("key", "columns"):
            if name in given:
                if not all(isinstance(k, str) for k in given[name]):
                    raise SettingRefused("key and columns are strings: CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]]", name)
                given[name] = tuple(given[name])
        if "quota" in given:
            with _Checking()("quota"):
                given["quota"] = parse_quota(given["quota"])
        for name in ("opens_at", "closes_at"):
            if isinstance(given.get(name), date) and not isinstance(given[name], datetime):
                d = given[name]
                given[name] = datetime(d.year, d.month, d.day, tzinfo=timezone.utc)
        given["title"] = given.get("title") or benchmark
        for f in dataclasses.fields(cls):
            if f.name not in given and f.default is dataclasses.MISSING:
                raise SettingRefused(f"{_file_key(f)} is required: {_kind_words(f.metadata['kind'])}", f.name)
        if "split_percent" in given:
            given["split_percent"] = float(given["split_percent"])
        return cls(**given)

    # -- its row ---------------------------------------------------------------------------------------------
    def stored(self, only: Collection[str] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """Its row's columns and its ``config``'s keys, by the module's rule (``only``: of those fields)."""
        columns: dict[str, Any] = {}
        config: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if only is not None and f.name not in only:
                continue
            value = _jsonable(getattr(self, f.name))
            if f.metadata["column"]:
                columns[f.metadata["column"]] = value
            else:
                config[f.metadata["config"] or f.name] = value
        return columns, config

    @classmethod
    def of_row(cls, row: Any) -> PhaseSettings:
        """The settings a stored row holds (a :class:`~kitti_eval_server.store.BenchmarkRecord`), read as they
        are: they were checked when they were written, and a row changed since by hand is served, not refused. A
        setting its ``config`` lacks (a row written before the setting existed) is the default."""
        read = object.__new__(cls)
        for f in dataclasses.fields(cls):
            if f.metadata["column"]:
                value = getattr(row, f.metadata["column"])
            else:
                value = row.config.get(f.metadata["config"] or f.name)
                value = f.default if value is None else value
            object.__setattr__(read, f.name, _read(f.name, value))
        return read

    @staticmethod
    def file_key(name: str) -> str:
        """The key a benchmark file gives the field ``name`` under."""
        return _file_key(_field(name))

    def changed(self, other: PhaseSettings) -> list[str]:
        """The fields whose values differ from ``other``'s."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) != getattr(other, f.name)]

    # -- its file ------------------------------------------------------------------------------------------
    def file_keys(self, scope: str) -> dict[str, Any]:
        """Its keys of ``scope`` (``benchmark`` or ``phase``) as a benchmark file says them: in the fields'
        order, each always said or when it is not its default."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.metadata["scope"] != scope:
                continue
            value = getattr(self, f.name)
            if f.metadata["said"] != "always" and value == f.default:
                continue
            if value is None:
                continue
            if f.name == "quota":
                value = quota_text(*value)
            elif f.name == "split_percent":
                value = int(value) if float(value).is_integer() else value
            elif isinstance(value, tuple):
                value = list(value)
            out[_file_key(f)] = value
        return out


def quota_text(count: int, days: float) -> str:
    """A quota as a file and the admin command say it, ``N/DAYS``, read back as it was (``3/1``, ``2/0.5``)."""
    short = f"{days:g}"
    return f"{count}/{short if float(short) == days else repr(days)}"


def settings_keys(scope: str) -> tuple[str, ...]:
    """The keys of ``scope`` a benchmark file may hold for the settings (``benchmark`` or ``phase``)."""
    return tuple(_file_key(f) for f in dataclasses.fields(PhaseSettings) if f.metadata["scope"] == scope)


def field_of(scope: str, key: str) -> str:
    """The field a file's key of ``scope`` sets."""
    for f in dataclasses.fields(PhaseSettings):
        if f.metadata["scope"] == scope and _file_key(f) == key:
            return f.name
    raise KeyError(key)


def _file_key(f: dataclasses.Field[Any]) -> str:
    return str(f.metadata["file_key"] or f.name)


def _field(name: str) -> dataclasses.Field[Any]:
    return next(f for f in dataclasses.fields(PhaseSettings) if f.name == name)


def _kind_words(kind: type | tuple[type, ...]) -> str:
    names = {str: "a string", bool: "true or false", int: "a whole number", list: "a list", float: "a number"}
    kinds = kind if isinstance(kind, tuple) else (kind,)
    said = [names[k] for k in kinds if k in names and not (k is int and float in kinds)]
    return " or ".join(dict.fromkeys(said))


def _read(name: str, value: Any) -> Any:
    """A setting's value as its row's JSON keeps it, in the type's form."""
    if name == "quota":
        return int(value[0]), float(value[1])
    if name == "split_percent" and value is not None:
        return float(value)
    if name == "phase":
        return str(value or MAIN_PHASE)
    return tuple(value) if isinstance(value, list) else value


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple):
        return list(value)
    return value


class _Checking:
    """``with check(name):`` a rule's refusal (a :class:`BadRequest`) said as the setting ``name``'s."""

    def __call__(self, name: str) -> _Checking:
        self.name = name
        return self

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, tb: Any) -> None:
        if isinstance(error, SettingRefused):
            return
        if isinstance(error, BadRequest):
            raise SettingRefused(error.message, self.name) from None


#: a benchmark file's keys for the settings: the benchmark's own, and a phase's
BENCHMARK_SETTINGS = settings_keys("benchmark")
PHASE_SETTINGS = settings_keys("phase")
