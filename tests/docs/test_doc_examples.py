"""Every bash and python example of the README and docs/ is run by a test, or says why not; the examples that
need only the bundled demo are run here, as written, in a folder laid out as they expect."""

from __future__ import annotations

import contextlib
import gzip
import importlib
import io
import os
import pickle
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from doc_examples import CHECKED, ROOT, TAKEN, Example, examples, pages, take, text

from kitti_eval.demo import demo_paths, demo_weaker_path

# ------------------------------------------------------------------------------------------- the examples here

# bash blocks run in the demo folder below: (the example, a line its output must hold)
SHELL = [
    (take("docs/cli/index.md", "## Distance ranges")[0], "Car AP_R40@0.70, 0.70, 0.70 (0-30m):"),
    (take("docs/cli/frames.md", "# Where the errors are")[0], "pv_rcnn"),
    (take("docs/cli/why-ap-is-lost.md", "# Why AP is lost")[0], "True-positive errors"),
    (take("docs/cli/checkpoints.md", "# Many checkpoints at once")[0], "epoch 80"),
]
# python blocks run in that folder with the names they take as given: (the example, what it is given)
PYTHON = [
    (take("docs/python/index.md", "# From Python", lang="python")[0], ()),
    (take("docs/python/index.md", "OpenPCDet users can swap one import", lang="python")[0], ("annos",)),
    (take("docs/frameworks.md", "## OpenPCDet: one import", lang="python")[0], ()),
    (take("docs/frameworks.md", "## mmdetection3d 1.x", lang="python")[0], ("data_root",)),
    (take("docs/frameworks.md", "Code that calls the evaluation function swaps", lang="python")[0], ("annos",)),
    (take("docs/frameworks.md", "## Any PyTorch-style loop", lang="python")[0], ("batches",)),
    (take("README.md", "### 3. Use it in OpenPCDet or mmdetection3d", 2, lang="python")[0], ()),
    (take("README.md", "### 3. Use it in OpenPCDet or mmdetection3d", 2, lang="python")[1], ("data_root",)),
]


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory) -> Path:
    """The demo's ground truth and predictions where the examples name them: kitti_infos_val.pkl and result.pkl,
    and result.pkl as OpenPCDet's output folders hold it for two models and two epochs: the bundled weaker model's
    for PointPillars and its 40th epoch, the demo's for the others."""
    folder = tmp_path_factory.mktemp("demo-folder")
    gt, pred = (gzip.decompress(p.read_bytes()) for p in demo_paths())
    weaker = gzip.decompress(demo_weaker_path().read_bytes())
    (folder / "kitti_infos_val.pkl").write_bytes(gt)
    results = {"result.pkl": pred}
    for model, data in (("pointpillar", weaker), ("pv_rcnn", pred)):
        results[f"output/kitti_models/{model}/default/eval/epoch_80/val/default/result.pkl"] = data
    for epoch, data in ((40, weaker), (80, pred)):
        results[f"output/pointpillar/eval/epoch_{epoch}/val/default/result.pkl"] = data
    for name, data in results.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    return folder


def _id(value: Any) -> str:
    return str(value) if isinstance(value, Example) else ""


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
@pytest.mark.parametrize(("example", "needle"), SHELL, ids=_id)
def test_shell_example_runs_on_the_demo(example: Example, needle: str, demo_folder: Path, tmp_path: Path) -> None:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env["MPLBACKEND"] = "Agg"
    work = tmp_path / "work"
    shutil.copytree(demo_folder, work)
    proc = subprocess.run(
        ["bash", "-c", "set -euo pipefail\n" + example.code],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert needle in proc.stdout, proc.stdout[-2000:]
    for written in re.findall(r"--plot(?:-dir)? (\S+)", example.code):  # the pictures it says it writes
        target = work / written
        assert target.is_file() or any(target.glob("*.png")), written


@pytest.fixture(scope="module")
def given(demo_folder: Path) -> dict[str, dict[str, Any]]:
    infos = pickle.loads((demo_folder / "kitti_infos_val.pkl").read_bytes())  # trusted: the package's demo
    results = pickle.loads((demo_folder / "result.pkl").read_bytes())
    return {
        "annos": {
            "gt_annos": [i["annos"] for i in infos],
            "dt_annos": results,
            "class_names": ["Car", "Pedestrian", "Cyclist"],
        },
        "data_root": {"data_root": "data/kitti/"},
        "batches": {"batches": [(infos[k : k + 8], results[k : k + 8]) for k in range(0, len(infos), 8)]},
    }


@pytest.mark.parametrize(("example", "names"), PYTHON, ids=_id)
def test_python_example_runs_on_the_demo(
    example: Example, names: tuple[str, ...], given: dict[str, dict[str, Any]], demo_folder: Path, monkeypatch
) -> None:
    monkeypatch.chdir(demo_folder)
    namespace: dict[str, Any] = {"__name__": "example"}
    for name in names:
        namespace.update(given[name])
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(example.code, str(example), "exec"), namespace)  # the example, as written
    if "result" in namespace and hasattr(namespace["result"], "get"):
        assert 0 < namespace["result"].get("Car", "3d", "moderate") < 100
    if "text" in namespace:  # OpenPCDet's table and keys
        assert namespace["text"].startswith("Car AP@") and "Car_3d/moderate_R40" in namespace["ret_dict"]
    if "result_str" in namespace:  # mmdetection3d's
        assert "AP40 Results" in namespace["result_str"]
        assert "KITTI/Car_3D_AP40_moderate_strict" in namespace["ap_dict"]
    if "val_evaluator" in namespace:
        assert namespace["val_evaluator"] == {
            "type": "kitti_eval.KittiMetric",
            "ann_file": "data/kitti/kitti_infos_val.pkl",
        }
    if example.code.startswith("# from .kitti_object_eval_python"):
        assert callable(namespace["kitti_eval"].get_official_eval_result)
    if printed.getvalue():  # what the page says it prints
        assert f"prints `{printed.getvalue().strip()}`" in text(example.page)


# ---------------------------------------------------------------------------------------- every example, run


def _modules_taking_examples() -> list[str]:
    found = []
    for p in sorted(Path(__file__).parents[1].rglob("test_*.py")):  # every folder of tests/
        if "from doc_examples import" in p.read_text("utf-8"):
            if str(p.parent) not in sys.path:
                sys.path.insert(0, str(p.parent))
            found.append(p.stem)
    return found


def test_every_example_is_run_by_a_test_or_says_why_not() -> None:
    for name in _modules_taking_examples():
        importlib.import_module(name)  # each takes its examples as it is imported
    untested, marked_but_run = [], []
    for page in pages():
        for example in examples(page):
            if example.lang not in CHECKED:
                continue
            taken = (example.page, example.line) in TAKEN
            if not taken and example.not_run is None:
                untested.append(str(example))
            if taken and example.not_run is not None:
                marked_but_run.append(f"{example} (run by {TAKEN[(example.page, example.line)]})")
    assert untested == [], (
        "examples no test runs: run each in a test (take() it from tests/helpers/doc_examples.py) or say why not "
        "in a '<!-- not run: REASON -->' line just before it:\n" + "\n".join(untested)
    )
    assert marked_but_run == []


def test_the_finder_sees_every_block() -> None:
    """The check above rests on the finder: a block it missed would pass unrun."""
    fences = sum(text(page).count("\n```") + text(page).startswith("```") for page in pages())
    assert fences == 2 * sum(len(examples(page)) for page in pages())  # every fence opens or closes one


def test_the_quick_start_is_what_ci_runs() -> None:
    """The README's two commands are run by .ci/run, not by a test: the same commands, on the same extra. Its
    test command is the quick one (-m "not slow"); .ci/run runs the slow tests after it, so between the two
    commands it runs every test, once."""
    (quick,) = [e for e in examples("README.md") if e.lang == "bash"][:1]
    assert quick.not_run is not None and ".ci/run" in quick.not_run
    commands = [line.split("#")[0].strip() for line in quick.code.splitlines()]
    assert commands == ['pip install -e ".[test]" && kitti-eval demo', 'python -m pytest -q -m "not slow"']
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'pip install --quiet -e ".[test]"' in ci
    assert '\npython -m pytest -q -m "not slow"\n' in ci and "\nkitti-eval demo > /dev/null\n" in ci
    assert "\npython -m pytest -q -m slow\n" in ci  # the rest: together every test
    runs = [line for line in ci.splitlines() if "pytest" in line and not line.lstrip().startswith("#")]
    assert runs == ['python -m pytest -q -m "not slow"', "python -m pytest -q -m slow"]
    assert "python -m pytest -q -m slow" in text("README.md")  # the README names the second command too
    assert [e.code for e in examples("docs/index.md")][:1] == [quick.code]  # the site's home says the same
