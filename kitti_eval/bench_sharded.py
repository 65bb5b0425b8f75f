"""``python -m kitti_eval.bench_sharded``: the sharded speed benchmark under the name the commands in the
README use; it is :mod:`kitti_eval.speed_sharded`."""

from __future__ import annotations

from .speed_sharded import main

if __name__ == "__main__":
    raise SystemExit(main())
