"""The service asks the library, never a copy of it: the same options, rules and answers as the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest
from server_helpers import app_client, upload

from kitti_eval.cli import _config, _parser
from kitti_eval.errors import ConfigError
from kitti_eval_server.scoring.evaluator import EvalOptions

#: (CLI flags, the same as the service's form fields)
_OPTIONS = [
    ([], {}),
    (["--classes", "Car,Van", "--protocol", "openpcdet"], {"classes": "Car,Van", "protocol": "openpcdet"}),
    (
        ["--iou", "Car=0.7,0.6,0.6", "--iou", "Car:loose=0.5,0.3,0.3"],
        {"iou": ("Car=0.7,0.6,0.6", "Car:loose=0.5,0.3,0.3")},
    ),
    (
        ["--classes", "Car,Bus", "--iou", "Bus=0.7,0.7,0.7", "--ranges", "0,30,inf", "--coco"],
        {"classes": "Car,Bus", "iou": ("Bus=0.7,0.7,0.7",), "ranges": "0,30,inf", "coco": True},
    ),
    (["--lidar-only", "--classes", " Car , Pedestrian "], {"lidar_only": True, "classes": " Car , Pedestrian "}),
]


def _cli(flags: list[str]):  # noqa: ANN202 - an EvalConfig
    return _config(_parser().parse_args(["--gt", "g", "--pred", "p", *flags]))


@pytest.mark.parametrize("flags, fields", _OPTIONS)
def test_options_read_the_same_through_the_cli_and_the_service(flags: list[str], fields: dict) -> None:
    defaults = {"classes": None, "protocol": None}  # the service's own defaults equal the library's
    options = EvalOptions(**{**{k: v for k, v in defaults.items() if v is not None}, **fields})
    assert _cli(flags) == options.config()


@pytest.mark.parametrize(
    "flags, fields",
    [
        (["--iou", "Car=0.7,0.6"], {"iou": ("Car=0.7,0.6",)}),
        (["--ranges", "30,0"], {"ranges": "30,0"}),
        (["--classes", "Bus"], {"classes": "Bus"}),
    ],
)
def test_bad_options_are_refused_with_the_same_words(flags: list[str], fields: dict, capsys) -> None:
    """The same rule refuses them (the CLI reports a malformed --iou as a usage error, exit 2)."""
    with pytest.raises(ConfigError) as service_error:
        EvalOptions(**fields).config()
    with pytest.raises((ConfigError, SystemExit)) as cli_error:
        _cli(flags)
    cli_text = str(cli_error.value) if isinstance(cli_error.value, ConfigError) else capsys.readouterr().err
    assert str(service_error.value).removeprefix("iou: ") in cli_text


def _two_demo_evaluations(client) -> list[str]:  # noqa: ANN001 - a TestClient
    from kitti_eval.demo import demo_paths

    data = demo_paths()[1].read_bytes()
    return [upload(client, data, "result.pkl.gz").json()["id"] for _ in range(2)]


@pytest.mark.parametrize(
    "body, flags",
    [
        ({"min": ["Car/3d/moderate >= 10"]}, ["--min", "Car/3d/moderate >= 10"]),
        (
            {"min": ["Car/3d/moderate >= 99"], "require_classes": ["Cyclist", "Truck"]},
            ["--min", "Car/3d/moderate >= 99", "--require-class", "Cyclist", "--require-class", "Truck"],
        ),
        ({"max_drop": ["0.5", "Car/bev/hard=0.1"]}, ["--max-drop", "0.5", "--max-drop", "Car/bev/hard=0.1"]),
    ],
)
def test_gate_verdicts_equal_the_clis(body: dict, flags: list[str], tmp_path: Path) -> None:
    """The same rules on the same two results: the service's JUnit report is the CLI's, to the byte."""
    from kitti_eval import cli
    from kitti_eval.demo import demo_paths

    with app_client(tmp_path / "data") as client:
        current, base = _two_demo_evaluations(client)
        answer = client.post(
            "/v1/gates", params={"format": "junit"}, json={"evaluation": current, "baseline": base, **body}
        )
    gt, pred = demo_paths()
    junit = tmp_path / "gate.xml"
    code = cli.main(
        ["gate", "--gt", str(gt), "--pred", str(pred), "--baseline", str(pred), *flags, "--junit", str(junit)]
    )
    assert (answer.status_code, code) in ((200, 0), (412, 3))
    assert answer.text == junit.read_text()


def test_gate_rules_are_refused_with_the_same_words(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from kitti_eval import cli
    from kitti_eval.demo import demo_paths

    gt, pred = demo_paths()
    with app_client(tmp_path / "data") as client:
        current, _ = _two_demo_evaluations(client)
        for body, flags in (
            ({}, []),
            ({"max_drop": ["0.5"]}, ["--max-drop", "0.5"]),
            ({"min": ["Car/3d >= 1"]}, ["--min", "Car/3d >= 1"]),
        ):
            message = client.post("/v1/gates", json={"evaluation": current, **body}).json()["error"]["message"]
            assert cli.main(["gate", "--gt", str(gt), "--pred", str(pred), *flags]) == 2
            assert message in capsys.readouterr().err


def test_the_services_comparison_is_the_clis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The service's comparison of two stored evaluations is what ``kitti-eval compare`` prints for the
    same two results (JSON and Markdown), plus the records' sides."""
    import json

    from kitti_eval import cli

    with app_client(tmp_path / "data") as client:
        first, second = _two_demo_evaluations(client)
        docs = [client.get(f"/v1/evaluations/{i}").json() for i in (first, second)]
        answer = client.get(f"/v1/evaluations/{first}/compare/{second}").json()
        markdown = client.get(f"/v1/evaluations/{first}/compare/{second}", params={"format": "markdown"}).text
    paths = []
    for k, doc in enumerate(docs):
        paths.append(tmp_path / f"{k}.json")
        paths[-1].write_text(json.dumps({key: doc[key] for key in doc if key not in ("id", "evaluation")}))
    assert cli.main(["compare", str(paths[0]), str(paths[1]), "--format", "json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert {k: v for k, v in answer.items() if k not in ("base", "other")} == printed
    assert answer["base"]["id"] == first and answer["other"]["id"] == second
    assert cli.main(["compare", str(paths[0]), str(paths[1]), "--format", "markdown"]) == 0
    # the same table, its columns headed with the evaluations' names where the command heads them with the files'
    head = "| value | 0.json | 1.json |"
    printed_markdown = capsys.readouterr().out
    assert printed_markdown.startswith(head)
    names = f"| value | {first[:8]} | {second[:8]} |"  # no model label: their ids' first characters
    assert printed_markdown.replace(head, names, 1) in markdown
