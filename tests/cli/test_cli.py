"""The command line: formats, exit codes, errors on stderr, the demo."""

from __future__ import annotations

import json
import pickle
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.cli import main

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"
GT, PRED = GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl"


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_version_is_printed_not_refused(capsys):
    """``kitti-eval --version`` prints the program and its version and exits 0 (it was a usage error)."""
    import kitti_eval

    assert run(capsys, "--version") == (0, f"kitti-eval {kitti_eval.__version__}\n", "")
    assert kitti_eval.__version__ == "0.1.0"


def test_table_reproduces_openpcdet_layout(capsys):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--protocol", "openpcdet")
    assert code == 0
    lines = out.splitlines()
    # per class: strict AP, strict AP_R40, loose AP, loose AP_R40; each a header and 4 rows
    assert len(lines) == 3 * 4 * 5
    assert lines[0] == "Car AP@0.70, 0.70, 0.70:"
    assert lines[5] == "Car AP_R40@0.70, 0.70, 0.70:"
    assert lines[10] == "Car AP@0.70, 0.50, 0.50:"
    assert lines[20] == "Pedestrian AP@0.50, 0.50, 0.50:"
    assert lines[30] == "Pedestrian AP@0.50, 0.25, 0.25:"
    expected = json.loads((GOLDEN / "expected.json").read_text())["python_pcdet"]["pkl"]["ret_dict"]
    r40 = lines[6:10]

    def row(key, digits):
        return ", ".join(f"{expected[f'Car_{key}/{d}_R40']:.{digits}f}" for d in ("easy", "moderate", "hard"))

    assert r40 == [
        "bbox AP:" + row("image", 4),
        "bev  AP:" + row("bev", 4),
        "3d   AP:" + row("3d", 4),
        "aos  AP:" + row("aos", 2),
    ]


def test_json_schema_has_every_key(capsys):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--format", "json")
    assert code == 0
    doc = json.loads(out)
    assert doc["schema_version"] == 1 and doc["protocol"] == "official"
    for oset in ("strict", "loose"):
        for recall in ("R11", "R40"):
            for cls in ("Car", "Pedestrian", "Cyclist"):
                for metric in ("bbox", "bev", "3d", "aos"):
                    assert set(doc["ap"][oset][recall][cls][metric]) == {"easy", "moderate", "hard"}
    assert doc["num_gt"]["Car"]["moderate"] > 0
    assert doc["overlaps"]["Pedestrian"]["loose"] == {"bbox": 0.5, "bev": 0.25, "3d": 0.25}
    assert "curves" not in doc
    assert doc["frames"] == 50


def test_markdown_has_a_row_per_class_and_metric(capsys):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--format", "markdown")
    assert code == 0
    assert "| Class | Metric | IoU | Easy | Moderate | Hard |" in out
    assert len(re.findall(r"^\| Car \| 3d \|", out, flags=re.M)) == 4  # 2 sets x 2 recall modes


def test_custom_iou_and_classes(capsys):
    code, out, _ = run(
        capsys, "--gt", GT, "--pred", PRED, "--format", "json", "--classes", "Car", "--iou", "Car:strict=0.5,0.5,0.5"
    )
    doc = json.loads(out)
    assert code == 0 and doc["classes"] == ["Car"]
    assert doc["overlaps"]["Car"]["strict"] == {"bbox": 0.5, "bev": 0.5, "3d": 0.5}
    # a looser threshold can only find more matches
    default = json.loads(run(capsys, "--gt", GT, "--pred", PRED, "--format", "json")[1])
    loose, strict = (d["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] for d in (doc, default))
    assert loose >= strict


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["--gt", "x"],
        ["--gt", "a", "--pred", "b", "--protocol", "nope"],
        ["--gt", "a", "--pred", "b", "--iou", "Car=0.7"],
        ["--gt", "a", "--pred", "b", "--format", "xml"],
    ],
)
def test_usage_errors_exit_2(capsys, argv):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == ""
    assert "usage:" in err or "error" in err


def test_unknown_class_without_thresholds_is_a_usage_error(capsys):
    code, _, err = run(capsys, "--gt", GT, "--pred", PRED, "--classes", "Bus")
    assert code == 2 and "Bus" in err and "Traceback" not in err
    code, out, _ = run(
        capsys, "--gt", GT, "--pred", PRED, "--classes", "Car,Bus", "--iou", "Bus=0.7,0.7,0.7", "--format", "json"
    )
    assert code == 0 and json.loads(out)["ap"]["strict"]["R40"]["Bus"]["3d"]["easy"] is None


def test_missing_file_exits_1(capsys, tmp_path):
    code, out, err = run(capsys, "--gt", tmp_path / "nope.pkl", "--pred", PRED)
    assert code == 1 and out == "" and "nope.pkl" in err and "Traceback" not in err


def test_hostile_pickle_exits_1_without_running(capsys, tmp_path):
    canary = tmp_path / "canary"

    class Evil:
        def __reduce__(self):
            import os

            return (os.system, (f"touch {canary}",))

    bad = tmp_path / "result.pkl"
    bad.write_bytes(pickle.dumps([Evil()]))
    code, _, err = run(capsys, "--gt", GT, "--pred", bad)
    assert code == 1 and "os" in err and not canary.exists()


def test_prediction_for_unknown_frame_names_it(capsys, tmp_path):
    results = pickle.loads(PRED.read_bytes())  # trusted test fixture
    results[3] = dict(results[3], frame_id="999999")
    bad = tmp_path / "result.pkl"
    bad.write_bytes(pickle.dumps(results))
    code, _, err = run(capsys, "--gt", GT, "--pred", bad)
    assert code == 1 and "999999" in err


def test_wrong_shape_names_frame_and_field(capsys, tmp_path):
    results = pickle.loads(PRED.read_bytes())
    results[2] = dict(results[2], bbox=np.zeros((len(results[2]["score"]), 3), np.float32))
    bad = tmp_path / "result.pkl"
    bad.write_bytes(pickle.dumps(results))
    code, _, err = run(capsys, "--gt", GT, "--pred", bad)
    assert code == 1 and "000002" in err and "bbox" in err


def test_missing_frames_are_reported_on_stderr(capsys, tmp_path):
    results = pickle.loads(PRED.read_bytes())
    short = tmp_path / "result.pkl"
    short.write_bytes(pickle.dumps(results[:-2]))
    code, _, err = run(capsys, "--gt", GT, "--pred", short)
    assert code == 0 and "2 of 50 frames have no predictions" in err and "000049" in err


def test_output_file(capsys, tmp_path):
    out = tmp_path / "r.json"
    code, stdout, _ = run(capsys, "--gt", GT, "--pred", PRED, "--format", "json", "--output", out)
    assert code == 0 and stdout == "" and json.loads(out.read_text())["frames"] == 50


def test_demo_runs_on_bundled_data(capsys):
    code, out, _ = run(capsys, "demo", "--format", "json")
    doc = json.loads(out)
    assert code == 0 and doc["frames"] == 200
    assert 0 < doc["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] < 100


def test_compile_notice_follows_numba_cache(monkeypatch, tmp_path):
    from kitti_eval._jit import kernels_cached

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernels_cached() is False
    deep = tmp_path / "work" / "kitti_eval"
    deep.mkdir(parents=True)
    (deep / "matching._pass2-400.py311.nbi").write_bytes(b"")
    assert kernels_cached() is False  # one of the two kernels is still missing
    (deep / "geometry._frame_overlaps_kernel-251.py311.nbi").write_bytes(b"")
    assert kernels_cached() is True


def test_errors_says_its_kernels_compile_when_only_the_evaluations_are_cached(monkeypatch, tmp_path, capsys):
    """A first kitti-eval errors after kitti-eval demo: the evaluation's kernels are cached, the decomposition's
    compile for seconds, and the command says so on stderr instead of a silence."""
    from kitti_eval.cli.common import start_warm_up

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    deep = tmp_path / "work" / "kitti_eval"
    deep.mkdir(parents=True)
    for marker in ("matching._pass2-400", "geometry._frame_overlaps_kernel-251", "_pickle_scan.scan-30"):
        (deep / f"{marker}.py311.nbi").write_bytes(b"")
    assert start_warm_up() is None and start_warm_up(decomposition=True) is None  # nothing to warm beside
    err = capsys.readouterr().err
    said = "compiling the error decomposition's kernels once (later runs use numba's cache)"
    assert err == f"kitti-eval: {said}\n"
    (deep / "decomposition._tp_error_events-195.py311.nbi").write_bytes(b"")
    start_warm_up(decomposition=True)
    assert capsys.readouterr().err == ""


def test_distance_ranges_in_every_output(capsys):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--ranges", "0,30,inf", "--format", "json")
    doc = json.loads(out)
    assert code == 0 and [r["label"] for r in doc["ranges"]] == ["0-30m", "30m+"] and doc["ranges"][1]["max"] is None
    by_range = [r["num_gt"]["Car"]["moderate"] for r in doc["ranges"]]
    assert sum(by_range) == doc["num_gt"]["Car"]["moderate"]  # the bins split the valid boxes
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--ranges", "0,30,inf")
    assert "Car AP_R40@0.70, 0.70, 0.70 (0-30m):" in out.splitlines()
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--ranges", "0,30,inf", "--format", "markdown")
    assert "### AP R40 by distance 30m+, strict IoU thresholds" in out
    assert run(capsys, "--gt", GT, "--pred", PRED, "--ranges", "30,0")[0] == 2


def test_coco_in_every_output(capsys):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--coco", "--format", "json", "--classes", "Car")
    doc = json.loads(out)
    assert code == 0 and set(doc["coco"]) == {"R11", "R40"}
    # the mean over thresholds 0.50 ... 0.95 sits below the AP at 0.50 (the loose 3D threshold of Car)
    assert 0 < doc["coco"]["R40"]["Car"]["3d"]["moderate"] < doc["ap"]["loose"]["R40"]["Car"]["3d"]["moderate"]
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--coco", "--classes", "Car")
    assert "Car coco AP_R40@0.50:0.05:0.95:" in out.splitlines()


def test_lidar_only_and_protocol_file_flags(capsys, tmp_path):
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--lidar-only", "--format", "json")
    doc = json.loads(out)
    assert code == 0 and doc["ap"]["strict"]["R40"]["Car"]["bbox"]["easy"] is None
    assert doc["ap"]["strict"]["R40"]["Car"]["3d"]["easy"] == doc["ap"]["strict"]["R40"]["Car"]["3d"]["hard"]
    f = tmp_path / "p.toml"
    f.write_text('classes = ["Car"]\nprotocol = "openpcdet"\n[overlaps.Car]\nstrict = [0.7, 0.6, 0.6]\n')
    code, out, _ = run(capsys, "--gt", GT, "--pred", PRED, "--protocol-file", f, "--format", "json")
    doc = json.loads(out)
    assert code == 0 and doc["classes"] == ["Car"] and doc["protocol"] == "openpcdet"
    assert doc["overlaps"]["Car"]["strict"] == {"bbox": 0.7, "bev": 0.6, "3d": 0.6}
    # a flag on the command line wins over the file
    code, out, _ = run(
        capsys, "--gt", GT, "--pred", PRED, "--protocol-file", f, "--protocol", "official", "--format", "json"
    )
    assert json.loads(out)["protocol"] == "official"
    f.write_text("nonsense = 1\n")
    assert run(capsys, "--gt", GT, "--pred", PRED, "--protocol-file", f)[0] == 2


def test_kitti_eval_format_is_read_in_any_case_and_a_bad_one_is_a_usage_error(capsys, monkeypatch):
    monkeypatch.setenv("KITTI_EVAL_FORMAT", "JSON")
    code, out, _ = run(capsys, "demo")
    assert code == 0 and json.loads(out)["schema_version"] == 1
    monkeypatch.setenv("KITTI_EVAL_FORMAT", "xml")
    for argv in (["demo"], ["--help"], ["gate", "--help"]):
        code, out, err = run(capsys, *argv)
        assert code == 2 and out == ""
        assert "KITTI_EVAL_FORMAT: unknown format 'xml'; expected one of table, json, markdown" in err


def test_a_mistyped_class_gets_a_suggestion(capsys):
    code, _, err = run(capsys, "demo", "--classes", "Cars")
    assert code == 2
    assert "class 'Cars' has no default IoU thresholds; did you mean 'Car'?" in err
    code, out, err = run(capsys, "demo", "--classes", "Cars,Pedestrian", "--iou", "Cars=0.7,0.7,0.7")
    assert code == 0 and "Pedestrian AP" in out
    assert "class 'Cars' has neither ground truth nor detections, so every AP of it is n/a; did you mean 'Car'?" in err
    code, _, err = run(capsys, "demo", "--classes", "Bus", "--iou", "Bus=0.5,0.5,0.5")
    assert code == 0 and "class 'Bus' has neither ground truth nor detections, so every AP of it is n/a\n" in err


def test_demo_where_prints_one_path_a_line(capsys):
    code, out, _ = run(capsys, "demo", "--where")
    lines = out.splitlines()
    assert code == 0 and len(lines) == 3
    assert all(Path(p).is_file() for p in lines)
    assert Path(lines[0]).name.startswith("kitti_infos_val") and Path(lines[1]).name.startswith("result")
    assert Path(lines[2]).name == "result_weaker.pkl.gz"  # the weaker model, for compare and baseline gates


def test_demo_where_writes_its_paths_at_once_for_a_reader_that_stops_after_one(monkeypatch):
    # with PYTHONUNBUFFERED=1 each print was a write of its own: `kitti-eval demo --where | head -n 1` then
    # broke the pipe on the second line when head had gone (exit 1, "error: Broken pipe") now and then
    writes: list[str] = []

    class Unbuffered:
        def write(self, text: str) -> int:
            writes.append(text)
            return len(text)

        def flush(self) -> None:
            pass

    monkeypatch.setattr(sys, "stdout", Unbuffered())
    assert main(["demo", "--where"]) == 0
    assert len(writes) == 1 and writes[0].count("\n") == 3 and writes[0].endswith("\n")


def test_a_tiny_negative_difference_prints_as_zero_not_minus_zero():
    from types import SimpleNamespace

    from kitti_eval.analysis.result_diff import render_comparison
    from kitti_eval.core.result import ValueKey

    key = ValueKey("Car", "3d", "moderate")
    cmp = SimpleNamespace(
        rows=lambda: [(key, 80.00001, 80.0, -0.00001, (-0.00002, 0.00004))],
        resamples=10,
        seed=0,
        notes=(),
        errors_only=False,
        names=("A", "B"),
    )
    table = render_comparison(cmp)  # type: ignore[arg-type]
    assert "-0.0000" not in table
    assert "+0.0000  [+0.0000, +0.0000]" in table
    assert "| +0.0000 | [+0.0000, +0.0000] |" in render_comparison(cmp, "markdown")  # type: ignore[arg-type]


def test_the_main_help_lists_every_exit_code(capsys):
    code, out, _ = run(capsys, "--help")
    assert code == 0
    text = " ".join(out.split())
    assert "Exit codes: 0 ok, 1 bad input, 2 usage error, 3 a gate rule failed" in text


def test_compare_errors_shows_which_error_types_changed(capsys, tmp_path):
    import copy

    from kitti_eval.io.safe_pickle import load_pickle

    results = load_pickle(PRED, source="r")
    worse = copy.deepcopy(results)
    for frame in worse:  # every box 0.4 m further away: localization errors grow
        frame["location"] = frame["location"] + np.float32([0.0, 0.0, 0.4])
    (tmp_path / "worse.pkl").write_bytes(pickle.dumps(worse, protocol=4))
    code, out, err = run(capsys, "compare", PRED, tmp_path / "worse.pkl", "--gt", GT, "--errors", "--format", "json")
    assert code == 0, err
    values = {v["key"]: v for v in json.loads(out)["values"]}
    loc = values["Car/3d/moderate/localization/R40"]
    assert loc["b"] > loc["a"] and loc["delta"] == pytest.approx(loc["b"] - loc["a"])
    assert "Car/3d/moderate/R40/strict" in values  # the AP values stay in the JSON
    code, out, _ = run(capsys, "compare", PRED, tmp_path / "worse.pkl", "--gt", GT, "--errors")
    lines = out.splitlines()
    assert code == 0 and all("/R40" in line and line.split()[0].count("/") == 4 for line in lines[1:])
    assert any(line.startswith("Car/3d/moderate/localization/R40 ") for line in lines)
    run(capsys, "--gt", GT, "--pred", PRED, "--format", "json", "-o", tmp_path / "plain.json")
    code, _, err = run(capsys, "compare", tmp_path / "plain.json", PRED, "--gt", GT, "--errors")
    assert code == 1 and "no error decomposition in" in err and "plain.json" in err


def test_every_option_with_a_default_states_it_in_its_help(capsys):
    """frames --help once left the default --difficulty to be guessed: every option of every command that has a
    default now says it, and frames' reads as the command uses it."""
    import argparse

    from kitti_eval.cli import build_parser
    from kitti_eval.cli.common import has_default

    def unstated(parser: argparse.ArgumentParser, name: str):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, subparser in action.choices.items():
                    yield from unstated(subparser, f"{name} {sub}")
            elif action.option_strings and has_default(action) and "default" not in (action.help or ""):
                yield f"{name} {action.option_strings[-1]}"

    assert list(unstated(build_parser(), "kitti-eval")) == []
    assert main(["frames", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--difficulty {easy,moderate,hard} default: moderate" in text
    assert "--set {strict,loose} IoU threshold set (default: strict)" in text


def test_every_file_a_command_writes_is_named_on_stderr(capsys, tmp_path):
    """A command that writes a file says where, so the reader is not left to guess (or to look for it)."""
    out = tmp_path / "result.json"
    code, stdout, err = run(capsys, "--gt", GT, "--pred", PRED, "--format", "json", "--quiet", "--output", out)
    assert code == 0 and stdout == "" and err == f"kitti-eval: wrote {out}\n" and json.loads(out.read_text())
    frames = tmp_path / "frames.csv"
    code, _, err = run(capsys, "frames", "--gt", GT, "--pred", PRED, "--format", "csv", "-o", frames)
    assert code == 0 and f"kitti-eval: wrote {frames}\n" in err and frames.read_text().startswith("frame,tp,fp,fn")
    junit, markdown = tmp_path / "gate.xml", tmp_path / "summary.md"
    code, _, err = run(
        capsys, "gate", "--result", out, "--min", "Car/3d/moderate >= 1", "--junit", junit, "--markdown", markdown
    )
    assert code == 0 and err.splitlines() == [f"kitti-eval: wrote {markdown}", f"kitti-eval: wrote {junit}"]
    assert junit.is_file() and markdown.is_file()


def test_compare_heads_its_columns_with_the_results_names(capsys, tmp_path):
    """The columns were headed A and B; now by the files' names, or their paths where the names are the same."""
    for run_dir in ("run1", "run2"):
        (tmp_path / run_dir).mkdir()
        assert (
            run(capsys, "--gt", GT, "--pred", PRED, "--format", "json", "-o", tmp_path / run_dir / "result.json")[0]
            == 0
        )
    (tmp_path / "run2" / "result.json").rename(tmp_path / "other.json")
    code, out, _ = run(capsys, "compare", tmp_path / "run1" / "result.json", tmp_path / "other.json")
    assert code == 0 and out.splitlines()[0].split()[:4] == ["value", "result.json", "other.json", "B"]
    (tmp_path / "other.json").rename(tmp_path / "run2" / "result.json")
    a, b = (str(tmp_path / d / "result.json") for d in ("run1", "run2"))
    code, out, _ = run(capsys, "compare", a, b, "--format", "markdown")
    assert code == 0 and out.splitlines()[0] == f"| value | {a} | {b} | B − A | 95% interval |"
