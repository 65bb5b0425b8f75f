"""``kitti-eval validate --benchmark`` against a benchmark whose current phase is on open labels speaks of its
validation set, as the service does; against a sealed one, of its test set."""

from __future__ import annotations

import urllib.request

import pytest
from server_helpers import app_client, golden_txt, zip_of
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval.cli import main
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file


class _Answer:
    """What urlopen hands back, from the in-process service's answer."""

    def __init__(self, body: bytes) -> None:
        self.body = body

    def read(self, limit: int = -1) -> bytes:
        return self.body

    def __enter__(self) -> _Answer:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


@pytest.mark.parametrize(
    ("text", "word"), [(TWO_PHASES, "validation"), (TWO_PHASES.replace("dev_gt", "other_gt"), "test")]
)
def test_validate_names_the_current_phases_set(tmp_path, monkeypatch, capsys, text, word) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        phased_world(c)
        apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST)
        asked = []

        def urlopen(request: urllib.request.Request, timeout: float) -> _Answer:
            path = request.full_url.split("//", 1)[1].split("/", 1)[1]
            asked.append(path)
            return _Answer(c.get("/" + path).content)

        monkeypatch.setattr(urllib.request, "urlopen", urlopen)
        broken = tmp_path / "broken.zip"
        broken.write_bytes(zip_of(dict(list(golden_txt("pred.tar.gz").items())[1:])))  # one frame missing
        capsys.readouterr()
        assert main(["validate", str(broken), "--benchmark", "http://bench.example/benchmarks/kitti-phases"]) == 1
        assert asked == ["v1/benchmarks/kitti-phases/frames"]
        assert f"1 {word} frames are missing: 000000" in capsys.readouterr().err
