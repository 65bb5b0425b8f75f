"""The store's accounts: users, projects and memberships, tokens and web sessions, and the audit log."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

from sqlalchemy import delete, func, insert, select, update
from sqlalchemy.engine import Connection, RowMapping
from sqlalchemy.exc import IntegrityError

from .database import (
    Area,
    audit,
    invitation_accounts,
    invitations,
    memberships,
    projects,
    retry_when_locked,
    tokens,
    users,
    utc,
)

__all__ = ["UserRecord", "TokenRecord", "AuditRecord", "AccountStore", "names_taken"]


@dataclass(frozen=True)
class UserRecord:
    name: str
    is_admin: bool
    created_at: datetime
    projects: tuple[str, ...] = ()
    #: the benchmark (its name as participants address it) of the invitation that made the account, which is the
    #: only one it takes part in; None for an account an admin made (by hand or by an import)
    invited_to: str | None = None


@dataclass(frozen=True)
class TokenRecord:
    id: str
    user_name: str
    kind: str
    parent: str | None
    secret_sha256: str
    scopes: str
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None


@dataclass(frozen=True)
class AuditRecord:
    id: int
    at: datetime
    actor: str
    action: str
    target: str
    outcome: str
    client: str
    detail: str


def names_taken(conn: Connection, names: Sequence[str]) -> list[str]:
    """Which of ``names`` a new account may not take: those equal to an existing user's name ignoring case (``Ana``
    beside ``ana`` would read as the same person on a board and in the audit log). Every way an account is made
    asks this; accounts made before the rule are left as they are."""
    lowered = sorted({n.lower() for n in names})
    taken = set(conn.execute(select(func.lower(users.c.name)).where(func.lower(users.c.name).in_(lowered))).scalars())
    return sorted(n for n in names if n.lower() in taken)


class AccountStore(Area):
    """Who may do what: users, projects, memberships, tokens and sessions; and what admins did."""

    @retry_when_locked
    def add_user(self, name: str, is_admin: bool) -> bool:
        """False if the name is taken (:func:`names_taken`: ignoring case)."""
        try:
            with self._writing() as conn:
                if names_taken(conn, [name]):
                    return False
                conn.execute(insert(users).values(name=name, is_admin=is_admin, created_at=datetime.now(timezone.utc)))
        except IntegrityError:  # made meanwhile
            return False
        return True

    @retry_when_locked
    def get_user(self, name: str) -> UserRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(users).where(users.c.name == name)).mappings().first()
            if row is None:
                return None
            member_of = self._projects_of(conn, name)
            invited_to = self._invited_to(conn, name).get(name)
        return UserRecord(row["name"], bool(row["is_admin"]), utc(row["created_at"]), member_of, invited_to)

    @retry_when_locked
    def list_users(self) -> list[UserRecord]:
        with self.engine.connect() as conn:
            rows = conn.execute(select(users).order_by(users.c.name)).mappings().all()
            pairs = conn.execute(select(memberships).order_by(memberships.c.project)).all()
            invited_to = self._invited_to(conn)
        member_of: dict[str, list[str]] = {}
        for user_name, project in pairs:
            member_of.setdefault(user_name, []).append(project)
        return [
            UserRecord(
                r["name"],
                bool(r["is_admin"]),
                utc(r["created_at"]),
                tuple(member_of.get(r["name"], ())),
                invited_to.get(r["name"]),
            )
            for r in rows
        ]

    @staticmethod
    def _invited_to(conn: Connection, user_name: str | None = None) -> dict[str, str]:
        """User -> the benchmark of the invitation that made the account (one user's, or every user's)."""
        query = select(invitation_accounts.c.user_name, invitations.c.benchmark).join(
            invitations, invitations.c.id == invitation_accounts.c.invitation
        )
        if user_name is not None:
            query = query.where(invitation_accounts.c.user_name == user_name)
        return {str(name): str(benchmark) for name, benchmark in conn.execute(query)}

    @staticmethod
    def _projects_of(conn: Any, user_name: str) -> tuple[str, ...]:
        rows = conn.execute(
            select(memberships.c.project).where(memberships.c.user_name == user_name).order_by(memberships.c.project)
        )
        return tuple(r[0] for r in rows)

    @retry_when_locked
    def add_project(self, name: str) -> bool:
        return self._insert(projects, name=name, created_at=datetime.now(timezone.utc))

    @retry_when_locked
    def project_exists(self, name: str) -> bool:
        with self.engine.connect() as conn:
            return conn.execute(select(projects.c.name).where(projects.c.name == name)).first() is not None

    @retry_when_locked
    def list_projects(self) -> list[str]:
        with self.engine.connect() as conn:
            return [r[0] for r in conn.execute(select(projects.c.name).order_by(projects.c.name))]

    @retry_when_locked
    def add_membership(self, user_name: str, project: str) -> bool:
        return self._insert(memberships, user_name=user_name, project=project)

    @retry_when_locked
    def remove_membership(self, user_name: str, project: str) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(
                delete(memberships).where(memberships.c.user_name == user_name, memberships.c.project == project)
            )
        return bool(done.rowcount)

    @retry_when_locked
    def add_token(self, record: TokenRecord) -> None:
        with self.engine.begin() as conn:
            conn.execute(insert(tokens).values(**record.__dict__))

    @retry_when_locked
    def get_token(self, token_id: str) -> TokenRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(tokens).where(tokens.c.id == token_id)).mappings().first()
        return None if row is None else self._token(row)

    @retry_when_locked
    def list_tokens(self, user_name: str | None = None) -> list[TokenRecord]:
        query = select(tokens).where(tokens.c.kind == "token").order_by(tokens.c.created_at)
        if user_name is not None:
            query = query.where(tokens.c.user_name == user_name)
        with self.engine.connect() as conn:
            return [self._token(r) for r in conn.execute(query).mappings().all()]

    @retry_when_locked
    def revoke_token(self, token_id: str) -> bool:
        """Revoke a token and the sessions opened with it; False if there is no such token."""
        now = datetime.now(timezone.utc)
        with self.engine.begin() as conn:
            found = conn.execute(select(tokens.c.id).where(tokens.c.id == token_id)).first()
            if found is None:
                return False
            conn.execute(
                update(tokens)
                .where((tokens.c.id == token_id) | (tokens.c.parent == token_id), tokens.c.revoked_at.is_(None))
                .values(revoked_at=now)
            )
        return True

    @retry_when_locked
    def purge_sessions(self, before: datetime) -> int:
        """Delete the web sessions that expired or were revoked before ``before``; how many."""
        with self.engine.begin() as conn:
            done = conn.execute(
                delete(tokens).where(
                    tokens.c.kind == "session", (tokens.c.expires_at < before) | (tokens.c.revoked_at < before)
                )
            )
        return int(done.rowcount or 0)

    @staticmethod
    def _token(row: RowMapping) -> TokenRecord:
        values = dict(row)
        for key in ("created_at", "expires_at", "revoked_at"):
            if values[key] is not None:
                values[key] = utc(values[key])
        return TokenRecord(**values)

    @retry_when_locked
    def add_audit(self, *, actor: str, action: str, target: str, outcome: str, client: str, detail: str) -> None:
        with self.engine.begin() as conn:
            self.add_audit_in(
                conn, actor=actor, action=action, target=target, outcome=outcome, client=client, detail=detail
            )

    @staticmethod
    def add_audit_in(
        conn: Connection, *, actor: str, action: str, target: str, outcome: str, client: str, detail: str
    ) -> None:
        """Within a transaction of the caller's (the one that makes the change it records)."""
        conn.execute(
            insert(audit).values(
                at=datetime.now(timezone.utc),
                actor=actor[:128],
                action=action[:64],
                target=target[:256],
                outcome=outcome[:32],
                client=client[:64],
                detail=detail[:512],
            )
        )

    @retry_when_locked
    def list_audit(self, *, limit: int = 100, offset: int = 0) -> list[AuditRecord]:
        """Newest first."""
        query = select(audit).order_by(audit.c.id.desc()).limit(limit).offset(offset)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [AuditRecord(**{**dict(r), "at": utc(r["at"])}) for r in rows]
