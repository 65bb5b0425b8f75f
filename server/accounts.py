"""Accounts, projects and tokens: who may see and change what when ``KITTI_EVAL_AUTH=accounts``.

A token is ``kte_<id>_<secret>``: the id (16 hex digits) is not secret and is how the token is looked up and
named in the audit log; the secret is 43 random URL-safe characters (:func:`secrets.token_urlsafe`, 256 bits).
Only the sha256 of the whole token is stored (a slow KDF buys nothing for a token of that entropy), and the
check compares digests with :func:`hmac.compare_digest`, also when the id is unknown (against a dummy
digest), so that the time taken does not tell how much of a guess was right.

A web session is a token of kind ``session`` opened with a token (its ``parent``): the cookie holds the
session's token, never the one the user signed in with, and revoking the token ends its sessions.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import re
import secrets
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

from .errors import BadRequest, Conflict, NotFound, Unauthorized, echo
from .store import AuditRecord, EvaluationRecord, GroundTruthRecord, Store, TokenRecord, UserRecord

__all__ = [
    "Accounts",
    "Caller",
    "OPEN",
    "READ",
    "WRITE",
    "TOKEN_PREFIX",
    "TokenRefused",
    "digest",
    "split_token",
    "csrf_token",
]

log = logging.getLogger("kitti_eval.server")

TOKEN_PREFIX = "kte_"
_ID_HEX = 16
READ = "read"
WRITE = "write"
ALL_SCOPES = frozenset({READ, WRITE})
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_TOKEN_ID = re.compile(rf"^[0-9a-f]{{{_ID_HEX}}}$")
#: compared against when a token's id is unknown, so that a miss takes as long as a wrong secret
_DUMMY_DIGEST = hashlib.sha256(b"no such token").hexdigest()
#: most days a token may be valid for
MAX_EXPIRY_DAYS = 3650


@dataclass(frozen=True)
class Caller:
    """Who sends a request and what they may do."""

    name: str
    is_admin: bool = False
    #: the projects whose evaluations and ground truths the caller sees; None: every project
    projects: frozenset[str] | None = None
    scopes: frozenset[str] = field(default=ALL_SCOPES)
    token_id: str | None = None
    #: signed in through the web page (a session cookie): forms that change state need ``csrf``
    session: bool = False
    csrf: str | None = None

    @property
    def actor(self) -> str:
        """How the audit log names the caller (the token's id, never the token)."""
        return f"{self.name} ({self.token_id})" if self.token_id else self.name

    @property
    def can_write(self) -> bool:
        return WRITE in self.scopes

    def sees_project(self, project: str | None) -> bool:
        return self.projects is None or (project is not None and project in self.projects)

    def sees_ground_truth(self, record: GroundTruthRecord) -> bool:
        """Shared ground truths (no project: the demo, those registered in open mode) are everyone's."""
        return record.project is None or self.sees_project(record.project)

    def sees_evaluation(self, record: EvaluationRecord) -> bool:
        return self.sees_project(record.project)


#: open mode: everyone sees and changes everything except the admin actions (which need the admin token)
OPEN = Caller("anyone")


class TokenRefused(Unauthorized):
    """A token that is unknown, wrong, revoked or expired. The client is told no more than that; ``reason``
    and ``token_id`` go to the audit log."""

    def __init__(self, reason: str, token_id: str | None) -> None:
        super().__init__("the token is not valid (unknown, revoked or expired)")
        self.reason = reason
        self.token_id = token_id


def digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()


def split_token(token: str) -> str | None:
    """The id of a token of ours, or None when the text cannot be one."""
    if not token.startswith(TOKEN_PREFIX):
        return None
    token_id, sep, secret = token[len(TOKEN_PREFIX) :].partition("_")
    if not sep or not secret or not _TOKEN_ID.fullmatch(token_id):
        return None
    return token_id


def csrf_token(session_token: str) -> str:
    """The CSRF token of a web session: derived from the session's secret, so it needs no storage and a page
    on another site, which cannot read the HttpOnly cookie, cannot compute it."""
    return hmac.new(session_token.encode(), b"kitti-eval csrf", hashlib.sha256).hexdigest()


def _new_token() -> tuple[str, str]:
    """(id, token)."""
    token_id = secrets.token_hex(_ID_HEX // 2)
    return token_id, f"{TOKEN_PREFIX}{token_id}_{secrets.token_urlsafe(32)}"


def _scopes(text: str) -> frozenset[str]:
    return frozenset(s for s in text.split(",") if s)


class Accounts:
    """Users, projects, memberships, tokens, sessions and the audit log, on the service's store.

    Every method that changes something records it in the audit log as done by ``actor``; a refused token
    is recorded by whoever refuses it (:meth:`refused`)."""

    def __init__(self, store: Store, admin_token: Callable[[], str]) -> None:
        self.store = store
        self._admin_token = admin_token

    # -- checking tokens ---------------------------------------------------------------------------------
    def resolve(self, presented: str, *, session: bool = False) -> Caller:
        """The caller a bearer token (or, ``session``, a session cookie) stands for; TokenRefused if none.
        Reads the database every time (no cache), so a token revoked through any replica is refused by
        all at once."""
        presented_digest = digest(presented)
        if not session:
            admin = self._admin_token()
            if admin and hmac.compare_digest(presented_digest, digest(admin)):
                return Caller("admin-token", is_admin=True)
        token_id = split_token(presented)
        record = self.store.get_token(token_id) if token_id is not None else None
        matches = hmac.compare_digest(presented_digest, record.secret_sha256 if record else _DUMMY_DIGEST)
        if record is None or not matches:
            raise TokenRefused("unknown token" if record is None else "wrong secret", token_id)
        if record.kind != ("session" if session else "token"):
            raise TokenRefused(f"a {record.kind} used as a {'session' if session else 'token'}", token_id)
        problem = self._problem(record)
        if problem is None and record.parent is not None:
            parent = self.store.get_token(record.parent)
            problem = "its token is gone" if parent is None else self._problem(parent, "its token ")
        if problem is not None:
            raise TokenRefused(problem, token_id)
        user = self.store.get_user(record.user_name)
        if user is None:
            raise TokenRefused("its user is gone", token_id)
        return Caller(
            user.name,
            is_admin=user.is_admin,
            projects=None if user.is_admin else frozenset(user.projects),
            scopes=_scopes(record.scopes),
            token_id=record.id,
            session=session,
            csrf=csrf_token(presented) if session else None,
        )

    @staticmethod
    def _problem(record: TokenRecord, prefix: str = "") -> str | None:
        if record.revoked_at is not None:
            return f"{prefix}revoked"
        if record.expires_at is not None and record.expires_at <= datetime.now(timezone.utc):
            return f"{prefix}expired"
        return None

    def refused(self, error: TokenRefused, *, client: str, target: str) -> None:
        self.audit(
            actor=f"token {error.token_id}" if error.token_id else "unknown token",
            action="token.refused",
            target=target,
            outcome="refused",
            client=client,
            detail=error.reason,
        )

    # -- managing ----------------------------------------------------------------------------------------
    @staticmethod
    def check_name(name: str, what: str) -> str:
        if not _NAME.fullmatch(name):
            raise BadRequest(
                f"{what} name {echo(name)} is not valid: 1-64 letters, digits, '.', '_' or '-', "
                "starting with a letter or digit"
            )
        return name

    def add_user(self, name: str, *, is_admin: bool, actor: str, client: str = "local") -> UserRecord:
        self.check_name(name, "user")
        if not self.store.add_user(name, is_admin):
            raise Conflict(f"a user named {name!r} exists")
        self.audit(actor=actor, action="user.add", target=name, client=client, detail="admin" if is_admin else "")
        user = self.store.get_user(name)
        assert user is not None
        return user

    def user(self, name: str) -> UserRecord:
        user = self.store.get_user(name)
        if user is None:
            raise NotFound(f"no user named {echo(name)}")
        return user

    def add_project(self, name: str, *, actor: str, client: str = "local") -> str:
        self.check_name(name, "project")
        if not self.store.add_project(name):
            raise Conflict(f"a project named {name!r} exists")
        self.audit(actor=actor, action="project.add", target=name, client=client)
        return name

    def check_project(self, name: str) -> str:
        if not self.store.project_exists(name):
            raise NotFound(f"no project named {echo(name)}")
        return name

    def add_member(self, user: str, project: str, *, actor: str, client: str = "local") -> None:
        self.user(user)
        self.check_project(project)
        if not self.store.add_membership(user, project):
            raise Conflict(f"{user!r} is a member of {project!r} already")
        self.audit(actor=actor, action="member.add", target=f"{user} -> {project}", client=client)

    def remove_member(self, user: str, project: str, *, actor: str, client: str = "local") -> None:
        if not self.store.remove_membership(user, project):
            raise NotFound(f"{echo(user)} is not a member of {echo(project)}")
        self.audit(actor=actor, action="member.remove", target=f"{user} -> {project}", client=client)

    def add_token(
        self,
        user: str,
        *,
        scopes: Iterable[str] = ALL_SCOPES,
        expires_days: float | None = None,
        actor: str,
        client: str = "local",
    ) -> tuple[TokenRecord, str]:
        """A new token for ``user``: (its record, the token itself, which is shown once and kept nowhere)."""
        self.user(user)
        wanted = frozenset(scopes)
        if not wanted or not wanted <= ALL_SCOPES:
            raise BadRequest(f"scopes are {', '.join(sorted(ALL_SCOPES))}; got {echo(','.join(sorted(wanted)))}")
        if expires_days is not None and not 0 < expires_days <= MAX_EXPIRY_DAYS:
            raise BadRequest(f"a token expires after more than 0 and at most {MAX_EXPIRY_DAYS} days")
        lifetime = timedelta(days=expires_days) if expires_days is not None else None
        record, token = self._new(user, "token", None, wanted, lifetime)
        detail = f"scopes {record.scopes}" + (f", expires {record.expires_at.isoformat()}" if record.expires_at else "")
        self.audit(actor=actor, action="token.add", target=f"{user} ({record.id})", client=client, detail=detail)
        return record, token

    def _new(
        self, user: str, kind: str, parent: str | None, scopes: frozenset[str], lifetime: timedelta | None
    ) -> tuple[TokenRecord, str]:
        token_id, token = _new_token()
        now = datetime.now(timezone.utc)
        record = TokenRecord(
            id=token_id,
            user_name=user,
            kind=kind,
            parent=parent,
            secret_sha256=digest(token),
            scopes=",".join(sorted(scopes)),
            created_at=now,
            expires_at=now + lifetime if lifetime else None,
            revoked_at=None,
        )
        self.store.add_token(record)
        return record, token

    def revoke_token(self, token_id: str, *, actor: str, client: str = "local") -> None:
        record = self.store.get_token(token_id)
        if record is None or record.kind != "token" or not self.store.revoke_token(token_id):
            raise NotFound(f"no token with id {echo(token_id)}")
        self.audit(actor=actor, action="token.revoke", target=f"{record.user_name} ({token_id})", client=client)

    def open_session(self, caller: Caller, hours: float, *, client: str = "local") -> str:
        """A web session for a caller signed in with a token: the session's own token, for the cookie."""
        assert caller.token_id is not None
        parent = self.store.get_token(caller.token_id)
        assert parent is not None
        lifetime = timedelta(hours=hours)
        if parent.expires_at is not None:
            lifetime = min(lifetime, parent.expires_at - datetime.now(timezone.utc))
        record, token = self._new(caller.name, "session", parent.id, caller.scopes, lifetime)
        # ended sessions are of no use after a day (their audit rows stay): they do not pile up
        self.store.purge_sessions(datetime.now(timezone.utc) - timedelta(days=1))
        self.audit(actor=caller.actor, action="session.open", target=f"session {record.id}", client=client)
        return token

    def close_session(self, caller: Caller, *, client: str = "local") -> None:
        if caller.session and caller.token_id is not None:
            self.store.revoke_token(caller.token_id)
            self.audit(actor=caller.actor, action="session.close", target=f"session {caller.token_id}", client=client)

    def holders(self) -> tuple[int, int]:
        """How many users, and tokens not revoked (web sessions included), the database holds."""
        tokens = [t for t in self.store.list_tokens() if t.revoked_at is None]
        return len(self.store.list_users()), len(tokens)

    # -- audit -------------------------------------------------------------------------------------------
    def audit(
        self, *, actor: str, action: str, target: str, client: str, outcome: str = "ok", detail: str = ""
    ) -> None:
        """A row in the audit table and a line in the log; neither ever holds a token."""
        log.info("audit: %s %s %s (%s) from %s %s", actor, action, target, outcome, client, detail)
        self.store.add_audit(actor=actor, action=action, target=target, outcome=outcome, client=client, detail=detail)

    def audit_log(self, *, limit: int = 100, offset: int = 0) -> list[AuditRecord]:
        return self.store.list_audit(limit=limit, offset=offset)
