"""The benchmark's file of docs/service/benchmarks.md ("The benchmark's file"), applied as written: in process
(the file, twice, its export, the refusal the page quotes) and with the page's commands in bash as a host runs
them on the server's machine."""

from __future__ import annotations

import shutil
import tomllib
from pathlib import Path

import pytest
from doc_examples import run_bash, take
from server_benchmarks import ok
from server_helpers import ADMIN, app_client, golden_bytes
from server_phases import HOST

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file, export_benchmark_file
from kitti_eval_server.errors import BadRequest

PAGE = Path(__file__).resolve().parents[2] / "docs" / "service" / "benchmarks.md"
(FILE,) = take("docs/service/benchmarks.md", "## The benchmark's file", 1, lang="toml")
(COMMANDS,) = take("docs/service/benchmarks.md", "The admin registers the phases' sets", 1)


def _register(c) -> None:
    for name, sealed in (("kitti-val", "false"), ("kitti-sealed", "true")):
        files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
        ok(c.post("/v1/ground-truths", data={"name": name, "sealed": sealed}, files=files, headers=ADMIN), 201)


def test_the_pages_file_applies_as_written_twice_and_exports_itself(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        _register(c)
        benchmarks = c.app.state.benchmarks.catalog
        made = apply_benchmark_file(benchmarks, FILE.code, caller=HOST, source="kitti-phases.toml")
        assert made.lines == ("phase dev: created", "phase test: created")
        again = apply_benchmark_file(benchmarks, FILE.code, caller=HOST, source="kitti-phases.toml")
        assert again.lines == ("phase dev: unchanged", "phase test: unchanged")
        phases = ok(c.get("/v1/benchmarks/kitti-phases/phases"))["items"]
        dev, test = phases
        assert (dev["name"], dev["open_labels"], dev["quota"]["submissions"]) == ("dev", True, 5)
        assert (test["name"], test["split_percent"], test["max_published"], test["late_submissions"]) == (
            "test",
            50,
            2,
            True,
        )
        bench = ok(c.get("/v1/benchmarks/kitti-phases"))
        assert bench["team_size"] == 3 and bench["open_to_all"] is True and len(bench["columns"]) == 5
        exported = export_benchmark_file(benchmarks, "kitti-phases", caller=HOST)
        assert tomllib.loads(exported)["phases"][1]["late_submissions"] is True
        assert not apply_benchmark_file(benchmarks, exported, caller=HOST).changed


def test_the_refusal_the_page_quotes_is_the_services(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        _register(c)
        ok(c.post("/v1/benchmarks", json={"name": "kitti-3d", "ground_truth": "kitti-sealed"}, headers=ADMIN), 201)
        with pytest.raises(BadRequest) as refused:
            apply_benchmark_file(c.app.state.benchmarks.catalog, FILE.code, caller=HOST, source="kitti-phases.toml")
    said = refused.value.message
    quoted = "kitti-phases.toml, line 24: the ground truth 'kitti-sealed' is already the test set of kitti-3d: "
    assert said.startswith(quoted) and f"`kitti-eval admin: error: {quoted}...`" in PAGE.read_text()


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_the_pages_commands_run_as_written(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts"):
        pass  # the service's first start makes the database, as on the page
    (tmp_path / "kitti-phases.toml").write_text(FILE.code)
    proc = run_bash(COMMANDS.code.replace("/srv/kitti-eval", str(tmp_path / "data")), tmp_path)
    applied = [line for line in proc.stdout.splitlines() if line.startswith("benchmark kitti-phases: phase")]
    assert applied == [
        "benchmark kitti-phases: phase dev: created; phase test: created",
        "benchmark kitti-phases: phase dev: unchanged; phase test: unchanged",
    ]
    for line in applied:
        assert f"`{line}`" in PAGE.read_text()
    exported = tomllib.loads((tmp_path / "exported.toml").read_text())
    assert [p["ground_truth"] for p in exported["phases"]] == ["kitti-val", "kitti-sealed"]
