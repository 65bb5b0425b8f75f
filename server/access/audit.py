"""The audit log: every action that changes something, and every refusal of a token, in one place.

The services record what they did through :class:`Audit`, whatever the door it came through (an HTTP route,
a web form, ``kitti-eval admin``): the caller says who acted and from where. A row in the audit table and a
line in the log; neither ever holds a token (only a token's id).
"""

from __future__ import annotations

import logging
from typing import Any, Protocol

from ..store import AuditRecord
from .policy import Caller

__all__ = ["Audit"]

log = logging.getLogger("kitti_eval.server")


class _AuditStore(Protocol):
    def add_audit(self, *, actor: str, action: str, target: str, outcome: str, client: str, detail: str) -> None: ...

    def add_audit_in(
        self, conn: Any, *, actor: str, action: str, target: str, outcome: str, client: str, detail: str
    ) -> None: ...

    def list_audit(self, *, limit: int = 100, offset: int = 0) -> list[AuditRecord]: ...


class Audit:
    def __init__(self, account_store: _AuditStore) -> None:
        """``account_store``: where the rows are written (the accounts' area of the store)."""
        self.account_store = account_store

    def record(self, caller: Caller, action: str, target: str, *, outcome: str = "ok", detail: str = "") -> None:
        """``caller`` did ``action`` on ``target``."""
        self._write(caller.actor, action, target, outcome, caller.client, detail)

    def record_in(self, conn: Any, caller: Caller, action: str, target: str, *, detail: str = "") -> None:
        """The same, written in the transaction of the change it records (one commit for both). The log line is
        written at once: call it last in the transaction."""
        self._write(caller.actor, action, target, "ok", caller.client, detail, conn=conn)

    def joined_in(self, conn: Any, *, user: str, token_id: str, client: str, detail: str) -> None:
        """``user`` made their account (and its token ``token_id``) by an invitation, from ``client``: in the
        transaction that makes it."""
        self._write(user, "invitation.join", f"{user} ({token_id})", "ok", client, detail, conn=conn)

    def refused_join(self, caller: Caller, *, invitation_id: str, detail: str) -> None:
        """A join by the invitation ``invitation_id`` (its id, never its code) was refused, from the caller's
        address."""
        self._write(caller.actor, "invitation.join", f"invitation {invitation_id}", "refused", caller.client, detail)

    def refused_use(self, caller: Caller, target: str, detail: str) -> None:
        """A valid token (or session) was refused what it asked (an admin action, a write with a read-only
        token, a change without the session's CSRF token)."""
        self._write(caller.actor, "token.forbidden", target, "refused", caller.client, detail)

    def refused_token(self, token_id: str | None, *, client: str, target: str, reason: str) -> None:
        """A token that is unknown, wrong, revoked or expired."""
        actor = f"token {token_id}" if token_id else "unknown token"
        self._write(actor, "token.refused", target, "refused", client, reason)

    def entries(self, *, limit: int = 100, offset: int = 0) -> list[AuditRecord]:
        return self.account_store.list_audit(limit=limit, offset=offset)

    def _write(
        self, actor: str, action: str, target: str, outcome: str, client: str, detail: str, conn: Any = None
    ) -> None:
        """A log line and a row (in ``conn``'s transaction when given, else in one of its own)."""
        log.info("audit: %s %s %s (%s) from %s %s", actor, action, target, outcome, client, detail)
        row = {"actor": actor, "action": action, "target": target, "outcome": outcome, "client": client}
        if conn is None:
            self.account_store.add_audit(**row, detail=detail)
        else:
            self.account_store.add_audit_in(conn, **row, detail=detail)
