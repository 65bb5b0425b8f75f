"""The file examples of the command-line pages, used as written: the gate rules file of docs/cli/gates.md with
the commands after it (on the bundled demo and its weaker model), and the protocol file of docs/cli/index.md."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from doc_examples import run_bash, take

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")

(RULES,) = take("docs/cli/gates.md", "## A rules file", lang="toml")
PASSING, WEAKER = take("docs/cli/gates.md", "## A rules file", 2)
(PROTOCOL,) = take("docs/cli/index.md", "`--protocol-file protocol.toml` sets", lang="toml")


def test_the_gate_rules_file_and_its_commands_run_as_written(tmp_path: Path) -> None:
    assert "gate.toml" in PASSING.code
    (tmp_path / "gate.toml").write_text(RULES.code)
    out = run_bash(PASSING.code, tmp_path).stdout
    assert "gate: PASSED (147 passed, 0 failed)" in out  # 144 drops, one floor, two classes
    out = run_bash(PASSING.code + WEAKER.code, tmp_path).stdout
    header = next(line for line in out.splitlines() if line.startswith("value "))
    assert header.split()[1:3] == ["result.pkl.gz", "result_weaker.pkl.gz"]  # the files' names, not A and B
    (fail,) = [line for line in out.splitlines() if line.startswith("FAIL ")]
    low, high = (float(v) for v in re.search(r"interval of the change \[([-+.\d]+), ([-+.\d]+)\]", fail).groups())  # type: ignore[union-attr]
    assert low < high < 0 and "dropped 14.4782 > 1, significantly" in fail
    assert "dropped 14.4782 > 1, significantly" in (Path(__file__).parents[2] / "docs/cli/gates.md").read_text()
    assert out.rstrip().endswith("exit 3")


def test_the_rules_file_with_require_classes_last_is_refused_naming_the_fix(tmp_path: Path) -> None:
    """The mistake the page warns of: the same file with require_classes moved to the end exits 2 and says why."""
    first, rest = RULES.code.split("\n", 1)
    assert first.startswith("require_classes")
    (tmp_path / "gate.toml").write_text(rest + first + "\n")
    out = run_bash(PASSING.code.replace("--rules gate.toml", "--rules gate.toml 2>&1 || true"), tmp_path).stdout
    assert "require_classes is inside the [max_drop] table; write it before the first [table] header" in out


def test_the_protocol_file_runs_as_written(tmp_path: Path) -> None:
    (tmp_path / "protocol.toml").write_text(PROTOCOL.code)
    proc = run_bash("kitti-eval demo --protocol-file protocol.toml", tmp_path)
    assert "Bus AP_R40@0.70, 0.70, 0.70:" in proc.stdout and "Bus AP_R40@0.50, 0.50, 0.50:" in proc.stdout
    assert "Car AP_R40@0.70, 0.70, 0.70:" in proc.stdout
