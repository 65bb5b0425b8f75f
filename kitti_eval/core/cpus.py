"""The threads an evaluation's matchings use: ``$KITTI_EVAL_THREADS``, else the CPUs this process may use (its
affinity, within a container's or a cgroup's CPU quota)."""

from __future__ import annotations

import math
import os

__all__ = ["default_workers", "available_cpus", "cgroup_cpu_quota"]


def default_workers() -> int:
    """Threads used for the matchings: ``$KITTI_EVAL_THREADS``, else the CPUs this process may use."""
    env = os.environ.get("KITTI_EVAL_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    return available_cpus()


def available_cpus() -> int:
    """The CPUs this process may use: those it may run on, and no more than its CPU quota (a container's
    ``--cpus``, a Kubernetes CPU limit: cgroup v2's ``cpu.max``, or v1's CFS quota), rounded up."""
    try:
        cpus = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
    quota = cgroup_cpu_quota()
    return cpus if quota is None else max(1, min(cpus, math.ceil(quota)))


def cgroup_cpu_quota(root: str = "/sys/fs/cgroup") -> float | None:
    """The CPUs the cgroup of this process may use in a period (quota / period), or None when unlimited or
    unknown."""
    try:
        with open(f"{root}/cpu.max", encoding="ascii") as fh:  # cgroup v2: "<quota|max> <period>"
            quota, period = fh.read().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:  # cgroup v1
        with (
            open(f"{root}/cpu/cpu.cfs_quota_us", encoding="ascii") as q,
            open(f"{root}/cpu/cpu.cfs_period_us", encoding="ascii") as p,
        ):
            v1_quota, v1_period = int(q.read()), int(p.read())
        return None if v1_quota <= 0 or v1_period <= 0 else v1_quota / v1_period
    except (OSError, ValueError):
        return None
