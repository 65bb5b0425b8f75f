"""A phase's settings are checked in one place (its split, its cap on published entries, the title's and
description's lengths, its dates): the HTTP route, the admin command and the benchmark file refuse the same value
with one sentence, and what a file is applied with is exported as it was."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest
from server_helpers import ADMIN, app_client
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval.cli import main
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file, export_benchmark_file
from kitti_eval_server.errors import BadRequest

SPLIT = "split_percent is the public part of the test frames: more than 0, less than 100"
CAP = "max_published is 1 to 1000 published entries a participant (or none)"
TEXTS = "a title is at most 200 characters, a description at most 20000"


@pytest.mark.parametrize(
    ("body", "flags", "edit", "says"),
    [
        ({"split_percent": 150}, ["--split-percent", "150"], ("split_percent = 50", "split_percent = 150"), SPLIT),
        ({"max_published": 0}, ["--max-published", "0"], ("split_percent = 50", "max_published = 0"), CAP),
        (
            {"title": "t" * 201},
            ["--title", "t" * 201],
            ('title = "KITTI 3D, two phases"', f'title = "{"t" * 201}"'),
            TEXTS,
        ),
    ],
)
def test_the_route_the_admin_command_and_the_file_refuse_a_setting_alike(
    tmp_path, monkeypatch, capsys, body, flags, edit, says
) -> None:
    data = tmp_path / "data"
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(data))
    with app_client(data, auth="accounts", auth_max_failures=1_000_000) as c:
        phased_world(c)
        routed = c.post("/v1/benchmarks", json={"name": "b", "ground_truth": "test_gt", **body}, headers=ADMIN)
        assert routed.status_code == 422 and routed.json()["error"]["message"] == says
        capsys.readouterr()
        assert main(["admin", "benchmark", "add", "b", "--ground-truth", "test_gt", *flags]) == 1
        assert capsys.readouterr().err.splitlines()[-1].endswith(says)
        with pytest.raises(BadRequest) as refused:
            apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES.replace(*edit), caller=HOST, source="f")
        assert refused.value.message.endswith(says)


def test_a_phase_made_now_that_closed_before_is_refused_at_its_line_and_nothing_is_written(tmp_path) -> None:
    """A phase the file does not give an opening opens when it is made: one whose closes_at has passed is
    refused at that line before any phase is written (the first phase was made before its refusal)."""
    past = TWO_PHASES.replace("split_percent = 50", "split_percent = 50\ncloses_at = 2020-01-01T00:00:00Z")
    with app_client(tmp_path / "data", auth="accounts") as c:
        phased_world(c, users=())
        with pytest.raises(BadRequest) as refused:
            apply_benchmark_file(c.app.state.benchmarks.catalog, past, caller=HOST, source="b.toml")
        assert refused.value.message == "b.toml, line 17: the phase 'test' closes after it opens"
        assert c.get("/v1/benchmarks/kitti-phases", headers=ADMIN).status_code == 404


def test_a_quota_of_any_days_is_exported_as_it_was_applied(tmp_path) -> None:
    """A quota's days are written back with every digit they were given: ``N/DAYS`` with the shortest form that
    reads back as the same number (a file exported then applied changes nothing)."""
    precise = TWO_PHASES.replace('quota = "2/1"', 'quota = "2/1000.875"')
    with app_client(tmp_path / "data", auth="accounts") as c:
        phased_world(c, users=())
        catalog = c.app.state.benchmarks.catalog
        apply_benchmark_file(catalog, precise, caller=HOST)
        exported = export_benchmark_file(catalog, "kitti-phases", caller=HOST)
        assert [p["quota"] for p in tomllib.loads(exported)["phases"]] == ["5/1", "2/1000.875"]
        assert not apply_benchmark_file(catalog, exported, caller=HOST).changed


def test_the_route_the_admin_command_and_the_file_make_the_same_settings(tmp_path, monkeypatch, capsys) -> None:
    """One phase made by each door with the same values holds the same settings (PhaseSettings, read from its
    row), whatever the door's shapes: a JSON body, the command's options, a file's keys."""
    data = tmp_path / "data"
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(data))
    closes = "2031-03-01T12:00:00+00:00"
    body = {
        "title": "Doors",
        "quota": "4/0.5",
        "key": ["Car/bev/hard"],
        "columns": ["Car/bev/hard", "Pedestrian/3d/easy/R11"],
        "split_percent": 25,
        "max_published": 3,
        "public": True,
        "opens_at": "2031-01-01T00:00:00Z",
        "closes_at": closes,
    }
    flags = ["--title", "Doors", "--quota", "4/0.5", "--key", "Car/bev/hard", "--column", "Car/bev/hard"]
    flags += ["--column", "Pedestrian/3d/easy/R11", "--split-percent", "25", "--max-published", "3", "--public"]
    flags += ["--opens", "2031-01-01T00:00:00Z", "--closes", closes, "--share-test-set"]
    phase = (
        'name = "doors"\ntitle = "Doors"\npublic = true\nkey = "Car/bev/hard"\n'
        'columns = ["Car/bev/hard", "Pedestrian/3d/easy/R11"]\n\n[[phases]]\nname = "main"\n'
        'ground_truth = "other_gt"\nquota = "4/0.5"\nsplit_percent = 25\nmax_published = 3\n'
        f"opens_at = 2031-01-01T00:00:00Z\ncloses_at = {closes}\n"
    )
    with app_client(data, auth="accounts", auth_max_failures=1_000_000) as c:
        phased_world(c, users=())
        made = c.post("/v1/benchmarks", json={"name": "routed", "ground_truth": "test_gt", **body}, headers=ADMIN)
        assert made.status_code == 201, made.text
        assert main(["admin", "benchmark", "add", "commanded", "--ground-truth", "test_gt", *flags]) == 0
        catalog = c.app.state.benchmarks.catalog
        apply_benchmark_file(catalog, phase, caller=HOST, source="f")
        routed, commanded, filed = (catalog.named(n).settings for n in ("routed", "commanded", "doors"))
        assert routed == commanded == dataclasses.replace(filed, ground_truth="test_gt")
        assert routed.quota == (4, 0.5) and routed.key == ("Car/bev/hard/R40/strict",) and routed.split_percent == 25


def test_a_benchmark_without_threshold_sets_or_classes_is_refused_by_every_door(tmp_path) -> None:
    """An empty list of threshold sets or classes is a refusal naming the setting (it was an index error, a 500
    from the route, in the column's parsing)."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        phased_world(c, users=())
        for field, says in (("threshold_sets", "no threshold set to evaluate"), ("classes", "no classes")):
            body = {"name": "b", "ground_truth": "test_gt", field: ""}
            refused = c.post("/v1/benchmarks", json=body, headers=ADMIN)
            assert refused.status_code == 422 and says in refused.json()["error"]["message"], refused.text
            with pytest.raises(BadRequest) as in_file:
                edited = TWO_PHASES.replace("team_size = 3", f'team_size = 3\n{field} = ""')
                apply_benchmark_file(c.app.state.benchmarks.catalog, edited, caller=HOST, source="f")
            assert in_file.value.message.startswith("f, line 6: ") and says in in_file.value.message
