"""A benchmark's teams: a participant makes a team and invites others who may take part, who join when they accept
(an invitation binds nobody: no one is put in a team, or made to share a quota, without saying so); the quota of
each phase is the team's (every member's accepted submission counts against it, and a member who submitted alone
before joining brings those submissions, not a quota of their own); one team per participant per benchmark; the
board names the team each entry counted for, recorded on the submission when it was accepted.

A member may leave their team until the benchmark's last phase has closed. Leaving frees no quota: what was
submitted for the team still counts against the team's quota, and against the leaver's own (their submissions
are theirs whichever team they counted for), for as long as it is in the quota's window.

The team's members are counted together, and their submissions accepted one after another, under one lock: the
team's (on PostgreSQL the ``quota_locks`` row of (phase, ``team~NAME``); on SQLite the database's write lock).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from ..access.policy import Caller, may_join_team, sees_teams
from ..errors import BadRequest, Conflict, Forbidden, NotFound, echo
from ..store import AccountStore, BenchmarkStore, QuotaTeam, SubmissionRecord
from ..store.team_store import TeamRecord, TeamRefused, TeamStore
from .benchmark import Benchmark
from .lifecycle import PhaseState
from .phases import last_phase
from .views import OWN_TEAM_FIELDS, TEAM_FIELDS, pick

if TYPE_CHECKING:
    from .catalog import BenchmarkCatalog

__all__ = ["Teams", "quota_team", "entry_teams", "team_view"]

_TEAM_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 ._-]{0,47}$")


def _store(area: BenchmarkStore) -> TeamStore:
    """The teams' area on the database of ``area`` (the benchmarks', which submissions and boards are given)."""
    return TeamStore(area.db)


def quota_team(store: BenchmarkStore, bench: Benchmark, participant: str) -> QuotaTeam | None:
    """The participant's team in the benchmark ``bench`` is a phase of (None: not in a team; a benchmark whose
    team size is 1 takes no teams): whose submissions count together against the phase's quota, and whom a
    submission accepted now counts for."""
    if bench.team_size < 2:
        return None
    team = _store(store).team_of(bench.shown_name, participant)
    if team is None:
        return None
    return QuotaTeam(team.name, team.members)


def entry_teams(bench: Benchmark, submissions: Sequence[SubmissionRecord]) -> dict[str, str]:
    """Submission id -> the team it counted for, recorded when it was accepted, in the benchmark ``bench`` is a
    phase of (none when it takes no teams): who joins or leaves later relabels none of the entries made."""
    if bench.team_size < 2:
        return {}
    return {submission.id: submission.team for submission in submissions if submission.team is not None}


def team_view(team: TeamRecord, *, own: bool = False) -> dict[str, Any]:
    """A team as those who see the benchmark's teams read it; ``own``: as its members read it, with whom it
    invited."""
    values = {
        "benchmark": team.benchmark,
        "name": team.name,
        "members": list(team.members),
        "invited": list(team.invited),
        "created_at": team.created_at.isoformat(),
    }
    return pick(values, OWN_TEAM_FIELDS if own else TEAM_FIELDS)


class Teams:
    """Making and listing a benchmark's teams, as the policy says."""

    def __init__(self, catalog: BenchmarkCatalog, team_store: TeamStore, account_store: AccountStore) -> None:
        """``account_store``: who may be invited (an account that may take part)."""
        self.catalog = catalog
        self.team_store = team_store
        self.account_store = account_store

    def _benchmark(self, name: str, caller: Caller) -> Benchmark:
        bench = self.catalog.get(name, caller)  # 404 for one the caller does not see
        if bench.is_later_phase:
            return self.catalog.get(bench.shown_name, caller)
        return bench

    def list(self, name: str, caller: Caller) -> dict[str, Any]:
        """The benchmark's teams (for those who may take part in it, and admins), and the caller's own."""
        bench = self._benchmark(name, caller)
        policy = self.catalog.policy
        if not sees_teams(
            policy, caller, benchmark=bench.shown_name, project=bench.project, open_to_all=bench.open_to_all
        ):
            raise Forbidden(f"the teams of {name!r} are seen by those who take part in it")
        store = self.team_store
        found = store.teams(bench.name)
        participant = policy.is_participant(caller)
        mine = next((t for t in found if caller.name in t.members), None) if participant else None
        return {
            "benchmark": bench.name,
            "team_size": bench.team_size,
            "items": [team_view(t) for t in found],
            "mine": team_view(mine, own=True) if mine is not None else None,
            "invitations": store.invitations(bench.name, caller.name) if participant and mine is None else [],
        }

    def _taking_part(self, name: str, caller: Caller, doing: str, *, teams_taken: bool = True) -> Benchmark:
        """The benchmark whose teams the caller changes (``doing``), refused when they do not take part in it, it
        takes no teams (unless ``teams_taken`` is False: one may leave a team of a benchmark whose team size has
        shrunk to 1) or its last phase has closed (as the lifecycle says)."""
        policy = self.catalog.policy
        if not policy.is_participant(caller):
            raise Forbidden(f"a participant {doing} with their own token")
        bench = self._benchmark(name, caller)
        if not policy.may_take_part(
            caller, benchmark=bench.shown_name, project=bench.project, open_to_all=bench.open_to_all
        ) or (policy.administers(caller)):
            raise Forbidden(f"one who takes part in {name!r} {doing}")
        if teams_taken and bench.team_size < 2:
            raise Conflict(f"the benchmark {name!r} takes no teams (its team size is 1)")
        last = last_phase(self.catalog, bench)
        if last.state() in (PhaseState.CLOSED, PhaseState.REVEALED):
            raise Conflict(
                f"the benchmark {name!r} has closed (its last phase, {last.phase_name!r}, is {last.state().value}): "
                "its teams no longer change"
            )
        return bench

    def create(self, name: str, team: str, members: Sequence[str], caller: Caller) -> dict[str, Any]:
        """The caller makes the team ``team`` (they are its first member) and invites ``members`` (others who may
        take part), who join when they accept (:meth:`join`). Refused when the benchmark takes no teams, the team
        would be larger than its team size, one invited may not take part, or the caller is in a team of the
        benchmark already."""
        bench = self._taking_part(name, caller, "makes a team")
        if self.team_store.team_of(bench.name, caller.name) is not None:  # said first; the insert checks
            raise Conflict(f"one team per participant per benchmark: you are in a team of {name!r}")
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
            user = self.account_store.get_user(member)
            if not may_join_team(
                user, benchmark=bench.shown_name, project=bench.project, open_to_all=bench.open_to_all
            ) or (
                self.team_store.team_of(bench.name, member) is not None
            ):  # one refusal whoever it is (missing, an admin, not taking part, in a team): it names no one
                raise BadRequest(
                    f"one of those invited may not join a team of {name!r}: a team invites participants of the "
                    "benchmark who are in no team of it"
                )
        store = self.team_store
        try:
            store.add_team(bench.name, team, caller.name, everyone[1:], datetime.now(timezone.utc))
        except TeamRefused as e:
            if e.taken:
                raise Conflict(f"a team named {team!r} exists in {name!r}") from None
            raise Conflict(f"one team per participant per benchmark: you are in a team of {name!r}") from None
        self.catalog.audit.record(
            caller, "team.add", f"{bench.name} {team}", detail="invited " + ",".join(everyone[1:])
        )
        return team_view(store.teams(bench.name, name=team)[0], own=True)

    def join(self, name: str, team: str, caller: Caller) -> dict[str, Any]:
        """The caller joins the team ``team``, which invited them: from then on what they submit, and what they
        submitted alone in the quota's window, counts against the team's quota. Refused when they were not
        invited (404, as a team that does not exist), are in a team of the benchmark, or the team is full."""
        bench = self._taking_part(name, caller, "joins a team")
        store = self.team_store
        try:
            store.join_team(bench.name, team, caller.name, bench.team_size, datetime.now(timezone.utc))
        except TeamRefused as e:
            if e.not_invited:
                raise NotFound(f"no team {echo(team)} of {name!r} invited you") from None
            if e.full:
                raise Conflict(f"the team {team!r} has its {bench.team_size} members") from None
            raise Conflict(f"one team per participant per benchmark: you are in a team of {name!r}") from None
        self.catalog.audit.record(caller, "team.join", f"{bench.name} {team}")
        return team_view(store.teams(bench.name, name=team)[0], own=True)

    def leave(self, name: str, caller: Caller) -> dict[str, Any]:
        """The caller leaves their team: what they submit from then on counts against their own quota, and what
        they submitted for the team still counts against the team's and their own (leaving frees no quota); the
        board keeps naming the team on the entries made for it. Refused when they are in no team (404) or the
        benchmark's last phase has closed (409): its teams no longer change."""
        bench = self._taking_part(name, caller, "leaves a team", teams_taken=False)
        left = self.team_store.leave_team(bench.name, caller.name)
        if left is None:
            raise NotFound(f"you are in no team of {name!r}")
        self.catalog.audit.record(caller, "team.leave", f"{bench.name} {left}")
        found = self.team_store.teams(bench.name, name=left)
        return {"benchmark": bench.name, "left": left, "members": list(found[0].members) if found else []}
