"""The service asks the library, never a copy of it: the same options, rules and answers as the CLI."""

from __future__ import annotations

import pytest

from kitti_eval.cli import _config, _parser
from kitti_eval.errors import ConfigError
from server.evaluator import EvalOptions

#: (CLI flags, the same as the service's form fields)
_OPTIONS = [
    ([], {}),
    (["--classes", "Car,Van", "--protocol", "openpcdet"], {"classes": "Car,Van", "protocol": "openpcdet"}),
    (["--iou", "Car=0.7,0.6,0.6", "--iou", "Car:loose=0.5,0.3,0.3"],
     {"iou": ("Car=0.7,0.6,0.6", "Car:loose=0.5,0.3,0.3")}),
    (["--classes", "Car,Bus", "--iou", "Bus=0.7,0.7,0.7", "--ranges", "0,30,inf", "--coco"],
     {"classes": "Car,Bus", "iou": ("Bus=0.7,0.7,0.7",), "ranges": "0,30,inf", "coco": True}),
    (["--lidar-only", "--classes", " Car , Pedestrian "], {"lidar_only": True, "classes": " Car , Pedestrian "}),
]


def _cli(flags: list[str]):  # noqa: ANN202 - an EvalConfig
    return _config(_parser().parse_args(["--gt", "g", "--pred", "p", *flags]))


@pytest.mark.parametrize("flags, fields", _OPTIONS)
def test_options_read_the_same_through_the_cli_and_the_service(flags: list[str], fields: dict) -> None:
    defaults = {"classes": None, "protocol": None}  # the service's own defaults equal the library's
    options = EvalOptions(**{**{k: v for k, v in defaults.items() if v is not None}, **fields})
    assert _cli(flags) == options.config()


@pytest.mark.parametrize("flags, fields", [
    (["--iou", "Car=0.7,0.6"], {"iou": ("Car=0.7,0.6",)}),
    (["--ranges", "30,0"], {"ranges": "30,0"}),
    (["--classes", "Bus"], {"classes": "Bus"}),
])
def test_bad_options_are_refused_with_the_same_words(flags: list[str], fields: dict, capsys) -> None:
    """The same rule refuses them (the CLI reports a malformed --iou as a usage error, exit 2)."""
    with pytest.raises(ConfigError) as service_error:
        EvalOptions(**fields).config()
    with pytest.raises((ConfigError, SystemExit)) as cli_error:
        _cli(flags)
    cli_text = str(cli_error.value) if isinstance(cli_error.value, ConfigError) else capsys.readouterr().err
    assert str(service_error.value).removeprefix("iou: ") in cli_text
