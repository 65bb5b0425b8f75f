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
import os
import re
import secrets
from collections.abc import Callable, Iterable
from datetime import datetime, timedelta, timezone
from pathlib import Path

from ..errors import BadRequest, Conflict, NotFound, Unauthorized, echo
from ..settings import Settings
from ..store import AccountStore, TokenRecord, UserRecord
from .audit import Audit
from .policy import ALL_SCOPES, READ, RESERVED_USER_NAMES, WRITE, Caller, Policy

log = logging.getLogger("kitti_eval.server")

__all__ = [
    "admin_token",
    "Accounts",
    "Caller",
    "READ",
    "WRITE",
    "TOKEN_PREFIX",
    "TokenRefused",
    "digest",
    "split_token",
    "csrf_token",
]

TOKEN_PREFIX = "kte_"
_ID_HEX = 16
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_TOKEN_ID = re.compile(rf"^[0-9a-f]{{{_ID_HEX}}}$")
#: compared against when a token's id is unknown, so that a miss takes as long as a wrong secret
_DUMMY_DIGEST = hashlib.sha256(b"no such token").hexdigest()
#: most days a token may be valid for
MAX_EXPIRY_DAYS = 3650


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

    Every method that changes something takes the caller who acts and records it in the audit log."""

    def __init__(self, account_store: AccountStore, audit: Audit, admin_token: Callable[[], str]) -> None:
        self.account_store = account_store
        self.audit = audit
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
                return Policy.admin_token_caller()  # the admin token stands for an admin
        token_id = split_token(presented)
        record = self.account_store.get_token(token_id) if token_id is not None else None
        matches = hmac.compare_digest(presented_digest, record.secret_sha256 if record else _DUMMY_DIGEST)
        if record is None or not matches:
            raise TokenRefused("unknown token" if record is None else "wrong secret", token_id)
        if record.kind != ("session" if session else "token"):
            raise TokenRefused(f"a {record.kind} used as a {'session' if session else 'token'}", token_id)
        problem = self._problem(record)
        if problem is None and record.parent is not None:
            parent = self.account_store.get_token(record.parent)
            problem = "its token is gone" if parent is None else self._problem(parent, "its token ")
        if problem is not None:
            raise TokenRefused(problem, token_id)
        user = self.account_store.get_user(record.user_name)
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
            signed_in=True,
            invited_to=None if user.is_admin else user.invited_to,
        )

    @staticmethod
    def _problem(record: TokenRecord, prefix: str = "") -> str | None:
        if record.revoked_at is not None:
            return f"{prefix}revoked"
        if record.expires_at is not None and record.expires_at <= datetime.now(timezone.utc):
            return f"{prefix}expired"
        return None

    def refused(self, error: TokenRefused, *, client: str, target: str) -> None:
        self.audit.refused_token(error.token_id, client=client, target=target, reason=error.reason)

    # -- managing ----------------------------------------------------------------------------------------
    @staticmethod
    def check_name(name: str, what: str) -> str:
        if not _NAME.fullmatch(name):
            raise BadRequest(
                f"{what} name {echo(name)} is not valid: 1-64 letters, digits, '.', '_' or '-', "
                "starting with a letter or digit"
            )
        return name

    @classmethod
    def check_user_name(cls, name: str) -> str:
        """A new user's name, whoever makes the account (an admin, an invitation, an import): the rules of a name,
        and none of the service's own callers'."""
        cls.check_name(name, "user")
        if name.lower() in RESERVED_USER_NAMES:
            raise BadRequest(
                f"the user name {name!r} is reserved, in any case: the service names its own callers and the "
                f"administrator so ({', '.join(sorted(RESERVED_USER_NAMES))})"
            )
        return name

    def add_user(self, name: str, *, is_admin: bool, caller: Caller) -> UserRecord:
        self.check_user_name(name)
        if not self.account_store.add_user(name, is_admin):
            raise Conflict(f"a user named {name!r} exists")
        self.audit.record(caller, "user.add", name, detail="admin" if is_admin else "")
        user = self.account_store.get_user(name)
        assert user is not None
        return user

    def user(self, name: str) -> UserRecord:
        user = self.account_store.get_user(name)
        if user is None:
            raise NotFound(f"no user named {echo(name)}")
        return user

    def add_project(self, name: str, *, caller: Caller) -> str:
        self.check_name(name, "project")
        if not self.account_store.add_project(name):
            raise Conflict(f"a project named {name!r} exists")
        self.audit.record(caller, "project.add", name)
        return name

    def check_project(self, name: str) -> str:
        if not self.account_store.project_exists(name):
            raise NotFound(f"no project named {echo(name)}")
        return name

    def add_member(self, user: str, project: str, *, caller: Caller) -> None:
        self.user(user)
        self.check_project(project)
        if not self.account_store.add_membership(user, project):
            raise Conflict(f"{user!r} is a member of {project!r} already")
        self.audit.record(caller, "member.add", f"{user} -> {project}")

    def remove_member(self, user: str, project: str, *, caller: Caller) -> None:
        if not self.account_store.remove_membership(user, project):
            raise NotFound(f"{echo(user)} is not a member of {echo(project)}")
        self.audit.record(caller, "member.remove", f"{user} -> {project}")

    def add_token(
        self,
        user: str,
        *,
        scopes: Iterable[str] = ALL_SCOPES,
        expires_days: float | None = None,
        caller: Caller,
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
        self.audit.record(caller, "token.add", f"{user} ({record.id})", detail=detail)
        return record, token

    def _new(
        self, user: str, kind: str, parent: str | None, scopes: frozenset[str], lifetime: timedelta | None
    ) -> tuple[TokenRecord, str]:
        record, token = self.token_record(user, kind, parent, scopes, lifetime)
        self.account_store.add_token(record)
        return record, token

    @staticmethod
    def token_record(
        user: str,
        kind: str = "token",
        parent: str | None = None,
        scopes: frozenset[str] = ALL_SCOPES,
        lifetime: timedelta | None = None,
    ) -> tuple[TokenRecord, str]:
        """A new token's record and the token itself, not stored yet (an account made with its token stores both
        in one transaction)."""
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
        return record, token

    def revoke_token(self, token_id: str, *, caller: Caller) -> None:
        record = self.account_store.get_token(token_id)
        if record is None or record.kind != "token" or not self.account_store.revoke_token(token_id):
            raise NotFound(f"no token with id {echo(token_id)}")
        self.audit.record(caller, "token.revoke", f"{record.user_name} ({token_id})")

    def open_session(self, caller: Caller, hours: float) -> str:
        """A web session for a caller signed in with a token: the session's own token, for the cookie."""
        assert caller.token_id is not None
        parent = self.account_store.get_token(caller.token_id)
        assert parent is not None
        lifetime = timedelta(hours=hours)
        if parent.expires_at is not None:
            lifetime = min(lifetime, parent.expires_at - datetime.now(timezone.utc))
        record, token = self._new(caller.name, "session", parent.id, caller.scopes, lifetime)
        # ended sessions are of no use after a day (their audit rows stay): they do not pile up
        self.account_store.purge_sessions(datetime.now(timezone.utc) - timedelta(days=1))
        self.audit.record(caller, "session.open", f"session {record.id}")
        return token

    def close_session(self, caller: Caller) -> None:
        if caller.session and caller.token_id is not None:
            self.account_store.revoke_token(caller.token_id)
            self.audit.record(caller, "session.close", f"session {caller.token_id}")

    def holders(self) -> tuple[int, int]:
        """How many users, and tokens not revoked (web sessions included), the database holds."""
        tokens = [t for t in self.account_store.list_tokens() if t.revoked_at is None]
        return len(self.account_store.list_users()), len(tokens)

    # -- listing (admins) --------------------------------------------------------------------------------
    def users(self) -> list[UserRecord]:
        return self.account_store.list_users()

    def projects(self) -> list[str]:
        return self.account_store.list_projects()

    def tokens(self, user: str | None = None) -> list[TokenRecord]:
        return self.account_store.list_tokens(user)


def admin_token(settings: Settings, data_dir: Path) -> str:
    """The admin token: ``KITTI_EVAL_ADMIN_TOKEN``, else the one in ``data_dir/admin-token`` (made there, readable by
    its owner only, by the first process that finds none)."""
    if settings.admin_token is not None:
        return settings.admin_token.get_secret_value()
    path = data_dir / "admin-token"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return path.read_text().strip()
    token = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    log.warning("generated an admin token in %s (set KITTI_EVAL_ADMIN_TOKEN to choose one)", path)
    return token
