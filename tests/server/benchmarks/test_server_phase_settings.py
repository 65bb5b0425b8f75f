"""A phase's range checks (its split, its cap on published entries, the title's and description's lengths) live
in one place: the HTTP route, the admin command and the benchmark file refuse the same value with one sentence."""

from __future__ import annotations

import pytest
from server_helpers import ADMIN, app_client
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval.cli import main
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file
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
