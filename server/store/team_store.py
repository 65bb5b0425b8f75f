"""The store's teams of a hosted benchmark: a team's name and its members, one team per participant per benchmark
(the rules are :mod:`kitti_eval_server.benchmarks.teams`'s). The tables are created with the others (they share
the schema's ``metadata``); a database made before teams gets them when the schema is created."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Column, DateTime, Index, String, Table, insert, select

from .database import Area, metadata, retry_when_locked, utc

__all__ = ["TeamRecord", "TeamStore", "TeamRefused", "teams", "team_members"]

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


class TeamRefused(Exception):
    """The team was not made: its name is taken (``taken``), or these participants are in a team already."""

    def __init__(self, *, taken: bool = False, in_teams: Sequence[str] = ()) -> None:
        super().__init__("team name taken" if taken else f"in a team already: {', '.join(in_teams)}")
        self.taken = taken
        self.in_teams = list(in_teams)


@dataclass(frozen=True)
class TeamRecord:
    benchmark: str
    name: str
    created_by: str
    created_at: datetime
    members: tuple[str, ...]  # in the order they joined, the maker first


class TeamStore(Area):
    """A benchmark's teams and their members."""

    @retry_when_locked
    def add_team(self, benchmark: str, name: str, members: Sequence[str], created_by: str, at: datetime) -> None:
        """The team and its members in one transaction (holding SQLite's write lock from its start): raises
        :class:`TeamRefused`, nothing written, when the name is taken or a member is in a team of the benchmark."""
        with self._writing() as conn:
            taken = conn.execute(
                select(teams.c.name).where(teams.c.benchmark == benchmark, teams.c.name == name)
            ).first()
            if taken is not None:
                raise TeamRefused(taken=True)
            inside = (
                conn.execute(
                    select(team_members.c.participant).where(
                        team_members.c.benchmark == benchmark, team_members.c.participant.in_(list(members))
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
        if name is not None:
            query = query.where(teams.c.name == name)
            members = members.where(team_members.c.team == name)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            people = (
                conn.execute(members.order_by(team_members.c.joined_at, team_members.c.participant)).mappings().all()
            )
        by_team: dict[str, list[str]] = {}
        for p in people:
            by_team.setdefault(p["team"], []).append(p["participant"])
        out = []
        for r in rows:
            listed = by_team.get(r["name"], [])
            maker_first = sorted(listed, key=lambda m: m != r["created_by"])
            out.append(TeamRecord(r["benchmark"], r["name"], r["created_by"], utc(r["created_at"]), tuple(maker_first)))
        return out
