"""What docs/service/benchmarks.md says a participant's list of submissions and the leaderboard's CSV hold,
checked against what the service answers: every field and column the answers have is named on the page."""

from __future__ import annotations

import ast
import csv
import io
import re
from pathlib import Path

from server_benchmarks import host, ok, submit
from server_helpers import app_client, golden_bytes

from kitti_eval_server.store.benchmark_store import SUBMISSION_STATUSES

ROOT = Path(__file__).resolve().parents[2]
SERVER = ROOT / "server"
PAGE = (ROOT / "docs" / "service" / "benchmarks.md").read_text(encoding="utf-8")


def _paragraph(opening: str) -> str:
    """The list item of the page that holds ``opening``, joined into one line."""
    start = PAGE.index(opening)
    end = PAGE.find("\n* ", start)
    return " ".join(PAGE[start:end].split())


def test_the_page_names_a_submission_s_statuses_and_the_service_sets_no_other() -> None:
    """The page's ``status`` values are the store's, in their order, and the service's code writes no other
    (every ``status="..."`` and ``"status": "..."`` of the benchmarks' wing and the store)."""
    said = _paragraph("* **Submitting**")
    listed = re.search(r"`status`\s*\(([^)]*)\)", said)
    assert listed, "the page no longer lists a submission's statuses"
    assert tuple(re.findall(r"`([a-z]+)`", listed.group(1).split("with its")[0])) == SUBMISSION_STATUSES
    written = set()
    for path in [*sorted((SERVER / "benchmarks").glob("*.py")), SERVER / "store" / "benchmark_store.py"]:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.keyword) and node.arg == "status" and isinstance(node.value, ast.Constant):
                written.add(node.value.value)
            if isinstance(node, ast.Dict):
                for key, value in zip(node.keys, node.values):
                    if isinstance(key, ast.Constant) and key.value == "status" and isinstance(value, ast.Constant):
                        written.add(value.value)
    assert written and written <= set(SUBMISSION_STATUSES), written


def test_the_submissions_list_and_the_csv_are_documented_field_by_field(tmp_path: Path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"quota": "1/1"})
        made = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
        ok(
            c.post(
                f"/v1/benchmarks/bench/submissions/{made['id']}/publish",
                json={"method": "M"},
                headers=hosted.headers("alice"),
            )
        )
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))
        table = c.get("/v1/benchmarks/bench/leaderboard", params={"format": "csv"}).text
    said = _paragraph("* **Submitting**")
    named = set(re.findall(r"`([a-z_0-9]+)`", said))
    assert set(mine) <= named, set(mine) - named
    assert set(mine["quota"]) <= named, set(mine["quota"]) - named
    assert set(mine["items"][0]) <= named, set(mine["items"][0]) - named
    assert mine["quota"]["left"] == 0 and mine["quota"]["next_at"] is not None
    header = next(csv.reader(io.StringIO(table)))
    assert len(set(header)) == len(header)  # no name twice (the key's column once was its column's name)
    columns_said = _paragraph("* **Leaderboard.**")
    fixed = [h for h in header if "/" not in h]
    assert all(f"`{h}`" in columns_said for h in fixed), [h for h in fixed if f"`{h}`" not in columns_said]
    assert header[7] == "key (Car/3d/moderate/R40/strict)" and f"`{header[7]}`" in columns_said
