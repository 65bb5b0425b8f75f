"""The store's teams of a hosted benchmark: a team's name, its members (one team per participant per benchmark) and
the participants its maker invited, who join when they accept (the rules are
:mod:`kitti_eval_server.benchmarks.teams`'s). The tables are created with the others (they share
the schema's ``metadata``); a database made before teams gets them when the schema is created."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Column, DateTime, Index, String, Table, delete, func, insert, select

from .database import Area, metadata, retry_when_locked, utc

__all__ = ["TeamRecord", "TeamStore", "TeamRefused", "teams", "team_members", "team_invites"]

#: a benchmark's teams (the benchmark's name: the one its participants address, not a phase's)
teams = Table(
    "teams",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("name", String(64), primary_key=True),
    Column("created_by", String(64), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
)

#: who is in which team: one row per (benchmark, participant), so a participant is in one team of a benchmark
team_members = Table(
    "team_members",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
    Column("team", String(64), nullable=False),
    Column("joined_at", DateTime(timezone=True), nullable=False),
    Index("ix_team_members_team", "benchmark", "team"),
)

#: whom a team's maker invited: they join when they accept (an invitation binds nobody until then)
team_invites = Table(
    "team_invites",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("team", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
    Column("invited_at", DateTime(timezone=True), nullable=False),
    Index("ix_team_invites_participant", "benchmark", "participant"),
)


class TeamRefused(Exception):
    """Not done: the team's name is taken (``taken``), these participants are in a team already (``in_teams``),
    the participant was not invited (``not_invited``) or the team is full (``full``)."""

    def __init__(
        self, *, taken: bool = False, in_teams: Sequence[str] = (), not_invited: bool = False, full: bool = False
    ) -> None:
        super().__init__("team refused")
        self.taken = taken
        self.in_teams = list(in_teams)
        self.not_invited = not_invited
        self.full = full


@dataclass(frozen=True)
class TeamRecord:
    benchmark: str
    name: str
    created_by: str
    created_at: datetime
    members: tuple[str, ...]  # in the order they joined, the maker first
    invited: tuple[str, ...] = ()  # invited, not joined yet


class TeamStore(Area):
    """A benchmark's teams and their members."""

    @retry_when_locked
    def add_team(self, benchmark: str, name: str, created_by: str, invited: Sequence[str], at: datetime) -> None:
        """The team, its maker its first member and the others invited, in one transaction (holding SQLite's
        write lock from its start): raises :class:`TeamRefused`, nothing written, when the name is taken or the
        maker is in a team of the benchmark."""
        members = [created_by]
        with self._writing() as conn:
            taken = conn.execute(
                select(teams.c.name).where(teams.c.benchmark == benchmark, teams.c.name == name)
            ).first()
            if taken is not None:
                raise TeamRefused(taken=True)
            inside = (
                conn.execute(
                    select(team_members.c.participant).where(
                        team_members.c.benchmark == benchmark, team_members.c.participant.in_(members)
                    )
                )
                .scalars()
                .all()
            )
            if inside:
                raise TeamRefused(in_teams=sorted(inside))
            conn.execute(insert(teams).values(benchmark=benchmark, name=name, created_by=created_by, created_at=at))
            conn.execute(
                insert(team_members),
                [{"benchmark": benchmark, "participant": m, "team": name, "joined_at": at} for m in members],
            )
            if invited:
                conn.execute(
                    insert(team_invites),
                    [{"benchmark": benchmark, "team": name, "participant": p, "invited_at": at} for p in invited],
                )

    @retry_when_locked
    def join_team(self, benchmark: str, name: str, participant: str, size: int, at: datetime) -> None:
        """The invited participant joins the team, in one transaction holding the write lock (SQLite) or the team's
        row (PostgreSQL): :class:`TeamRefused` when they were not invited, are in a team already, or the team has
        ``size`` members. Their other invitations in the benchmark are dropped."""
        with self._writing() as conn:
            row = conn.execute(
                select(teams.c.name).where(teams.c.benchmark == benchmark, teams.c.name == name).with_for_update()
            ).first()
            invited = conn.execute(
                select(team_invites.c.team).where(
                    team_invites.c.benchmark == benchmark,
                    team_invites.c.team == name,
                    team_invites.c.participant == participant,
                )
            ).first()
            if row is None or invited is None:
                raise TeamRefused(not_invited=True)
            inside = conn.execute(
                select(team_members.c.team).where(
                    team_members.c.benchmark == benchmark, team_members.c.participant == participant
                )
            ).first()
            if inside is not None:
                raise TeamRefused(in_teams=[participant])
            count = conn.execute(
                select(func.count()).where(team_members.c.benchmark == benchmark, team_members.c.team == name)
            ).scalar_one()
            if count >= size:
                raise TeamRefused(full=True)
            conn.execute(
                insert(team_members).values(benchmark=benchmark, participant=participant, team=name, joined_at=at)
            )
            conn.execute(
                delete(team_invites).where(
                    team_invites.c.benchmark == benchmark, team_invites.c.participant == participant
                )
            )

    @retry_when_locked
    def leave_team(self, benchmark: str, participant: str) -> str | None:
        """The participant leaves their team of the benchmark, in one transaction holding the write lock (SQLite)
        or the team's row (PostgreSQL): the team they left (None: they were in none). A team its last member
        leaves keeps its name (the board names it on the entries made for it) and its invitations are dropped."""
        with self._writing() as conn:
            name = conn.execute(
                select(team_members.c.team).where(
                    team_members.c.benchmark == benchmark, team_members.c.participant == participant
                )
            ).scalar_one_or_none()
            if name is None:
                return None
            conn.execute(
                select(teams.c.name).where(teams.c.benchmark == benchmark, teams.c.name == name).with_for_update()
            ).first()
            conn.execute(
                delete(team_members).where(
                    team_members.c.benchmark == benchmark, team_members.c.participant == participant
                )
            )
            left = conn.execute(
                select(func.count()).where(team_members.c.benchmark == benchmark, team_members.c.team == name)
            ).scalar_one()
            if left == 0:
                conn.execute(
                    delete(team_invites).where(team_invites.c.benchmark == benchmark, team_invites.c.team == name)
                )
            return str(name)

    @retry_when_locked
    def invitations(self, benchmark: str, participant: str) -> list[str]:
        """The teams of the benchmark that invited the participant, by name."""
        query = select(team_invites.c.team).where(
            team_invites.c.benchmark == benchmark, team_invites.c.participant == participant
        )
        with self.engine.connect() as conn:
            return sorted(conn.execute(query).scalars().all())

    @retry_when_locked
    def team_of(self, benchmark: str, participant: str) -> TeamRecord | None:
        """The participant's team in the benchmark, with its members."""
        with self.engine.connect() as conn:
            name = conn.execute(
                select(team_members.c.team).where(
                    team_members.c.benchmark == benchmark, team_members.c.participant == participant
                )
            ).scalar_one_or_none()
        if name is None:
            return None
        found = self.teams(benchmark, name=name)
        return found[0] if found else None

    @retry_when_locked
    def teams(self, benchmark: str, *, name: str | None = None) -> list[TeamRecord]:
        """The benchmark's teams by name (``name``: that one only), each with its members."""
        query = select(teams).where(teams.c.benchmark == benchmark).order_by(teams.c.name)
        members = select(team_members).where(team_members.c.benchmark == benchmark)
        invites = select(team_invites).where(team_invites.c.benchmark == benchmark)
        if name is not None:
            query = query.where(teams.c.name == name)
            members = members.where(team_members.c.team == name)
            invites = invites.where(team_invites.c.team == name)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            people = (
                conn.execute(members.order_by(team_members.c.joined_at, team_members.c.participant)).mappings().all()
            )
            asked = conn.execute(invites.order_by(team_invites.c.participant)).mappings().all()
        by_invite: dict[str, list[str]] = {}
        for a in asked:
            by_invite.setdefault(a["team"], []).append(a["participant"])
        by_team: dict[str, list[str]] = {}
        for p in people:
            by_team.setdefault(p["team"], []).append(p["participant"])
        out = []
        for r in rows:
            listed = by_team.get(r["name"], [])
            maker_first = sorted(listed, key=lambda m: m != r["created_by"])
            invited = tuple(by_invite.get(r["name"], []))
            out.append(
                TeamRecord(
                    r["benchmark"], r["name"], r["created_by"], utc(r["created_at"]), tuple(maker_first), invited
                )
            )
        return out
