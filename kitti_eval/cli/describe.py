"""``kitti-eval describe FILE``: what a ground-truth or prediction file holds, before it is evaluated."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .common import EXIT_OK, emit


def add_parser(sub: Any) -> argparse.ArgumentParser:
    from ..io.describe import KINDS

    p = sub.add_parser(
        "describe",
        help="what a ground-truth or prediction file holds",
        description="Sniff a ground-truth or prediction file: format, frames, boxes per class, "
        "dtypes, dimension order, camera/LiDAR consistency.",
    )
    p.add_argument("file", type=Path, help="a pickle, a KITTI txt folder, or a zip/tar of one")
    p.add_argument("--kind", choices=sorted(KINDS), help="read it as ground truth or predictions (default: guess)")
    p.add_argument("--gt", type=Path, help="infos with calibration, to check prediction locations against boxes_lidar")
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..io.describe import describe

    emit(describe(args.file, args.kind, args.gt), None)
    return EXIT_OK
