"""Who may see and do what: the one place the service decides it.

Two things live here and nowhere else:

* **What a route asks of its caller** (:class:`Access`). Every route declares it where it is declared, as
  the dependency it takes (:mod:`kitti_eval_server.access.deps`: ``PublicCaller``, ``ReaderCaller``, ...); the door
  (:class:`kitti_eval_server.access.auth.AuthMiddleware`) reads those declarations when the app starts and refuses a
  route that declares none. There is no list of public paths anywhere else.
* **What a caller may see and do** (:class:`Policy`): evaluations, ground truths and their frames,
  benchmarks, submissions and their scores, admin actions. The services ask it; every service method that
  shows or changes something takes the caller as a required argument, so no call can forget to ask.

Nothing outside this module (and :mod:`kitti_eval_server.access.accounts`, which makes callers from their records)
reads a caller's rights or the mode: the service asks the policy a question (:meth:`Policy.may_take_part`,
:meth:`Policy.is_baseline`, :func:`default_project`, ...; a test walks the sources). A :class:`Caller`
made without saying otherwise is nobody, and a :class:`Policy` is never made without its test sets.

A :class:`Caller` is made by the policy alone (:meth:`Policy.everyone`, :meth:`Policy.anonymous`, or
:meth:`kitti_eval_server.access.accounts.Accounts.resolve` for a token), and the routes receive it from their access
dependency. ``KITTI_EVAL_AUTH`` is an :class:`~kitti_eval_server.settings.AuthMode`: in ``open`` mode everyone
is :meth:`Policy.everyone` (sees and changes everything, admin actions need the admin token); in ``accounts``
mode the rules below apply. The table "Who may do what" of docs/service/accounts.md is checked against
:data:`RULES` by a test.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from enum import Enum
from typing import Protocol

from ..errors import BadRequest, Forbidden, NotFound, Sealed, Unauthorized, echo
from ..settings import AuthMode

__all__ = [
    "Access",
    "Caller",
    "Policy",
    "default_project",
    "RULES",
    "may_join_team",
    "may_gate_unkept",
    "owns_gate_result",
    "invited_projects",
    "sees_teams",
    "require_open_labels",
    "READ",
    "WRITE",
    "ALL_SCOPES",
    "SAFE_METHODS",
    "CSRF_HEADER",
    "BUILT_IN_CALLERS",
    "RESERVED_USER_NAMES",
]

READ = "read"
WRITE = "write"
ALL_SCOPES = frozenset({READ, WRITE})
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
#: a script using a web session's cookie sends the session's CSRF token in this header (forms: field ``csrf``)
CSRF_HEADER = "x-csrf-token"
#: the names of the callers the service makes itself (no user may take one: the audit log, a job's owner and a
#: submission's participant name callers by these)
BUILT_IN_CALLERS = frozenset({"admin-token", "anyone", "anonymous", "metrics-scraper"})
#: the names no new user takes, in any case: the built-in callers', and ``admin`` (an account so named would read as
#: the administrator on a board and in the audit log)
RESERVED_USER_NAMES = BUILT_IN_CALLERS | {"admin"}
#: how long a sign-in form's CSRF token is valid
SIGNIN_CSRF_S = 3600


class Access(str, Enum):
    """What a route asks of its caller before it runs (declared by the route, enforced by the door and the
    route's dependency)."""

    #: nobody is asked: the probes, the sign-in page, static files; a token sent along is not looked at
    PUBLIC = "public"
    #: read without a token, or with a valid one: public benchmarks' descriptions and boards
    ANYONE = "anyone"
    #: a valid token or web session (accounts mode)
    READER = "reader"
    #: a valid token or session that may write; a session also sends its CSRF token
    WRITER = "writer"
    #: an admin's token or session that may write (or the admin token); a session also sends its CSRF token
    ADMIN = "admin"
    #: ``/metrics``: its own token when ``KITTI_EVAL_METRICS_TOKEN`` is set, else an admin's (accounts mode; a
    #: read-only token will do) or anyone (open mode)
    SCRAPER = "scraper"


@dataclass(frozen=True)
class Caller:
    """Who sends a request, what they may do, and where from (for the audit log). Made without saying
    otherwise, a caller is nobody: no project, no scope, not signed in, not an admin."""

    name: str
    is_admin: bool = False
    #: the projects whose evaluations and ground truths the caller sees; None: every project
    projects: frozenset[str] | None = frozenset()
    scopes: frozenset[str] = frozenset()
    token_id: str | None = None
    #: signed in through the web page (a session cookie): changes need the session's ``csrf``
    session: bool = False
    csrf: str | None = None
    #: the client's address (or ``cli``, ``local``), as the audit log names it
    client: str = "local"
    #: False for a reader without a token (accounts mode)
    signed_in: bool = False
    #: an account made by an invitation: the benchmark it takes part in, the only one (None: any it may)
    invited_to: str | None = None

    @property
    def actor(self) -> str:
        """How the audit log names the caller (the token's id, never the token)."""
        return f"{self.name} ({self.token_id})" if self.token_id else self.name

    @property
    def can_write(self) -> bool:
        return WRITE in self.scopes

    def at(self, client: str) -> Caller:
        """The same caller, seen coming from ``client``."""
        return replace(self, client=client)


class _Evaluation(Protocol):
    @property
    def project(self) -> str | None: ...

    @property
    def gt_name(self) -> str | None: ...


class _User(Protocol):
    @property
    def is_admin(self) -> bool: ...

    @property
    def projects(self) -> tuple[str, ...]: ...

    @property
    def invited_to(self) -> str | None: ...


class _GroundTruth(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def project(self) -> str | None: ...

    @property
    def sealed(self) -> bool: ...


#: the rules as one table: (route group, access, what a member may do there, what an admin may do there).
#: The "Who may do what" table of docs/service/accounts.md is this one (tests/server/access/test_policy.py compares
#: them).
RULES: Sequence[tuple[str, Access, str, str]] = (
    ("probes, sign-in page, static files, API docs", Access.PUBLIC, "yes", "yes"),
    (
        "public benchmarks: description, frame ids, board",
        Access.ANYONE,
        "yes (no token needed); the test set's name: members of its project",
        "yes",
    ),
    ("private benchmarks: description, frame ids, board", Access.READER, "members of its project", "yes"),
    (
        "evaluations: list, read, compare, gates",
        Access.READER,
        "their projects', none on a benchmark's test set",
        "all",
    ),
    ("evaluations: upload", Access.WRITER, "into their projects, not against a benchmark's test set", "all"),
    (
        "evaluations for a gate, not kept: run, read the result once",
        Access.READER,
        "a read-only token too: against the ground truths they see, not a benchmark's test set; the result is "
        "theirs alone, stored as no evaluation",
        "their own",
    ),
    ("frames of an evaluation", Access.READER, "their projects', never of a sealed ground truth", "never sealed"),
    ("ground truths: list, read", Access.READER, "their projects' and shared", "all"),
    ("ground truths: register, delete", Access.ADMIN, "no", "yes"),
    (
        "benchmark submissions: submit",
        Access.WRITER,
        "members of its project (every account when it is open to all), within the quota, while open",
        "as baselines (below)",
    ),
    (
        "own submissions: scores",
        Access.READER,
        "the public part's AP until the reveal, then all; never a count of the test set",
        "all (submissions/all)",
    ),
    (
        "own submissions: frames (TP, FP, FN per frame)",
        Access.READER,
        "in a phase on open labels only, never on a sealed test set",
        "their baselines', on open labels",
    ),
    ("own submissions: publish, withdraw", Access.WRITER, "until the benchmark closes", "their baselines"),
    (
        "benchmark baselines: submit, publish, withdraw",
        Access.WRITER,
        "no",
        "under no quota, shown unranked, until the close",
    ),
    ("benchmark teams: list", Access.READER, "who may take part in it", "yes"),
    (
        "benchmark teams: make one, join one, leave one",
        Access.WRITER,
        "who may take part: makes one inviting others who may, joins one that invited them, leaves theirs (one "
        "team each a benchmark, at most its team size; none changes once its last phase has closed)",
        "no (admins submit baselines)",
    ),
    ("benchmarks: create, close, reopen, reveal, rescore, disqualify", Access.ADMIN, "no", "yes"),
    (
        "joining by an invitation: the page, the JSON route",
        Access.PUBLIC,
        "anyone with the link, while it has uses and has not expired: makes an account that takes part in its "
        "benchmark (a member of its project) and in no other, and uploads no evaluation",
        "yes",
    ),
    ("accounts: users, projects, members, tokens, audit log", Access.ADMIN, "no", "yes"),
    ("jobs: list, cancel, re-run", Access.ADMIN, "no", "yes"),
    ("metrics", Access.SCRAPER, "with the metrics token only", "yes (read-only tokens too)"),
)


def identity(caller: Caller) -> dict[str, bool | str]:
    """What ``GET /v1/me`` shows of a caller (``kitti-eval login`` says it): the user, whether an admin, whether
    read-only; never the token nor its id."""
    return {"user": caller.name, "admin": caller.is_admin, "read_only": not caller.can_write}


def _admit_scraper(own: str | None, accounts: bool, caller: Caller, bearer: str | None) -> Caller | None:
    """``/metrics``: with a token of its own (``own``), that token only; else in accounts mode an admin's (a
    read-only token will do: every tenant's activity is not a participant's to see); None: as a reader."""
    if own is not None:
        if bearer is None:
            raise Unauthorized("the metrics need their token: send 'Authorization: Bearer <KITTI_EVAL_METRICS_TOKEN>'")
        if not hmac.compare_digest(bearer.encode(), own.encode()):
            raise Forbidden("the metrics token is not valid")
        return Caller("metrics-scraper", scopes=frozenset({READ}), client=caller.client, signed_in=True)
    if not accounts:
        return None
    if not caller.signed_in:
        raise Unauthorized("sign in: send 'Authorization: Bearer <token>'")
    if not caller.is_admin:
        raise Forbidden("the metrics are for admins (or for a scraper's own token, KITTI_EVAL_METRICS_TOKEN)")
    return caller


class Policy:
    """Every "may this caller see / do this" of the service. Stateless but for the mode and the tokens it
    compares; what it needs to know about the benchmarks' test sets it asks ``test_sets`` (ground truth name
    -> the names of the benchmarks whose test set it is)."""

    def __init__(
        self,
        mode: AuthMode,
        *,
        admin_token: Callable[[], str],
        test_sets: Callable[[], Mapping[str, Sequence[str]]],
        metrics_token: Callable[[], str | None] = lambda: None,
    ) -> None:
        self.mode = mode
        self._admin_token = admin_token
        self._metrics_token = metrics_token
        self._test_sets = test_sets

    @property
    def accounts(self) -> bool:
        return self.mode is AuthMode.ACCOUNTS

    # -- questions the rest of the service asks (nothing outside this module and accounts.py reads a caller's
    # rights or the mode) -----------------------------------------------------------------------------------
    def has_accounts(self) -> bool:
        """Whether callers sign in (accounts mode): there is a sign-in page, sessions, submissions."""
        return self.accounts

    def without_token(self, client: str) -> Caller:
        """The caller a request without a token is: open mode's everyone, accounts mode's anonymous reader."""
        return self.anonymous(client) if self.accounts else self.everyone(client)

    def job_owner(self, caller: Caller) -> str | None:
        """Whose share of the queue an accepted job counts against: the caller's in accounts mode, nobody's in
        open mode (everyone is the same caller there)."""
        return caller.name if self.accounts else None

    def is_signed_in(self, caller: Caller) -> bool:
        """Whether the caller has anything of their own to list (a reader without a token has not)."""
        return caller.signed_in

    def audits_refusal(self, caller: Caller) -> bool:
        """Whether a refused use of the caller's rights goes to the audit log: a signed-in account's."""
        return self.accounts and caller.signed_in

    def checks_csrf(self, caller: Caller) -> bool:
        """Whether the caller's changes carry a CSRF token: a web session's (its cookie goes along by itself)."""
        return caller.session

    def may_open_session(self, caller: Caller) -> bool:
        """A web session is a user's: the admin token (no user) cannot sign in to the pages."""
        return caller.token_id is not None

    def is_baseline(self, caller: Caller) -> bool:
        """An admin's submission is a baseline: under no quota, on the board without a rank."""
        return caller.is_admin

    def counts_quota(self, caller: Caller) -> bool:
        """Whether the caller's submissions are counted against a benchmark's quota: a participant's, not an
        admin's baselines."""
        return self.is_participant(caller) and not caller.is_admin

    def projects_of(self, caller: Caller, every: Callable[[], Sequence[str]]) -> list[str]:
        """The projects the caller's uploads may go to: theirs (``every()`` for an admin); none in open mode."""
        if not self.accounts:
            return []
        return list(every()) if caller.projects is None else sorted(caller.projects)

    # -- callers -----------------------------------------------------------------------------------------
    def everyone(self, client: str = "local") -> Caller:
        """Open mode's caller: sees and changes everything but the admin actions."""
        return Caller("anyone", projects=None, scopes=ALL_SCOPES, client=client, signed_in=True)

    def anonymous(self, client: str = "local") -> Caller:
        """Accounts mode, no token: sees public benchmarks only."""
        return Caller("anonymous", client=client)

    @staticmethod
    def admin_token_caller(client: str = "local") -> Caller:
        """Whoever presents the admin token: an admin of every project."""
        return Caller("admin-token", is_admin=True, projects=None, scopes=ALL_SCOPES, client=client, signed_in=True)

    @staticmethod
    def command_line(login: str) -> Caller:
        """``kitti-eval admin``: whoever may open the service's database acts as an admin."""
        return Caller(f"cli:{login}", is_admin=True, projects=None, scopes=ALL_SCOPES, client="cli", signed_in=True)

    def own_metrics_token(self) -> bool:
        """Whether ``/metrics`` has a token of its own (a scraper's, not an account's)."""
        return self._metrics_token() is not None

    def is_admin_token(self, presented: str | None) -> bool:
        expected = self._admin_token()
        if not presented or not expected:
            return False
        return hmac.compare_digest(presented.encode(), expected.encode())

    # -- routes ------------------------------------------------------------------------------------------
    def admit(
        self, access: Access, caller: Caller, *, method: str, bearer: str | None, csrf: str | None, header: bool = False
    ) -> Caller:
        """The caller a route declared with ``access`` runs for, or the refusal (401/403). ``bearer``: the
        request's bearer token (open mode's admin actions, ``/metrics``' own token); ``csrf``: the CSRF token
        the request carries (``header``: in the X-CSRF-Token header, else a form's field), checked for a web
        session's changes."""
        if access is Access.PUBLIC or access is Access.ANYONE:
            return caller
        if access is Access.SCRAPER:
            scraper = _admit_scraper(self._metrics_token(), self.accounts, caller, bearer)
            if scraper is not None:
                return scraper
            access = Access.READER
        if access is Access.ADMIN and not self.accounts:
            if caller.is_admin:
                return caller
            if bearer is None:
                raise Unauthorized("this action needs the admin token: send 'Authorization: Bearer <token>'")
            if not self.is_admin_token(bearer):
                raise Forbidden("the admin token is not valid")
            return self.admin_token_caller(caller.client)
        if not caller.signed_in:
            raise Unauthorized("sign in: send 'Authorization: Bearer <token>'")
        if access is Access.ADMIN and not caller.is_admin:
            raise Forbidden("this action is for admins")
        if access in (Access.WRITER, Access.ADMIN) and not caller.can_write:
            raise Forbidden("this token is read-only")
        if method.upper() not in SAFE_METHODS:
            self.check_csrf(caller, csrf, header=header)  # whatever the route: a session's change carries it
        return caller

    # -- the sign-in form's CSRF token -------------------------------------------------------------------------
    def _signin_mac(self, issued: str) -> str:
        key = hashlib.sha256(b"kitti-eval sign-in form:" + self._admin_token().encode()).digest()
        return hmac.new(key, issued.encode(), hashlib.sha256).hexdigest()

    def issue_signin_csrf(self, now: float | None = None) -> str:
        """A CSRF token for the sign-in form (there is no session yet): issued and signed by the service (with a
        key derived from the admin token, the same in every process and replica), valid for
        :data:`SIGNIN_CSRF_S` seconds."""
        issued = f"{int((time.time() if now is None else now) + SIGNIN_CSRF_S)}.{secrets.token_urlsafe(16)}"
        return f"{issued}.{self._signin_mac(issued)}"

    def check_signin_csrf(
        self, sent: object, cookie: str | None, now: float | None = None, *, form: str = "sign-in"
    ) -> None:
        """The token of a form shown before there is a session (``form``: ``sign-in``, ``join``, as the refusal
        names it): the one the form's page set in its cookie, issued by this service and not expired. A pair the
        client made up, however alike, is refused."""
        if not (isinstance(sent, str) and cookie and hmac.compare_digest(sent.encode(), cookie.encode())):
            raise Forbidden(f"the {form} form is stale or came from another site; try again")
        issued, _, mac = sent.rpartition(".")
        expires, _, _ = issued.partition(".")
        fresh = expires.isdigit() and int(expires) > (time.time() if now is None else now)
        if not (issued and fresh and hmac.compare_digest(mac.encode(), self._signin_mac(issued).encode())):
            raise Forbidden(f"the {form} form is stale or came from another site; try again")

    def check_csrf(self, caller: Caller, sent: str | None, *, header: bool = False) -> None:
        """A web session's change carries the session's CSRF token (a form's ``csrf`` field, a script's
        ``X-CSRF-Token`` header); a page on another site cannot know it."""
        if caller.session and not (sent and caller.csrf and hmac.compare_digest(sent, caller.csrf)):
            if header:
                raise Forbidden("the X-CSRF-Token header does not hold this web session's CSRF token")
            raise Forbidden("the form is stale or came from another site (no valid CSRF token); reload the page")

    # -- projects, evaluations, ground truths ------------------------------------------------------------
    def project_filter(self, caller: Caller) -> frozenset[str] | None:
        """The projects whose records the caller may list (None: all)."""
        return caller.projects

    def sees_project(self, caller: Caller, project: str | None) -> bool:
        return caller.projects is None or (project is not None and project in caller.projects)

    def sees_ground_truth(self, caller: Caller, record: _GroundTruth) -> bool:
        """Shared ground truths (no project: the demo, those registered in open mode) are every signed-in
        caller's."""
        return self._sees_ground_truths_of(caller, record.project)

    def _sees_ground_truths_of(self, caller: Caller, project: str | None) -> bool:
        """Whether the caller sees the ground truths of ``project`` (None: the shared ones)."""
        return caller.signed_in and (project is None or self.sees_project(caller, project))

    def sees_evaluation(self, caller: Caller, record: _Evaluation) -> bool:
        """Their projects' evaluations; none against a benchmark's test set but an admin's (one made before the
        benchmark existed would score the test set beyond the quota)."""
        if not caller.signed_in or not self.sees_project(caller, record.project):
            return False
        return caller.is_admin or record.gt_name is None or record.gt_name not in self._test_sets()

    def hidden_ground_truths(self, caller: Caller) -> list[str]:
        """The ground truths whose evaluations the caller may not list: the benchmarks' test sets, but for
        admins."""
        return [] if caller.is_admin else sorted(self._test_sets())

    def require_evaluation(self, caller: Caller, record: _Evaluation | None, evaluation_id: str) -> None:
        """404, the same for another project's evaluation as for a missing one."""
        if record is None or not self.sees_evaluation(caller, record):
            raise NotFound(f"no evaluation with id {echo(evaluation_id)}")

    def require_ground_truth(self, caller: Caller, record: _GroundTruth | None, name: str) -> None:
        if record is None or not self.sees_ground_truth(caller, record):
            raise NotFound(f"no ground truth named {echo(name)}; GET /v1/ground-truths lists them")

    def may_evaluate_against(self, caller: Caller, record: _GroundTruth) -> None:
        """A benchmark's test set is scored only through the benchmark's submissions (under its quota);
        admins may evaluate against it (their baselines), audited by the caller."""
        if caller.is_admin:
            return
        if caller.invited_to is not None:
            raise Forbidden(
                f"an account made by an invitation takes part in benchmark {caller.invited_to!r} and nothing "
                f"more: it submits there (POST /v1/benchmarks/{caller.invited_to}/submissions), it uploads no "
                "evaluation"
            )
        benchmarks = list(self._test_sets().get(record.name, ()))
        if benchmarks:
            names = ", ".join(repr(b) for b in benchmarks)
            raise Forbidden(
                f"the ground truth {record.name!r} is the test set of benchmark {names}: it is scored only "
                f"through the benchmark's submissions (POST /v1/benchmarks/{benchmarks[0]}/submissions)"
            )

    def is_test_set(self, record: _GroundTruth) -> bool:
        return record.name in self._test_sets()

    def require_frames(self, record: _GroundTruth, evaluation_id: str) -> None:
        """No per-frame view of a sealed ground truth leaves the service, for anyone."""
        if record.sealed:
            raise Sealed(
                f"the ground truth {record.name!r} of evaluation {evaluation_id} is sealed: only aggregate "
                "results (AP, curves, error totals) are available, no per-frame view"
            )

    # -- benchmarks --------------------------------------------------------------------------------------
    def sees_benchmark(self, caller: Caller, *, benchmark: str, public: bool, project: str | None) -> bool:
        """A public benchmark is everyone's (without a token too); a private one its project's members' (every
        signed-in caller's when it has no project), and of an account made by an invitation, its invitation's
        alone."""
        if public or caller.is_admin:
            return True
        if not caller.signed_in or (caller.invited_to is not None and caller.invited_to != benchmark):
            return False
        return project is None or self.sees_project(caller, project)

    def names_test_set(self, caller: Caller, *, project: str | None) -> bool:
        """Whether the caller reads the name of a benchmark's test set: those who see the ground truth itself
        (admins, the members of its project, every signed-in account when it is shared). An anonymous visitor
        of a public benchmark, or another project's member, never learns that it exists."""
        return caller.is_admin or self._sees_ground_truths_of(caller, project)

    def may_take_part(self, caller: Caller, *, benchmark: str, project: str | None, open_to_all: bool) -> bool:
        """Who may submit to a benchmark they see (``benchmark``: its name as participants address it, the same
        for all its phases): a participant (:meth:`is_participant`) who is a member of the test set's project
        (every signed-in account when the test set is shared), or any participant when the benchmark is open to
        all; an account made by an invitation, in its invitation's benchmark only. Reading a public benchmark is
        not taking part in it. An admin submits baselines to every benchmark."""
        if not self.is_participant(caller):
            return False
        if caller.invited_to is not None and caller.invited_to != benchmark:
            return False
        return caller.is_admin or open_to_all or project is None or self.sees_project(caller, project)

    def administers(self, caller: Caller) -> bool:
        """An admin: sees every project's records and the benchmarks' jobs, submits baselines."""
        return caller.is_admin

    def is_participant(self, caller: Caller) -> bool:
        """Who may submit: a signed-in user's own token (not the admin token, not open mode's everyone). An
        admin's submission is a baseline: counted against no quota, shown on the board without a rank."""
        return self.accounts and caller.signed_in and caller.token_id is not None

    def owns(self, caller: Caller, participant: str) -> bool:
        """A submission is its participant's: only they read its scores, publish or withdraw it."""
        return caller.signed_in and caller.token_id is not None and caller.name == participant

    def sees_job(self, caller: Caller, owner: str, *, project: str | None = None, open_to_all: bool = False) -> bool:
        """A job is its owner's (who uploaded or submitted) while they still see what it is for (``project``: an
        evaluation's project, a benchmark's test set's; a member removed from it no longer does, but anyone still
        takes part in a benchmark ``open_to_all``), and every admin's."""
        if caller.is_admin:
            return True
        sees = project is None or open_to_all or self.sees_project(caller, project)
        return caller.signed_in and caller.name == owner and sees

    def require_admin(self, caller: Caller) -> None:
        """For what a route already declared ADMIN and a domain method checks again (the command line's
        caller is an admin)."""
        if not caller.is_admin:
            raise Forbidden("this action is for admins")


# -- evaluations a gate asks for without keeping them: beside the class (whose size is kept down) ------------------
def may_gate_unkept(caller: Caller) -> None:
    """An evaluation a gate asks for without keeping it (stored as no evaluation, its result read once by its owner)
    is any signed-in caller's to ask for, a read-only token's too: it changes nothing anyone else sees, and it
    spends the queue's compute under the caller's share as an upload does (:meth:`Policy.may_evaluate_against`
    still refuses a benchmark's test set)."""
    if not caller.signed_in:
        raise Unauthorized("sign in: send 'Authorization: Bearer <token>'")


def owns_gate_result(caller: Caller, owner: str) -> bool:
    """A gate's result is read by the caller who asked for it alone (an admin too reads only their own)."""
    return caller.signed_in and caller.name == owner


# -- invitations, teams and open labels: the benchmarks' rules beside the class (whose size is kept down) ----------
def invited_projects(*, project: str | None, open_to_all: bool, wanted: str | None) -> tuple[str, ...]:
    """The projects an account made by an invitation to a benchmark is a member of: the benchmark's test set's
    project when only its members take part (``wanted``, the host's ``--project``, must be that one), else the
    project the host named, if any. Nothing more: an invited account is never an admin, and sees what the members
    of those projects see."""
    if project is not None and not open_to_all:
        if wanted is not None and wanted != project:
            raise BadRequest(
                f"the benchmark's test set is project {project!r}'s and only its members take part: an invitation "
                f"to it makes members of {project!r} (leave --project out)"
            )
        return (project,)
    return (wanted,) if wanted is not None else ()


# -- teams and open labels ----------------------------------------------------------------------------------------
def may_join_team(user: _User | None, *, benchmark: str, project: str | None, open_to_all: bool) -> bool:
    """Whom a participant may invite to a team: an account that is not an admin's (an admin submits baselines)
    and that may take part in the benchmark (a member of its test set's project, any account when the test set is
    shared or the benchmark is open to all; an account made by an invitation, in its invitation's benchmark
    only)."""
    if user is None or user.is_admin:
        return False
    if user.invited_to is not None and user.invited_to != benchmark:
        return False
    return open_to_all or project is None or project in user.projects


def sees_teams(policy: Policy, caller: Caller, *, benchmark: str, project: str | None, open_to_all: bool) -> bool:
    """A benchmark's teams and their members are seen by those who may take part in it, and by admins (the board
    names the team of each published entry that is not anonymous)."""
    return caller.is_admin or policy.may_take_part(
        caller, benchmark=benchmark, project=project, open_to_all=open_to_all
    )


def require_open_labels(*, open_labels: bool, what: str) -> None:
    """A submission's frames are shown to its participant in a phase on open labels only: a sealed test set's
    per-frame view never leaves the service."""
    if not open_labels:
        raise Sealed(
            f"the {what} is on a sealed test set: only aggregate results are shown, no per-frame view (a phase on "
            "open labels shows its participants their frames)"
        )


def default_project(policy: Policy, caller: Caller, exists: Callable[[str], bool], wanted: str | None) -> str | None:
    """The project a new evaluation of the caller goes to when its ground truth has none: ``wanted`` if it
    is one of theirs (404 as a missing one otherwise), their only project, or None in open mode; 400 when
    they have several and named none."""
    if not policy.accounts:
        return None
    if wanted:
        if not policy.sees_project(caller, wanted) or not exists(wanted):
            raise NotFound(f"no project of yours named {echo(wanted)}")
        return wanted
    if caller.projects is not None and len(caller.projects) == 1:
        return next(iter(caller.projects))
    mine = ", ".join(sorted(caller.projects)) if caller.projects is not None else "any project"
    raise BadRequest(f"name the project of the evaluation (form field 'project'): {mine or 'you have none'}")
