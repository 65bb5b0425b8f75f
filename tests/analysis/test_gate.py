"""Gate rules pass and fail where they should; reports parse; the CLI exits 0 / 3 / 1 / 2."""

from __future__ import annotations

import copy
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from doc_examples import take

from kitti_eval.analysis.gate import (
    GateRules,
    MaxDrop,
    ValueKey,
    parse_floor,
    parse_max_drop,
    render_junit,
    render_verdict_markdown,
    rules_from_toml,
    run_gate,
)
from kitti_eval.cli import main
from kitti_eval.errors import ConfigError, InputError

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"
GT, PRED = GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl"


def doc(values: dict[str, float | None], classes=("Car", "Pedestrian")) -> dict:
    """A minimal result document: every value 50.0 unless given as 'Class/metric/difficulty' (R40, strict)."""
    ap = {
        oset: {
            r: {
                c: {m: dict.fromkeys(("easy", "moderate", "hard"), 50.0) for m in ("bbox", "bev", "3d", "aos")}
                for c in classes
            }
            for r in ("R11", "R40")
        }
        for oset in ("strict", "loose")
    }
    for key, v in values.items():
        k = ValueKey.parse(key)
        ap[k.oset][k.recall][k.cls][k.metric][k.difficulty] = v
    return {"schema_version": 1, "classes": list(classes), "threshold_sets": ["strict", "loose"], "ap": ap}


def test_floor_passes_and_fails_at_the_bound():
    d = doc({"Car/3d/moderate": 78.5})
    assert run_gate(d, GateRules(floors=(parse_floor("Car/3d/moderate/R40 >= 78.5"),))).passed
    verdict = run_gate(d, GateRules(floors=(parse_floor("Car/3d/moderate > 78.5"),)))
    assert not verdict.passed and "is not > 78.5" in verdict.failures[0].message


def test_floor_on_a_null_value_fails_loudly():
    verdict = run_gate(doc({"Car/aos/easy": None}), GateRules(floors=(parse_floor("Car/aos/easy >= 0"),)))
    assert not verdict.passed and "null" in verdict.failures[0].message


def test_floor_on_a_class_the_result_lacks_is_bad_input():
    with pytest.raises(InputError, match="no class 'Cyclist'"):
        run_gate(doc({}), GateRules(floors=(parse_floor("Cyclist/3d/easy >= 1"),)))


def test_required_class_must_be_evaluated():
    nulls = {
        f"Pedestrian/{m}/{d}/{r}/{s}": None
        for m in ("bbox", "bev", "3d", "aos")
        for d in ("easy", "moderate", "hard")
        for r in ("R11", "R40")
        for s in ("strict", "loose")
    }
    verdict = run_gate(doc(nulls), GateRules(require_classes=("Car", "Pedestrian", "Cyclist")))
    failed = {c.key: c.message for c in verdict.failures}
    assert set(failed) == {"Pedestrian", "Cyclist"}
    assert "not evaluated" in failed["Pedestrian"] and "not in the result" in failed["Cyclist"]


def test_max_drop_against_baseline():
    base = doc({"Car/3d/moderate": 80.0})
    rules = GateRules(max_drops=(MaxDrop(0.5),))
    assert run_gate(doc({"Car/3d/moderate": 79.5}), rules, base).passed  # drop 0.5: allowed
    verdict = run_gate(doc({"Car/3d/moderate": 79.4}), rules, base)  # drop 0.6: not
    assert [c.key for c in verdict.failures] == ["Car/3d/moderate/R40/strict"]
    assert verdict.failures[0].delta == pytest.approx(-0.6)
    # a per-value limit overrides the blanket one
    rules = GateRules(max_drops=(MaxDrop(0.5), parse_max_drop("Car/3d/moderate=1.0")))
    assert run_gate(doc({"Car/3d/moderate": 79.4}), rules, base).passed


def test_max_drop_when_a_value_becomes_null_fails():
    verdict = run_gate(doc({"Car/bev/hard": None}), GateRules(max_drops=(MaxDrop(5.0),)), doc({}))
    assert [c.key for c in verdict.failures] == ["Car/bev/hard/R40/strict"]


def test_insignificant_drop_passes_with_a_note():
    base, now = doc({"Car/3d/moderate": 80.0}), doc({"Car/3d/moderate": 79.0})
    key = ValueKey.parse("Car/3d/moderate")
    rules = GateRules(max_drops=(MaxDrop(0.5, key),))
    significant = run_gate(now, rules, base, intervals={key: (-2.1, -0.2)})
    assert not significant.passed  # the failure names the interval that made the drop count
    expected = "dropped 1.0000 > 0.5, significantly (95% interval of the change [-2.1000, -0.2000])"
    assert significant.checks[0].message == expected
    assert run_gate(now, rules, base).checks[0].message == "dropped 1.0000 > 0.5"  # no bootstrap, no interval
    verdict = run_gate(now, rules, base, intervals={key: (-2.1, 0.3)})
    assert verdict.passed and "not significantly" in verdict.checks[0].message


def test_rules_from_toml(tmp_path):
    f = tmp_path / "gate.toml"
    f.write_text(
        'require_classes = ["Car"]\n[[floor]]\nvalue = "Car/3d/moderate"\nmin = 60\n'
        '[max_drop]\nall = 0.5\n"Pedestrian/3d/moderate/R11" = 2\n'
    )
    rules = rules_from_toml(f)
    assert rules.require_classes == ("Car",)
    assert rules.floors[0].key == ValueKey("Car", "3d", "moderate") and rules.floors[0].bound == 60
    assert {d.key for d in rules.max_drops} == {None, ValueKey("Pedestrian", "3d", "moderate", "R11")}
    f.write_text("[[floor]]\nvalue = 'Car/3d/medium'\nmin = 1\n")
    with pytest.raises(ConfigError, match="unknown difficulty"):
        rules_from_toml(f)
    f.write_text("floor = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        rules_from_toml(f)


@pytest.mark.parametrize("table", ["[max_drop]\nall = 0.5", '[[floor]]\nvalue = "Car/3d/moderate"\nmin = 1'])
def test_require_classes_after_a_table_is_named_not_lost(tmp_path, table):
    """TOML puts a key written after a table's header into that table: a rules file that meant to require a class
    would otherwise fail as a limit that is no number, or (after a floor) pass without requiring it."""
    f = tmp_path / "gate.toml"
    f.write_text(f'{table}\nrequire_classes = ["Car"]\n')
    with pytest.raises(ConfigError, match="require_classes is inside .*; write it before the first"):
        rules_from_toml(f)
    f.write_text('[[floor]]\nvalue = "Car/3d/moderate"\nmin = 1\nmax_drop = 2\n')
    with pytest.raises(ConfigError, match=r"floor #1 has unknown keys \['max_drop'\]"):
        rules_from_toml(f)


@pytest.mark.parametrize("bad", ["Car/3d >= 1", "Car/3d/moderate => 1", "Car/4d/easy >= 1", "Car/3d/easy >= nan"])
def test_bad_rules_are_config_errors(bad):
    with pytest.raises(ConfigError):
        parse_floor(bad)


def test_junit_and_markdown_reports():
    verdict = run_gate(
        doc({"Car/3d/moderate": 10.0}),
        GateRules(floors=(parse_floor("Car/3d/moderate >= 60"), parse_floor("Car/bev/moderate >= 40"))),
    )
    root = ET.fromstring(render_junit(verdict))
    assert root.tag == "testsuite" and root.get("tests") == "2" and root.get("failures") == "1"
    cases = root.findall("testcase")
    assert [c.find("failure") is not None for c in cases] == [True, False]
    md = render_verdict_markdown(verdict)
    assert "❌ failed" in md and "| ❌ | `Car/3d/moderate/R40/strict >= 60` | 10.0000 |" in md


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_gate_exit_codes(capsys, tmp_path):
    result = tmp_path / "r.json"
    assert main(["--gt", str(GT), "--pred", str(PRED), "--format", "json", "-o", str(result)]) == 0
    value = json.loads(result.read_text())["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
    code, out, _ = run(capsys, "gate", "--result", result, "--min", f"Car/3d/moderate >= {value - 0.01}")
    assert code == 0 and "PASSED" in out
    junit, md = tmp_path / "g.xml", tmp_path / "g.md"
    code, out, _ = run(
        capsys,
        "gate",
        "--result",
        result,
        "--min",
        f"Car/3d/moderate >= {value + 0.01}",
        "--junit",
        junit,
        "--markdown",
        md,
    )
    assert code == 3 and "FAILED" in out
    assert ET.parse(junit).getroot().get("failures") == "1" and "❌" in md.read_text()
    # evaluate and gate in one go, against a baseline given as predictions: identical -> no drop
    code, out, _ = run(capsys, "gate", "--gt", GT, "--pred", PRED, "--baseline", PRED, "--max-drop", "0")
    assert code == 0
    # a worse baseline file: drop everything on Car by removing its detections
    worse = copy.deepcopy(json.loads(result.read_text()))
    worse["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] = value + 3.0
    base = tmp_path / "base.json"
    base.write_text(json.dumps(worse))
    code, out, _ = run(capsys, "gate", "--result", result, "--baseline", base, "--max-drop", "1")
    assert code == 3 and "dropped 3.0000 > 1" in out


def test_cli_gate_usage_and_input_errors(capsys, tmp_path):
    assert run(capsys, "gate", "--gt", GT, "--pred", PRED)[0] == 2  # no rules
    assert run(capsys, "gate", "--result", tmp_path / "x.json", "--min", "Car/3d/easy >= 1")[0] == 1
    (tmp_path / "bad.json").write_text('{"hello": 1}')
    code, _, err = run(capsys, "gate", "--result", tmp_path / "bad.json", "--min", "Car/3d/easy >= 1")
    assert code == 1 and "not a kitti-eval JSON result" in err
    assert run(capsys, "gate", "--result", tmp_path / "bad.json", "--max-drop", "1")[0] == 2  # no baseline


(CI_JOB,) = take("docs/cli/gates.md", "A ready-to-copy job", lang="yaml")


def test_readme_ci_example_runs_as_written(tmp_path):
    """The 'Evaluate and gate' step of the CI job in docs/cli/gates.md, run by bash on the bundled demo data."""
    import os
    import re
    import shutil
    import subprocess
    import sys

    block = re.search(r"- name: Evaluate and gate\n\s+run: \|\n((?:          .*\n)+)", CI_JOB.code)
    assert block, "the docs' CI example lost its 'Evaluate and gate' step"
    script = "set -euo pipefail\n" + "\n".join(line[10:] for line in block.group(1).splitlines())
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("no bash")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("GITHUB_STEP_SUMMARY", None)
    proc = subprocess.run([bash, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "gate: PASSED" in proc.stdout
    assert ET.parse(tmp_path / "gate.xml").getroot().get("failures") == "0"
    assert "passed" in (tmp_path / "summary.md").read_text()


def test_an_all_pass_gate_of_many_checks_prints_no_empty_table():
    from kitti_eval.analysis.gate import render_verdict

    verdict = run_gate(doc({}), GateRules(max_drops=(MaxDrop(0.5),)), doc({}))
    assert len(verdict.checks) == 96 and verdict.passed  # 2 classes x 4 metrics x 3 x 2 x 2
    assert (
        render_verdict(verdict)
        == "all 96 checks passed (--show-passed lists them)\ngate: PASSED (96 passed, 0 failed)\n"
    )
    assert render_verdict_markdown(verdict) == "### KITTI AP gate: ✅ passed\n\n96 passed, 0 failed.\n"
    failing = run_gate(doc({"Car/3d/moderate": 40.0}), GateRules(max_drops=(MaxDrop(0.5),)), doc({}))
    text = render_verdict(failing)
    assert text.splitlines()[0].split() == ["rule", "now", "base", "delta", "note"]
    assert "... and 95 passing checks not shown" in text
    assert "| ❌ | `Car/3d/moderate/R40/strict drop <= 0.5` |" in render_verdict_markdown(failing)


def test_rules_on_error_types_read_the_decomposition(capsys, tmp_path):
    key = ValueKey.parse("Car/3d/moderate/localization")
    assert (key.error, key.recall, str(key)) == ("localization", "R40", "Car/3d/moderate/localization/R40")
    assert ValueKey.parse("Car/aos/hard/orientation/R11").recall == "R11"
    with pytest.raises(ConfigError, match="orientation errors are an AOS type"):
        ValueKey.parse("Car/3d/hard/orientation")
    with pytest.raises(ConfigError, match="a maximum drop is for AP values"):
        parse_max_drop("Car/3d/moderate/missed=1")
    document = doc({})
    document["errors"] = {"Car": {"3d": {"moderate": {"localization": 4.5, "missed": None}}}}
    verdict = run_gate(document, GateRules(floors=(parse_floor("Car/3d/moderate/localization <= 5"),)))
    assert verdict.passed and verdict.checks[0].current == 4.5
    verdict = run_gate(document, GateRules(floors=(parse_floor("Car/3d/moderate/missed <= 5"),)))
    assert not verdict.passed and "null" in verdict.checks[0].message
    with pytest.raises(InputError, match="no error decomposition"):
        run_gate(doc({}), GateRules(floors=(parse_floor("Car/3d/moderate/localization <= 5"),)))
    # through the CLI: --gt/--pred are evaluated with the decomposition when a rule needs it
    code = main(["gate", "--gt", str(GT), "--pred", str(PRED), "--rule", "Car/3d/moderate/localization <= 100"])
    out = capsys.readouterr().out
    assert code == 0 and "Car/3d/moderate/localization/R40 <= 100" in out
    code = main(["gate", "--gt", str(GT), "--pred", str(PRED), "--rule", "Car/3d/moderate/localization < 0"])
    assert code == 3
