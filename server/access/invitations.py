"""Invitations: people make their own accounts to take part in a benchmark, through a link a host handed out.

An invitation is ``/join/CODE``: the code is 256 random bits (:func:`secrets.token_urlsafe`), shown once when it is
made, and only its sha256 is kept (as a token's). It admits to one benchmark, for ``max_uses`` accounts (None: as
many as join) until it expires or is revoked. An account it makes is an ordinary user's, never an admin's, a
member of the projects :func:`~kitti_eval_server.access.policy.invited_projects` names (the benchmark's test set's
project where only its members take part), with one token that may read and write: it may take part in the
benchmark and sees what those projects' members see, nothing more. A join is one transaction (the use, the
account, its memberships, its token and its audit row); a used-up, expired or revoked invitation is 410 with one
message, a taken name 409.

``kitti-eval admin user import FILE.csv`` makes many accounts at once, each with a token: every line is checked
before anything is written, and the file is refused whole, naming its line, when one is not right.
"""

from __future__ import annotations

import csv
import io
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

from sqlalchemy.engine import Connection

from ..errors import ApiError, BadRequest, Conflict, Gone, NotFound, echo
from ..store import InvitationRecord, InvitationStore, JoinRefused, NewAccount
from .accounts import Accounts, digest
from .audit import Audit
from .policy import Caller, Policy, invited_projects, may_join_team

__all__ = [
    "Invitations",
    "Invited",
    "ImportLine",
    "parse_import",
    "state_of",
    "usable",
    "GONE",
    "MAX_USES",
    "DEFAULT_DAYS",
    "MAX_IMPORT_LINES",
]

#: the one message of a used-up, expired or revoked invitation, or of one whose benchmark's last phase has closed
GONE = (
    "this invitation is used up, expired or revoked, or its benchmark has closed: ask the host of the benchmark "
    "for a new link"
)
#: the refused joins the audit log keeps (an unknown code, 404, names no invitation): spent or closed, a taken name,
#: a name that is not valid, too many attempts from one address
AUDITED_REFUSALS = frozenset({410, 409, 422, 429})
#: most accounts one invitation may make
MAX_USES = 100_000
#: most days an invitation may be valid for
MAX_DAYS = 3650
#: how long an invitation is valid when its host names no time: a link handed out to a class is not a door left
#: open for good
DEFAULT_DAYS = 14
#: most accounts one import makes
MAX_IMPORT_LINES = 10_000
_CODE_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_")


@dataclass(frozen=True)
class Invited:
    """What a valid invitation shows the person who opens its link: the benchmark it admits to."""

    benchmark: str


@dataclass(frozen=True)
class ImportLine:
    """A line of an import's CSV: its number in the file (the header is line 1), the name, the project."""

    line: int
    name: str
    project: str | None


def parse_import(text: str) -> list[ImportLine]:
    """The lines of an import's CSV (columns ``name`` and, optionally, ``project``; a header line first), or
    BadRequest naming the line that is not right: a missing name, a name or project that is not valid, a name
    twice."""
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip().lower() for h in next(reader)]
    except StopIteration:
        raise BadRequest("the file is empty: its first line names the columns, name and (optionally) project") from None
    except csv.Error as e:
        raise BadRequest(f"line 1: not CSV ({e})") from None
    if "name" not in header or not set(header) <= {"name", "project"} or len(set(header)) != len(header):
        raise BadRequest(f"line 1: the columns are name and (optionally) project; got {echo(','.join(header))}")
    lines: list[ImportLine] = []
    seen: dict[str, int] = {}
    try:
        for row in reader:
            number = reader.line_num
            if not any(cell.strip() for cell in row):
                continue
            if len(row) != len(header):
                raise BadRequest(f"line {number}: {len(row)} fields, the header has {len(header)}")
            fields = dict(zip(header, (cell.strip() for cell in row)))
            name, project = fields["name"], fields.get("project") or None
            try:
                Accounts.check_user_name(name)
                if project is not None:
                    Accounts.check_name(project, "project")
            except BadRequest as e:
                raise BadRequest(f"line {number}: {e.message}") from None
            if name.lower() in seen:  # as a name taken already: ignoring case
                raise BadRequest(f"line {number}: the user {name!r} is on line {seen[name.lower()]} too")
            seen[name.lower()] = number
            lines.append(ImportLine(number, name, project))
            if len(lines) > MAX_IMPORT_LINES:
                raise BadRequest(f"line {number}: an import makes at most {MAX_IMPORT_LINES} accounts")
    except csv.Error as e:
        raise BadRequest(f"line {reader.line_num}: not CSV ({e})") from None
    if not lines:
        raise BadRequest("the file names no account: a line a user after the header")
    return lines


class Invitations:
    """Invitations to the benchmarks, joining by one, and accounts made many at once; every change audited."""

    def __init__(
        self,
        store: InvitationStore,
        accounts: Accounts,
        policy: Policy,
        audit: Audit,
        benchmark: Callable[[str], tuple[str, str | None, bool]],
        closed: Callable[[str], bool],
    ) -> None:
        """``benchmark(name)``: the benchmark's name as participants address it, its test set's project and whether
        it is open to all (NotFound when there is none); ``closed(name)``: whether its last phase has closed (as
        the phases' lifecycle says; NotFound when there is no such benchmark)."""
        self.store = store
        self.accounts = accounts
        self.policy = policy
        self.audit = audit
        self._benchmark = benchmark
        self._closed = closed

    # -- the host's ---------------------------------------------------------------------------------------
    def add(
        self,
        benchmark: str,
        *,
        uses: int | None,
        expires_days: float | None,
        project: str | None,
        caller: Caller,
    ) -> tuple[InvitationRecord, str]:
        """A new invitation to ``benchmark``: its record and its code (shown once, kept nowhere). It expires after
        ``expires_days`` (None: :data:`DEFAULT_DAYS`); every invitation expires."""
        self.policy.require_admin(caller)
        name, bench_project, open_to_all = self._benchmark(benchmark)
        if uses is not None and not 0 < uses <= MAX_USES:
            raise BadRequest(f"an invitation is used at least once and at most {MAX_USES} times; got {uses}")
        if expires_days is None:
            expires_days = DEFAULT_DAYS
        if not 0 < expires_days <= MAX_DAYS:
            raise BadRequest(f"an invitation expires after more than 0 and at most {MAX_DAYS} days")
        projects = invited_projects(project=bench_project, open_to_all=open_to_all, wanted=project)
        for p in projects:
            self.accounts.check_project(p)
        code = secrets.token_urlsafe(32)
        now = datetime.now(timezone.utc)
        record = InvitationRecord(
            id=secrets.token_hex(8),
            code_sha256=digest(code),
            benchmark=name,
            project=projects[0] if projects else None,
            max_uses=uses,
            uses=0,
            created_by=caller.actor[:128],
            created_at=now,
            expires_at=now + timedelta(days=expires_days),
            revoked_at=None,
        )
        self.store.add_invitation(record)
        detail = f"benchmark {name}, project {record.project or '-'}, uses {uses or 'any'}"
        if record.expires_at is not None:
            detail += f", expires {record.expires_at.isoformat()}"
        self.audit.record(caller, "invitation.add", record.id, detail=detail)
        return record, code

    def listed(self, caller: Caller, benchmark: str | None = None) -> list[InvitationRecord]:
        self.policy.require_admin(caller)
        return self.store.list_invitations(benchmark)

    def revoke(self, invitation_id: str, *, caller: Caller) -> None:
        self.policy.require_admin(caller)
        if not self.store.revoke_invitation(invitation_id, datetime.now(timezone.utc)):
            raise NotFound(f"no invitation with id {echo(invitation_id)} that is not revoked already")
        self.audit.record(caller, "invitation.revoke", invitation_id)

    def participants(self, benchmark: str, caller: Caller) -> dict[str, int] | None:
        """For an admin (None for anyone else): how many accounts may take part in the benchmark
        (:func:`~kitti_eval_server.access.policy.may_join_team`'s rule: not an admin's, a member of its test set's
        project unless it is shared or open to all), and how many of them its invitations made."""
        if not self.policy.administers(caller):
            return None
        name, project, open_to_all = self._benchmark(benchmark)
        users = self.accounts.users()
        taking_part = sum(
            1 for u in users if may_join_team(u, benchmark=name, project=project, open_to_all=open_to_all)
        )
        return {"accounts": taking_part, "joined": self.store.joined(name)}

    # -- the invited's -----------------------------------------------------------------------------------
    def _named(self, code: str) -> InvitationRecord | None:
        """The invitation whose code is ``code``, whatever its state (None: none, or no accounts)."""
        if not (20 <= len(code) <= 100 and set(code) <= _CODE_CHARS) or not self.policy.has_accounts():
            return None
        return self.store.get_invitation(code_sha256=digest(code))

    def refused(self, code: str, error: ApiError, *, caller: Caller, name: object = None) -> None:
        """Audit a refused join (one of :data:`AUDITED_REFUSALS`) by the invitation it named: the invitation's id
        (never the code), the caller's address, the status, the name asked for and why. Both doors (the page and
        the JSON route) call it with what they refused; an unknown code leaves no row."""
        if error.status_code not in AUDITED_REFUSALS:
            return
        record = self._named(code)
        if record is None:
            return
        asked = echo(name, 64) if isinstance(name, str) else "-"
        detail = f"{error.status_code}, name {asked}: {error.message}"
        self.audit.refused_join(caller, invitation_id=record.id, detail=detail[:1000])

    def _usable(self, code: str) -> InvitationRecord:
        record = self._named(code)
        if record is None:
            raise NotFound("no such invitation: check the link the host gave you")
        if not usable(record, datetime.now(timezone.utc)) or self._has_closed(record.benchmark):
            raise Gone(GONE)
        return record

    def _has_closed(self, benchmark: str) -> bool:
        """Whether the invitation's benchmark takes no one any more: its last phase has closed, or it is gone."""
        try:
            return self._closed(benchmark)
        except NotFound:
            return True

    def invited(self, code: str, *, caller: Caller) -> Invited:
        """What the link's page shows: the benchmark it admits to (404 unknown, 410 used up, expired, revoked)."""
        return Invited(self._usable(code).benchmark)

    def join(self, code: str, name: object, *, caller: Caller) -> tuple[str, str, str]:
        """Make the account ``name`` by the invitation ``code``: (the user, its token, shown once; the
        benchmark). 404 unknown code, 410 used up, expired or revoked (or its benchmark has closed), 409 a taken
        name, 422 a name that is not valid; audited as the new user's join, from the caller's address."""
        record = self._usable(code)
        if not isinstance(name, str):
            raise BadRequest('send the user name you want: {"name": "..."}')
        Accounts.check_user_name(name)
        token, secret = self.accounts.token_record(name)
        account = NewAccount(name, (record.project,) if record.project else (), token)
        detail = f"invitation {record.id}, benchmark {record.benchmark}, project {record.project or '-'}"

        def audit(conn: Connection) -> None:
            self.audit.joined_in(conn, user=name, token_id=token.id, client=caller.client, detail=detail)

        try:
            self.store.join(record.id, account, datetime.now(timezone.utc), audit)
        except JoinRefused as e:
            if e.taken:
                raise Conflict(f"the user name {name!r} is taken: choose another") from None
            raise Gone(GONE) from None
        return name, secret, record.benchmark

    # -- many at once ------------------------------------------------------------------------------------
    def import_users(self, lines: list[ImportLine], *, caller: Caller) -> list[tuple[str, str]]:
        """Make an account with a token for each line (:func:`parse_import`), or none: BadRequest naming the first
        line whose project does not exist, Conflict naming the first whose name is taken. (name, token) each."""
        self.policy.require_admin(caller)
        for line in lines:
            if line.project is not None:
                try:
                    self.accounts.check_project(line.project)
                except NotFound:
                    raise NotFound(f"line {line.line}: no project named {echo(line.project)}") from None
        taken = set(self.store.taken([line.name for line in lines]))
        for line in lines:
            if line.name in taken:
                raise Conflict(f"line {line.line}: a user named {line.name!r} exists; nothing was imported")
        made, accounts, line_of = [], [], {}
        for line in lines:
            token, secret = self.accounts.token_record(line.name)
            accounts.append(NewAccount(line.name, (line.project,) if line.project else (), token))
            made.append((line.name, secret))
            line_of[line.name] = line

        def audit(conn: Connection, account: NewAccount) -> None:
            line = line_of[account.name]
            detail = f"line {line.line}, project {line.project or '-'}"
            self.audit.record_in(conn, caller, "user.import", f"{account.name} ({account.token.id})", detail=detail)

        try:
            self.store.add_accounts(accounts, datetime.now(timezone.utc), audit)
        except JoinRefused:
            raise Conflict("a name of the file was taken meanwhile; nothing was imported") from None
        return made


def state_of(record: InvitationRecord, now: datetime) -> str:
    """An invitation at ``now``: ``revoked``, ``expired``, ``used up`` or ``open`` (it may still make an
    account)."""
    if record.revoked_at is not None:
        return "revoked"
    if record.expires_at is not None and record.expires_at <= now:
        return "expired"
    if record.max_uses is not None and record.uses >= record.max_uses:
        return "used up"
    return "open"


def usable(record: InvitationRecord, now: datetime) -> bool:
    """Whether an invitation may still make an account at ``now``: not revoked, not expired, uses left."""
    return state_of(record, now) == "open"
