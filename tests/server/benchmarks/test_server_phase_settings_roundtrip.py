"""A phase's settings have one home (:class:`PhaseSettings`): what is stored of them reads back as they were, what
a benchmark file says of them parses back as they were, and a file applied then exported is the file applied
(Hypothesis draws the settings)."""

from __future__ import annotations

import dataclasses
import tomllib
from datetime import datetime, timedelta, timezone

import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from server_helpers import ADMIN, app_client
from server_phases import HOST, phased_world

from kitti_eval.core.protocol import DIFFICULTIES, METRICS, RECALL_MODES, THRESHOLD_SETS
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file, export_benchmark_file
from kitti_eval_server.benchmarks.phase_settings import (
    BENCHMARK_SETTINGS,
    PHASE_SETTINGS,
    PhaseSettings,
    SettingRefused,
)
from kitti_eval_server.store import BenchmarkRecord

CLASSES = ("Car", "Pedestrian", "Cyclist")
_TEXT = st.text(st.characters(codec="utf-8", exclude_categories=("Cs", "Cc")), max_size=30)
_MOMENTS = st.integers(0, 365 * 24 * 3600).map(
    lambda s: datetime(2031, 1, 1, tzinfo=timezone.utc) + timedelta(seconds=s)
)


@st.composite
def _scoring(draw: st.DrawFn) -> dict[str, object]:
    classes = draw(st.lists(st.sampled_from(CLASSES), min_size=1, max_size=3, unique=True))
    sets = draw(st.lists(st.sampled_from(THRESHOLD_SETS), min_size=1, max_size=2, unique=True))
    parts = st.tuples(
        st.sampled_from(classes),
        st.sampled_from(METRICS),
        st.sampled_from(DIFFICULTIES),
        st.sampled_from(RECALL_MODES),
        st.sampled_from(sets),
    )
    column = st.tuples(parts, st.integers(3, 5)).map(lambda given: "/".join(given[0][: given[1]]))  # short forms too
    return {
        "protocol": draw(st.sampled_from(("official", "openpcdet"))),
        "classes": ",".join(classes),
        "threshold_sets": ",".join(sets),
        "key": tuple(draw(st.lists(column, min_size=1, max_size=3))),
        "columns": tuple(draw(st.lists(column, max_size=6))),
    }


@st.composite
def phase_settings(draw: st.DrawFn, *, ground_truth: str = "test_gt", split: bool = True) -> PhaseSettings:
    opens = draw(_MOMENTS)
    closes = draw(st.none() | st.integers(1, 90 * 24 * 3600).map(lambda s: opens + timedelta(seconds=s)))
    return PhaseSettings(
        title=draw(_TEXT.filter(bool)),
        description=draw(_TEXT),
        public=draw(st.booleans()),
        open_to_all=draw(st.booleans()),
        **draw(_scoring()),
        team_size=draw(st.integers(1, 50)),
        phase=draw(st.from_regex(r"[a-z0-9][a-z0-9_-]{0,19}", fullmatch=True)),
        ground_truth=ground_truth,
        opens_at=opens,
        closes_at=closes,
        quota=(draw(st.integers(1, 100_000)), draw(st.sampled_from((1.0, 0.5, 3650.0)) | st.floats(0.001, 3650))),
        split_percent=draw(st.none() | st.floats(0.5, 99.5) | st.integers(1, 99).map(float)) if split else None,
        max_published=draw(st.none() | st.integers(1, 1000)),
        late_submissions=draw(st.booleans()),
    )


def _row(chosen: PhaseSettings) -> BenchmarkRecord:
    columns, config = chosen.stored()
    now = datetime.now(timezone.utc)
    return BenchmarkRecord(
        name="b", project=None, config=config, closed=False, revealed=False, created_at=now, **columns
    )


@given(phase_settings())
def test_the_stored_settings_read_back_as_they_were(chosen: PhaseSettings) -> None:
    columns, config = chosen.stored()
    assert set(columns) <= {f.name for f in dataclasses.fields(BenchmarkRecord)} and "config" not in columns
    assert PhaseSettings.of_row(_row(chosen)) == chosen


@given(phase_settings())
def test_what_a_file_says_of_the_settings_parses_back_as_they_were(chosen: PhaseSettings) -> None:
    said = {**chosen.file_keys("benchmark"), **chosen.file_keys("phase")}
    assert set(chosen.file_keys("benchmark")) <= set(BENCHMARK_SETTINGS)
    assert set(chosen.file_keys("phase")) <= set(PHASE_SETTINGS)
    fields = {PhaseSettings.file_key(f.name): f.name for f in dataclasses.fields(PhaseSettings)}
    assert PhaseSettings.parse({fields[k]: v for k, v in said.items()}, benchmark="b") == chosen


def test_a_row_written_before_a_setting_existed_reads_its_default() -> None:
    made = PhaseSettings.parse({"ground_truth": "g", "opens_at": "2031-01-01T00:00:00Z"}, benchmark="b")
    row = _row(made)
    old = dataclasses.replace(row, config={k: v for k, v in row.config.items() if k not in ("phase", "team_size")})
    assert PhaseSettings.of_row(old) == made


def test_a_file_applied_then_exported_is_the_file_applied(tmp_path) -> None:
    """Settings drawn for a benchmark of two phases (a development phase on open labels, a test phase on a
    sealed set), applied to one benchmark one after another (no submission: every setting may change), each
    exported as it was applied, and applying the export changes nothing."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        phased_world(c, users=())
        catalog = c.app.state.benchmarks.catalog

        @settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
        @given(
            phase_settings(ground_truth="dev_gt", split=False),
            phase_settings(ground_truth="test_gt"),
            st.integers(1, 30 * 24 * 3600),
        )
        def round_trip(dev: PhaseSettings, test: PhaseSettings, gap: int) -> None:
            dev, test = dataclasses.replace(dev, phase="dev"), dataclasses.replace(test, phase="test")
            shared = {f: getattr(dev, f) for f in ("title", "description", "public", "open_to_all", "team_size")}
            shared |= {f: getattr(dev, f) for f in ("protocol", "classes", "threshold_sets", "key", "columns")}
            after = (dev.closes_at or dev.opens_at) + timedelta(seconds=gap)
            test = dataclasses.replace(test, **shared, opens_at=after, closes_at=None)
            doc = {"name": "rt", **dev.file_keys("benchmark"), "phases": [dev.file_keys("phase")]}
            doc["phases"].append(test.file_keys("phase"))
            text = tomli_w.dumps(doc)
            apply_benchmark_file(catalog, text, caller=HOST)
            exported = export_benchmark_file(catalog, "rt", caller=HOST)
            assert tomllib.loads(exported) == tomllib.loads(text)
            assert not apply_benchmark_file(catalog, exported, caller=HOST).changed

        round_trip()
        assert c.get("/v1/benchmarks/rt", headers=ADMIN).status_code == 200


_TOML_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**63 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.sampled_from(["3/1", "Car/3d/easy", "2031-01-01T00:00:00Z", "official", "strict", "0/0", "1/nan"])
    | st.datetimes(timezones=st.just(timezone.utc))
    | st.dates(),
    lambda inner: st.lists(inner, max_size=3),
    max_leaves=6,
)


@settings(max_examples=300)
@given(st.dictionaries(st.sampled_from([f.name for f in dataclasses.fields(PhaseSettings)]), _TOML_VALUES))
def test_any_value_a_door_gives_is_a_setting_or_a_refusal_naming_it(values: dict[str, object]) -> None:
    """Whatever a file's keys (or a body's fields) hold, the settings are made or refused with SettingRefused
    naming one of them: never another exception."""
    try:
        PhaseSettings.parse({"ground_truth": "g", **values}, benchmark="b")
    except SettingRefused as refused:
        assert refused.setting in {f.name for f in dataclasses.fields(PhaseSettings)}
