"""``python -m kitti_eval.bench``: the speed benchmark under the name the commands in the README use; it is
:mod:`kitti_eval.speed` (``--sharded``: :mod:`kitti_eval.speed_sharded`)."""

from __future__ import annotations

from .speed import main

if __name__ == "__main__":
    raise SystemExit(main())
