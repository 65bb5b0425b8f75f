"""A benchmark's teams: a participant makes a team with others who may take part; the quota of each phase is the
team's (every member's accepted submission counts against it, and a member who submitted alone before the team
was made brings those submissions, not a quota of their own); one team per participant per benchmark; the board
names the team of each entry.

The team's members are counted together, and their submissions accepted one after another, under one lock: the
team's (on PostgreSQL the ``quota_locks`` row of (phase, ``team~NAME``); on SQLite the database's write lock).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from ..errors import BadRequest, Conflict, Forbidden, echo
from ..policy import Caller
from ..store import Store
from ..store.team_store import TeamRecord, TeamRefused, TeamStore
from .rules import Benchmark
from .views import TEAM_FIELDS, pick

if TYPE_CHECKING:
    from .catalog import BenchmarkCatalog

__all__ = ["Teams", "quota_team", "team_names", "team_view"]

_TEAM_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 ._-]{0,47}$")


def _store(store: Store) -> TeamStore:
    return TeamStore(store.db)


def quota_team(store: Store, bench: Benchmark, participant: str) -> tuple[str, list[str]] | None:
    """The lock name and members of the participant's team in the benchmark ``bench`` is a phase of (None: not
    in a team): whose submissions count together against the phase's quota."""
    team = _store(store).team_of(bench.shown_name, participant)
    if team is None:
        return None
    return f"team~{team.name}", list(team.members)


def team_names(store: Store, bench: Benchmark) -> dict[str, str]:
    """Participant -> their team's name, in the benchmark ``bench`` is a phase of."""
    return {m: t.name for t in _store(store).teams(bench.shown_name) for m in t.members}


def team_view(team: TeamRecord) -> dict[str, Any]:
    values = {
        "benchmark": team.benchmark,
        "name": team.name,
        "members": list(team.members),
        "created_at": team.created_at.isoformat(),
    }
    return pick(values, TEAM_FIELDS)


class Teams:
    """Making and listing a benchmark's teams, as the policy says."""

    def __init__(self, catalog: BenchmarkCatalog) -> None:
        self.catalog = catalog

    def _benchmark(self, name: str, caller: Caller) -> Benchmark:
        bench = self.catalog.get(name, caller)  # 404 for one the caller does not see
        if bench.is_later_phase:
            return self.catalog.get(bench.shown_name, caller)
        return bench

    def list(self, name: str, caller: Caller) -> dict[str, Any]:
        """The benchmark's teams (for those who may take part in it, and admins), and the caller's own."""
        bench = self._benchmark(name, caller)
        policy = self.catalog.policy
        if not policy.sees_teams(caller, project=bench.project, open_to_all=bench.open_to_all):
            raise Forbidden(f"the teams of {name!r} are seen by those who take part in it")
        found = _store(self.catalog.store).teams(bench.name)
        mine = next((t for t in found if caller.name in t.members), None)
        return {
            "benchmark": bench.name,
            "team_size": bench.team_size,
            "items": [team_view(t) for t in found],
            "mine": team_view(mine) if mine is not None and policy.is_participant(caller) else None,
        }

    def create(self, name: str, team: str, members: Sequence[str], caller: Caller) -> dict[str, Any]:
        """The caller makes the team ``team`` with ``members`` (others who may take part; the caller is in it
        too). Refused when the benchmark takes no teams, the team would be larger than its team size, a member
        may not take part, or someone named is in a team of the benchmark already."""
        policy = self.catalog.policy
        if not policy.is_participant(caller):
            raise Forbidden("a participant makes a team with their own token")
        bench = self._benchmark(name, caller)
        if not policy.may_take_part(caller, project=bench.project, open_to_all=bench.open_to_all) or (
            policy.administers(caller)
        ):
            raise Forbidden(f"a team of {name!r} is made by one who takes part in it")
        if bench.team_size < 2:
            raise Conflict(f"the benchmark {name!r} takes no teams (its team size is 1)")
        team = team.strip()
        if not _TEAM_NAME.fullmatch(team):
            raise BadRequest(
                f"a team's name is 1-48 letters, digits, spaces, '.', '_' or '-', starting with a letter or digit; "
                f"got {echo(team)}"
            )
        everyone = list(dict.fromkeys([caller.name, *(m.strip() for m in members)]))
        if len(everyone) > bench.team_size:
            raise BadRequest(f"a team of {name!r} has at most {bench.team_size} members, its maker included")
        for member in everyone[1:]:
            user = self.catalog.store.get_user(member)
            if not policy.may_join_team(user, project=bench.project, open_to_all=bench.open_to_all):
                raise BadRequest(f"{echo(member)} may not take part in {name!r}: a team is made of its participants")
        try:
            _store(self.catalog.store).add_team(bench.name, team, everyone, caller.name, datetime.now(timezone.utc))
        except TeamRefused as e:
            if e.taken:
                raise Conflict(f"a team named {team!r} exists in {name!r}") from None
            raise Conflict(
                f"one team per participant per benchmark: {', '.join(e.in_teams)} already in a team of {name!r}"
            ) from None
        self.catalog.audit.record(caller, "team.add", f"{bench.name} {team}", detail=",".join(everyone))
        made = _store(self.catalog.store).teams(bench.name, name=team)
        return team_view(made[0])
