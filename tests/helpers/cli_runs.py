"""The CLI run in process for its JSON document, as the parity tests compare it with the service's."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from kitti_eval.cli import main


def cli_json(gt: Path | str, pred: Path | str, out_dir: Path, *flags: str) -> dict[str, Any]:
    """``kitti-eval --gt GT --pred PRED --format json --quiet FLAGS`` written to a new file in ``out_dir``: the exit
    code asserted 0, the document returned."""
    fd, name = tempfile.mkstemp(prefix="cli-", suffix=".json", dir=out_dir)
    os.close(fd)
    out = Path(name)
    argv = ["--gt", str(gt), "--pred", str(pred), "--format", "json", "--output", str(out), "--quiet", *flags]
    assert main(argv) == 0
    doc: dict[str, Any] = json.loads(out.read_text())
    return doc
