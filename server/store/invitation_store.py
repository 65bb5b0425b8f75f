"""The store's invitations: a link a host hands out so that people make their own accounts to take part in one
benchmark (the rules are :mod:`kitti_eval_server.access.invitations`'s), and the accounts each one made. Only the
sha256 of an invitation's code is kept, as for tokens. The tables are created with the others (they share the
schema's ``metadata``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, insert, or_, select, update
from sqlalchemy.engine import Connection, RowMapping
from sqlalchemy.exc import IntegrityError

from .account_store import TokenRecord, names_taken
from .database import Area, invitation_accounts, invitations, memberships, retry_when_locked, tokens, users, utc

__all__ = ["InvitationRecord", "InvitationStore", "NewAccount", "JoinRefused", "invitations", "invitation_accounts"]


class JoinRefused(Exception):
    """Nothing written: the invitation is used up, expired or revoked (``gone``), or the name is taken
    (``taken``)."""

    def __init__(self, *, gone: bool = False, taken: bool = False) -> None:
        super().__init__("join refused")
        self.gone = gone
        self.taken = taken


@dataclass(frozen=True)
class InvitationRecord:
    id: str
    code_sha256: str
    benchmark: str
    project: str | None
    max_uses: int | None
    uses: int
    created_by: str
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    #: the accounts it made, in the order they joined
    accounts: tuple[str, ...] = ()


@dataclass(frozen=True)
class NewAccount:
    """An account to make: its name, the projects it is a member of, its token's record (the token itself is
    never stored)."""

    name: str
    projects: tuple[str, ...]
    token: TokenRecord


class InvitationStore(Area):
    """Invitations, the accounts they made, and accounts made many at once."""

    @retry_when_locked
    def add_invitation(self, record: InvitationRecord) -> None:
        values = {k: v for k, v in record.__dict__.items() if k != "accounts"}
        with self._writing() as conn:
            conn.execute(insert(invitations).values(**values))

    @retry_when_locked
    def get_invitation(
        self, *, code_sha256: str | None = None, invitation_id: str | None = None
    ) -> InvitationRecord | None:
        query = select(invitations)
        if code_sha256 is not None:
            query = query.where(invitations.c.code_sha256 == code_sha256)
        else:
            query = query.where(invitations.c.id == invitation_id)
        with self.engine.connect() as conn:
            row = conn.execute(query).mappings().first()
            return None if row is None else self._record(row, self._accounts_of(conn, [row["id"]]))

    @retry_when_locked
    def list_invitations(self, benchmark: str | None = None) -> list[InvitationRecord]:
        query = select(invitations).order_by(invitations.c.created_at, invitations.c.id)
        if benchmark is not None:
            query = query.where(invitations.c.benchmark == benchmark)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            made = self._accounts_of(conn, [r["id"] for r in rows])
        return [self._record(r, made) for r in rows]

    @retry_when_locked
    def revoke_invitation(self, invitation_id: str, at: datetime) -> bool:
        """False when there is no such invitation, or it was revoked already."""
        with self._writing() as conn:
            done = conn.execute(
                update(invitations)
                .where(invitations.c.id == invitation_id, invitations.c.revoked_at.is_(None))
                .values(revoked_at=at)
            )
        return bool(done.rowcount)

    @retry_when_locked
    def joined(self, benchmark: str) -> int:
        """How many accounts the benchmark's invitations made."""
        query = (
            select(func.count())
            .select_from(invitation_accounts)
            .join(invitations, invitations.c.id == invitation_accounts.c.invitation)
            .where(invitations.c.benchmark == benchmark)
        )
        with self.engine.connect() as conn:
            return int(conn.execute(query).scalar_one())

    @retry_when_locked
    def join(self, invitation_id: str, account: NewAccount, at: datetime, audit: Callable[[Connection], None]) -> None:
        """Use the invitation once and make the account (its memberships, its token, the audit row ``audit``
        writes) in
        one transaction: :class:`JoinRefused`, nothing written, when the invitation is used up, expired or
        revoked at ``at``, or the name is taken. The use is counted by one conditional update, so two joins at
        once never exceed the uses."""
        with self._writing() as conn:
            used = conn.execute(
                update(invitations)
                .where(
                    invitations.c.id == invitation_id,
                    invitations.c.revoked_at.is_(None),
                    or_(invitations.c.expires_at.is_(None), invitations.c.expires_at > at),
                    or_(invitations.c.max_uses.is_(None), invitations.c.uses < invitations.c.max_uses),
                )
                .values(uses=invitations.c.uses + 1)
            )
            if not used.rowcount:
                raise JoinRefused(gone=True)
            if self._taken(conn, [account.name]):
                raise JoinRefused(taken=True)
            self._make(conn, account, at)
            conn.execute(
                insert(invitation_accounts).values(user_name=account.name, invitation=invitation_id, joined_at=at)
            )
            audit(conn)

    @retry_when_locked
    def taken(self, names: Sequence[str]) -> list[str]:
        """Which of ``names`` are users' already, ignoring case (:func:`.account_store.names_taken`)."""
        with self.engine.connect() as conn:
            return self._taken(conn, names)

    @retry_when_locked
    def add_accounts(
        self, accounts: Sequence[NewAccount], at: datetime, audit: Callable[[Connection, NewAccount], None]
    ) -> None:
        """Make every account, or none: :class:`JoinRefused` (``taken``) when a name is taken by then; ``audit``
        writes each one's audit row in the transaction."""
        with self._writing() as conn:
            if self._taken(conn, [a.name for a in accounts]):
                raise JoinRefused(taken=True)
            for account in accounts:
                self._make(conn, account, at)
            for account in accounts:
                audit(conn, account)

    @staticmethod
    def _taken(conn: Connection, names: Sequence[str]) -> list[str]:
        return names_taken(conn, names)

    @staticmethod
    def _make(conn: Connection, account: NewAccount, at: datetime) -> None:
        try:
            conn.execute(insert(users).values(name=account.name, is_admin=False, created_at=at))
        except IntegrityError:  # made meanwhile (PostgreSQL: another transaction committed it first)
            raise JoinRefused(taken=True) from None
        if account.projects:
            conn.execute(insert(memberships), [{"user_name": account.name, "project": p} for p in account.projects])
        conn.execute(insert(tokens).values(**account.token.__dict__))

    @staticmethod
    def _accounts_of(conn: Connection, ids: Sequence[str]) -> dict[str, list[str]]:
        made: dict[str, list[str]] = {}
        if not ids:
            return made
        rows = conn.execute(
            select(invitation_accounts.c.invitation, invitation_accounts.c.user_name)
            .where(invitation_accounts.c.invitation.in_(list(ids)))
            .order_by(invitation_accounts.c.joined_at, invitation_accounts.c.user_name)
        )
        for invitation, user_name in rows:
            made.setdefault(invitation, []).append(user_name)
        return made

    @staticmethod
    def _record(row: RowMapping, made: dict[str, list[str]]) -> InvitationRecord:
        values = dict(row)
        for key in ("created_at", "expires_at", "revoked_at"):
            if values[key] is not None:
                values[key] = utc(values[key])
        return InvitationRecord(**values, accounts=tuple(made.get(row["id"], ())))
