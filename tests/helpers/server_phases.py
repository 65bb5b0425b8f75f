"""Shared by the tests of benchmarks defined by a file: the issue's two-phase file as a host writes it, the
command line's caller that applies it, and a world of three participants with a development set on open labels
(``dev_gt``) and two sealed sets (``test_gt``, ``other_gt``), all the golden ``kitti_infos_val.pkl``."""

from __future__ import annotations

from typing import Any

from server_benchmarks import Hosted, ok
from server_helpers import ADMIN, golden_bytes

from kitti_eval_server.access.policy import Policy

__all__ = ["TWO_PHASES", "HOST", "phased_world"]

#: a benchmark of two phases, as a host would write it (the example the file's keys are documented with)
TWO_PHASES = """\
name = "kitti-phases"
title = "KITTI 3D, two phases"
public = true
key = ["Car/3d/moderate/R40/strict"]
team_size = 3

[[phases]]
name = "dev"
ground_truth = "dev_gt"
quota = "5/1"

[[phases]]
name = "test"
ground_truth = "test_gt"
quota = "2/1"
split_percent = 50
"""

#: who applies a file: the command line's caller (an admin)
HOST = Policy.command_line("host")


def phased_world(c: Any, users: tuple[str, ...] = ("alice", "bob", "carol")) -> Hosted:
    hosted = Hosted()
    for user in users:
        ok(c.post("/v1/admin/users", json={"name": user}, headers=ADMIN), 201)
        hosted.tokens[user] = ok(c.post("/v1/admin/tokens", json={"user": user}, headers=ADMIN), 201)["token"]
    data = golden_bytes("kitti_infos_val.pkl")
    for name, sealed in (("dev_gt", "false"), ("test_gt", "true"), ("other_gt", "true")):
        files = {"file": ("kitti_infos_val.pkl", data)}
        ok(c.post("/v1/ground-truths", data={"name": name, "sealed": sealed}, files=files, headers=ADMIN), 201)
    return hosted
