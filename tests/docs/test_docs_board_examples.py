"""The shell examples of ``docs/cli/compare-many.md`` and ``docs/service/leaderboard-intervals.md``, run as written
(bash needed; the service's against a live service in accounts mode, curl needed), and what the pages say of
their output checked against it."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from doc_examples import TAKEN, examples, run_bash
from server_helpers import LiveServer

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def _take_all(page: str) -> dict[str, list[str]]:
    """Every bash block of ``page``, recorded as run by this module (see tests/helpers/doc_examples.py)."""
    chosen = [e for e in examples(page) if e.lang == "bash"]
    for e in chosen:
        TAKEN[(e.page, e.line)] = __name__
    return {page: [e.code for e in chosen]}


_TAKEN_HERE = {**_take_all("docs/cli/compare-many.md"), **_take_all("docs/service/leaderboard-intervals.md")}


def _blocks(page: Path) -> list[str]:
    return _TAKEN_HERE[page.relative_to(ROOT).as_posix()]


def _run(script: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return run_bash(script, cwd, timeout=600)


def _ranks(cell: str) -> tuple[int, int]:
    best, _, worst = cell.partition("-")
    return int(best), int(worst or best)


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_the_compare_many_page_runs_as_written(tmp_path: Path) -> None:
    blocks = _blocks(DOCS / "cli" / "compare-many.md")
    assert len(blocks) == 2
    table = _run(blocks[0], tmp_path).stdout.splitlines()
    assert table[0].split()[:3] == ["rank", "result", "Car/3d/moderate/R40/strict"]
    rows = [line.split() for line in table[1:5]]
    assert [r[1].split("/")[1] for r in rows][3] == "blurred"  # the less precise model last
    runs, blurred = rows[:3], rows[3]
    assert blurred[-1] == "4"  # "last with the rank range 4"
    assert [r[-1] == "*" for r in runs] == [False, False, True]  # "the run above it carries the *"
    spans = [_ranks(r[-1] if r[-1] != "*" else r[-2]) for r in runs]
    for i in range(3):
        for j in range(i + 1, 3):
            assert spans[i][0] <= spans[j][1] and spans[j][0] <= spans[i][1], spans  # "their rank ranges overlap"
    printed = _run(blocks[1], tmp_path).stdout
    doc = json.loads((tmp_path / "ranking.json").read_text())
    assert printed.strip() == str([r["rank_range"] for r in doc["results"]])
    assert [r["differs_from_next"] for r in doc["results"]] == [False, False, True, None]
    assert doc["bootstrap"] == {"method": "paired bootstrap over frames", "resamples": 1000, "seed": 0, "level": 0.95}


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl")
def test_the_leaderboard_intervals_page_runs_as_written(tmp_path: Path) -> None:
    blocks = _blocks(DOCS / "service" / "leaderboard-intervals.md")
    assert len(blocks) == 6
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        script = "\n".join(blocks).replace("/srv/kitti-eval", str(server.data_dir))
        script = script.replace("http://127.0.0.1:8000", server.url)
        out = _run(script, tmp_path).stdout
    board = json.loads((tmp_path / "board.json").read_text())
    assert board["bootstrap"]["part"] == "whole" and board["bootstrap"]["pending"] == 0
    assert f"'seed': {board['bootstrap']['seed']}" in out and "interval_low,interval_high,rank_best,rank_worst" in out
    entries = board["entries"]
    # what the page says of them
    assert sorted(e["method"] for e in entries[:2]) == ["run1", "run2"] and entries[2]["method"] == "blurred"
    assert [e["rank_range"] for e in entries] == [[1, 2], [1, 2], [3, 3]]
    assert [e["differs_from_next"] for e in entries] == [False, True, None]
    for e in entries:
        assert f"{e['rank']} {e['method']} {e['key']} {e['interval']} {e['rank_range']}" in out
    comparison = json.loads(re.search(r"^\{\n.*?^\}$", out, re.S | re.M).group(0))  # type: ignore[union-attr]
    leader = comparison["leader"]
    assert leader["method"] == entries[0]["method"] and leader["significant"] is True
    # the command line's interval of the difference, the same to the 4 places both show
    (line,) = [x for x in out.splitlines() if x.startswith("Car/3d/moderate/R40/strict ")]
    low, high = (float(v) for v in re.search(r"\[([-+0-9.]+), ([-+0-9.]+)\]", line).groups())  # type: ignore[union-attr]
    assert [low, high] == leader["interval"]
