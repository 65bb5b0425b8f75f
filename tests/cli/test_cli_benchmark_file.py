"""``kitti-eval admin benchmark apply FILE.toml`` and ``export NAME FILE.toml`` on the server's machine: the file
applied twice is one benchmark, what export writes applies as it is, a refusal is one line naming the file's line
and exit code 1, and the service then serves the phases the file defines."""

from __future__ import annotations

import tomllib

import pytest
from server_helpers import GOLDEN, app_client
from server_phases import TWO_PHASES as FILE

from kitti_eval.cli import main


@pytest.fixture
def admin(tmp_path, monkeypatch, capsys):
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(["admin", "--create", *argv])
        out, err = capsys.readouterr()
        return code, out, err

    gt = str(GOLDEN / "kitti_infos_val.pkl")
    assert run("ground-truth", "add", "dev_gt", gt)[0] == 0
    assert run("ground-truth", "add", "test_gt", gt, "--sealed")[0] == 0
    return run


def test_apply_twice_then_export_and_apply_what_it_wrote(admin, tmp_path) -> None:
    path = tmp_path / "kitti-phases.toml"
    path.write_text(FILE)
    code, out, _ = admin("benchmark", "apply", str(path))
    assert code == 0 and out == "benchmark kitti-phases: phase dev: created; phase test: created\n"
    code, out, _ = admin("benchmark", "apply", str(path))
    assert code == 0 and out == "benchmark kitti-phases: phase dev: unchanged; phase test: unchanged\n"
    assert admin("benchmark", "list")[1].splitlines()[0].split("\t")[:2] == ["kitti-phases", "dev_gt"]
    assert len(admin("benchmark", "list")[1].splitlines()) == 1
    written = tmp_path / "exported.toml"
    code, out, _ = admin("benchmark", "export", "kitti-phases", str(written))
    assert code == 0 and out == f"benchmark kitti-phases: written to {written}\n"
    doc = tomllib.loads(written.read_text())
    assert [p["name"] for p in doc["phases"]] == ["dev", "test"] and doc["phases"][1]["split_percent"] == 50
    code, out, _ = admin("benchmark", "apply", str(written))
    assert code == 0 and out.endswith("phase dev: unchanged; phase test: unchanged\n")
    # the leaderboard's CSV is what export prints without a file, as before
    assert admin("benchmark", "export", "kitti-phases")[1].startswith("rank,method,")
    with app_client(tmp_path / "data") as c:
        phases = c.get("/v1/benchmarks/kitti-phases/phases").json()["items"]
        assert [(p["name"], p["current"]) for p in phases] == [("dev", True), ("test", False)]
        assert c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard").status_code == 200


def test_a_refused_file_is_one_line_naming_its_line_and_exit_code_1(admin, tmp_path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(FILE.replace("split_percent = 50", "split_percent = 150"))
    code, out, err = admin("benchmark", "apply", str(path))
    assert code == 1 and out == "" and "Traceback" not in err
    assert err.splitlines()[-1] == (
        f"kitti-eval admin: error: {path}, line 16: "
        "split_percent is the public part of the test frames: more than 0, less than 100"
    )
    path.write_text("name = [")
    code, _, err = admin("benchmark", "apply", str(path))
    assert code == 1 and err.splitlines()[-1].startswith(f"kitti-eval admin: error: {path}: not a TOML file: ")
    code, _, err = admin("benchmark", "apply", str(tmp_path / "missing.toml"))
    assert code == 1 and "missing.toml: cannot be read" in err.splitlines()[-1]
    assert admin("benchmark", "list")[1] == ""  # nothing was made
