"""Hosted benchmarks: a sealed ground truth, participants' submissions under a quota, and a leaderboard.

Who takes part: a benchmark is seen by everyone who sees its ground truth (the members of the ground truth's
project, every signed-in account when the ground truth is shared) and, when it is public, its leaderboard by
anyone, without a token. Whoever sees a benchmark may submit to it with a token that may write (accounts mode
only: a participant is an account). Admins create, close, reopen, reveal and rescore benchmarks, list every
submission and disqualify entries.

A submission is checked first with :func:`kitti_eval.io.submission.validate_submission` against the test frame
ids (the sentences ``kitti-eval validate`` prints; a refused submission costs nothing), then counted against
the quota and accepted in one transaction (:meth:`Store.accept_submission`), then evaluated on the sealed set
and stored. Its participant sees its full (aggregate) result; nobody else sees it until it is published.

The public/private split: with ``split_percent`` p, a test frame is in the public part when the first 8 bytes
of sha256(seed + ":" + frame id), read as an integer, are below p % of 2**64. The seed is 32 random hex digits
drawn when the benchmark is created, stored in its row and never shown; the parts are therefore fixed for the
benchmark's life and unknown to participants. While the benchmark runs (or until an admin reveals the
ranking after the close) the board shows the scores on the public part; after the reveal, those on the
private part.
"""

from __future__ import annotations

import csv
import hashlib
import html
import io
import logging
import math
import re
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import THRESHOLD_SETS
from kitti_eval.errors import InputError, KittiEvalError
from kitti_eval.io.submission import SubmissionRules, validate_submission

from .accounts import Accounts, Caller
from .errors import ApiError, BadRequest, Conflict, Forbidden, NotFound, NotReady, echo
from .evaluator import EvalOptions, evaluate_document
from .service import FileIn, Service, sealed_document
from .store import BenchmarkRecord, GroundTruthRecord, QuotaRefused, SubmissionRecord, new_id
from .uploads import clean_filename, load_upload, receive_upload

__all__ = [
    "Benchmarks",
    "Benchmark",
    "QuotaExceeded",
    "InvalidSubmission",
    "DEFAULT_KEY",
    "render_markdown",
    "parse_quota",
    "in_public_part",
]

log = logging.getLogger("kitti_eval.server")

DEFAULT_KEY = "Car/3d/moderate/R40/strict"
_METRICS = ("bbox", "bev", "3d", "aos")
_DIFFICULTIES = ("easy", "moderate", "hard")
_RECALLS = ("R40", "R11")
_MAX_COLUMNS = 60
_LINK = re.compile(r"^https?://[^\s<>\"']{1,490}$")


class QuotaExceeded(ApiError):
    status_code = 429
    code = "quota_exceeded"

    def __init__(self, message: str, retry_after_s: int, retry_at: datetime) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})
        self.retry_at = retry_at


class InvalidSubmission(ApiError):
    """The submission breaks the rules: ``problems`` are the sentences ``kitti-eval validate`` prints."""

    status_code = 422
    code = "invalid_submission"

    def __init__(self, problems: list[str]) -> None:
        super().__init__(f"the submission is not valid ({len(problems)} problems): " + "; ".join(problems[:5]))
        self.problems = problems


# -------------------------------------------------------------------------------------------- parsing


def parse_quota(text: str) -> tuple[int, float]:
    """``N/DAYS`` (e.g. ``3/1``: three accepted submissions a participant per day)."""
    n, sep, days = text.partition("/")
    try:
        count, span = int(n), float(days) if sep else 1.0
    except ValueError:
        raise BadRequest(f"a quota is N/DAYS, e.g. 3/1; got {echo(text)}") from None
    if not 1 <= count <= 100_000 or not 0 < span <= 3650 or not math.isfinite(span):
        raise BadRequest("a quota is 1 to 100000 submissions per more than 0 and at most 3650 days")
    return count, span


def parse_column(text: str, classes: Sequence[str], sets: Sequence[str]) -> str:
    """``CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]]`` normalised to its five parts."""
    parts = text.strip().split("/")
    if not 3 <= len(parts) <= 5:
        raise BadRequest(f"a column is CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]], e.g. {DEFAULT_KEY}; got {echo(text)}")
    parts += ["R40", sets[0] if "strict" not in sets else "strict"][len(parts) - 3 :]
    cls, metric, difficulty, recall, oset = parts
    known = {c.lower(): c for c in classes}
    if cls.lower() not in known:
        raise BadRequest(f"column {echo(text)}: the class is one of {', '.join(classes)}")
    if metric not in _METRICS or difficulty not in _DIFFICULTIES or recall not in _RECALLS or oset not in sets:
        raise BadRequest(
            f"column {echo(text)}: metric {'/'.join(_METRICS)}, difficulty {'/'.join(_DIFFICULTIES)}, "
            f"recall {'/'.join(_RECALLS)}, set {'/'.join(sets)}"
        )
    return "/".join((known[cls.lower()], metric, difficulty, recall, oset))


def in_public_part(seed: str, frame_id: str, percent: float) -> bool:
    digest = hashlib.sha256(f"{seed}:{frame_id}".encode()).digest()
    return int.from_bytes(digest[:8], "big") < percent / 100 * 2**64


def _parse_time(value: str | datetime | None, what: str) -> datetime | None:
    if value is None or value == "":
        return None
    if isinstance(value, datetime):
        moment = value
    else:
        try:
            moment = datetime.fromisoformat(value.strip().replace("Z", "+00:00"))
        except ValueError:
            raise BadRequest(f"{what}: an ISO 8601 time, e.g. 2026-12-31T23:59:00+00:00; got {echo(value)}") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


# ------------------------------------------------------------------------------------------- Markdown

_INLINE = [
    (re.compile(r"`([^`]+)`"), r"<code>\1</code>"),
    (re.compile(r"\*\*([^*]+)\*\*"), r"<strong>\1</strong>"),
    (re.compile(r"\*([^*]+)\*"), r"<em>\1</em>"),
    (re.compile(r"\[([^\]]+)\]\((https?://[^\s)\"']+)\)"), r'<a href="\2" rel="nofollow noopener">\1</a>'),
]


def _inline(text: str) -> str:
    out = html.escape(text, quote=True)
    for pattern, replacement in _INLINE:
        out = pattern.sub(replacement, out)
    return out


def render_markdown(text: str) -> str:
    """A small Markdown subset as HTML: paragraphs, ``#`` headings, ``-`` lists, ``**bold**``, ``*emphasis*``,
    `` `code` `` and ``[links](https://...)``. Every character of the text is HTML-escaped first, so no tag,
    attribute or script of the author's reaches the page."""
    blocks: list[str] = []
    items: list[str] = []
    para: list[str] = []

    def flush() -> None:
        if para:
            blocks.append(f"<p>{_inline(' '.join(para))}</p>")
            para.clear()
        if items:
            blocks.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in items) + "</ul>")
            items.clear()

    for raw in text.splitlines():
        line = raw.strip()
        heading = re.match(r"^(#{1,3})\s+(.*)$", line)
        if not line:
            flush()
        elif heading:
            flush()
            level = len(heading.group(1)) + 2  # h3..h5 under the page's own headings
            blocks.append(f"<h{level}>{_inline(heading.group(2))}</h{level}>")
        elif line.startswith(("- ", "* ")):
            if para:
                flush()
            items.append(line[2:])
        else:
            if items:
                flush()
            para.append(line)
    flush()
    return "\n".join(blocks)


# ------------------------------------------------------------------------------------------ records


@dataclass(frozen=True)
class Benchmark(BenchmarkRecord):
    """A stored benchmark with its rules read from its row."""

    @classmethod
    def from_record(cls, record: BenchmarkRecord) -> Benchmark:
        return cls(**{f.name: getattr(record, f.name) for f in fields(record)})

    @property
    def key(self) -> list[str]:
        return list(self.config["key"])

    @property
    def columns(self) -> list[str]:
        return list(self.config["columns"])

    @property
    def quota(self) -> tuple[int, float]:
        return int(self.config["quota"][0]), float(self.config["quota"][1])

    @property
    def split_percent(self) -> float | None:
        value = self.config.get("split_percent")
        return None if value is None else float(value)

    def is_open(self, now: datetime | None = None) -> bool:
        now = now or datetime.now(timezone.utc)
        return not self.closed and self.opens_at <= now and (self.closes_at is None or now < self.closes_at)

    @property
    def phase(self) -> str:
        """Which scores the board shows: ``all`` (no split), ``public`` (the public part) or ``private``."""
        if self.split_percent is None:
            return "all"
        return "private" if self.revealed else "public"

    def options(self) -> EvalOptions:
        return EvalOptions(
            protocol=self.config["protocol"], classes=self.config["classes"], threshold_sets=self.config["sets"]
        )

    def describe(self) -> dict[str, Any]:
        """What anyone who sees the benchmark may read (never the split's seed)."""
        n, days = self.quota
        return {
            "name": self.name,
            "title": self.title,
            "description": self.description,
            "ground_truth": self.gt_name,
            "protocol": self.config["protocol"],
            "classes": self.config["classes"].split(","),
            "threshold_sets": self.config["sets"].split(","),
            "key": self.key,
            "columns": self.columns,
            "quota": {"submissions": n, "days": days},
            "public": self.public,
            "opens_at": self.opens_at.isoformat(),
            "closes_at": self.closes_at.isoformat() if self.closes_at else None,
            "open": self.is_open(),
            "closed": self.closed,
            "split_percent": self.split_percent,
            "revealed": self.revealed,
            "board": self.phase,
        }


def key_value(scores: Mapping[str, float | None], key: Sequence[str]) -> float | None:
    values = [scores.get(c) for c in key]
    if any(v is None for v in values):
        return None
    return round(sum(v for v in values if v is not None) / len(values), 4)


def _scores(doc: Mapping[str, Any], columns: Sequence[str]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for column in columns:
        cls, metric, difficulty, recall, oset = column.split("/")
        value: Any = doc.get("ap", {}).get(oset, {}).get(recall, {}).get(cls, {}).get(metric, {}).get(difficulty)
        out[column] = None if value is None else round(float(value), 4)
    return out


def _submission_view(record: SubmissionRecord, *, full: bool) -> dict[str, Any]:
    """A submission as its participant (``full``) or an admin listing sees it."""
    out = {
        "id": record.id,
        "benchmark": record.benchmark,
        "participant": record.participant,
        "created_at": record.created_at.isoformat(),
        "status": record.status,
        "filename": record.pred_filename,
        "sha256": record.pred_sha256,
        "size": record.pred_size,
        "published": bool(record.published),
        "method": record.method,
        "anonymous": bool(record.anonymous),
        "affiliation": record.affiliation,
        "link": record.link,
        "disqualified": bool(record.disqualified),
        "scored_at": record.scored_at.isoformat() if record.scored_at else None,
        "scores": (record.scores or {}).get("all"),
    }
    if full:
        out["result"] = record.result
    return out


# ------------------------------------------------------------------------------------------- service


class Benchmarks:
    """Benchmarks on the service's store, ground truths and evaluation machinery."""

    def __init__(self, service: Service) -> None:
        self.service = service
        self.store = service.store

    @property
    def accounts(self) -> Accounts:
        return self.service.accounts

    # -- seeing -------------------------------------------------------------------------------------------
    def _get(self, name: str) -> Benchmark:
        record = self.store.get_benchmark(name)
        if record is None:
            raise NotFound(f"no benchmark named {echo(name)}")
        return Benchmark.from_record(record)

    def sees(self, caller: Caller | None, bench: Benchmark) -> bool:
        """``caller`` None: no token (accounts mode)."""
        if bench.public:
            return True
        if caller is None:
            return False
        return caller.is_admin or caller.projects is None or bench.project is None or bench.project in caller.projects

    def get(self, name: str, caller: Caller | None) -> Benchmark:
        bench = self._get(name)
        if not self.sees(caller, bench):
            raise NotFound(f"no benchmark named {echo(name)}")
        return bench

    def visible(self, caller: Caller | None) -> list[Benchmark]:
        found = [Benchmark.from_record(r) for r in self.store.list_benchmarks()]
        return [b for b in found if self.sees(caller, b)]

    def frame_ids(self, name: str, caller: Caller | None) -> list[str]:
        """The test frame ids (public, as KITTI's: the labels are what is sealed)."""
        bench = self.get(name, caller)
        return list(self._ground_truth(bench)[1].frame_ids)

    def _ground_truth(self, bench: Benchmark) -> tuple[GroundTruthRecord, Annotations]:
        record = self.service.ground_truths.record(bench.gt_name)
        return record, self.service.ground_truths.load(record)

    # -- admin ----------------------------------------------------------------------------------------------
    def create(
        self,
        name: str,
        *,
        ground_truth: str,
        title: str | None = None,
        description: str = "",
        protocol: str = "official",
        classes: str = "Car,Pedestrian,Cyclist",
        threshold_sets: str = ",".join(THRESHOLD_SETS),
        key: Sequence[str] = (DEFAULT_KEY,),
        columns: Sequence[str] = (),
        quota: str = "3/1",
        public: bool = False,
        opens_at: str | datetime | None = None,
        closes_at: str | datetime | None = None,
        split_percent: float | None = None,
        actor: str,
        client: str = "local",
    ) -> Benchmark:
        self.accounts.check_name(name, "benchmark")
        record = self.service.ground_truths.record(ground_truth)
        if not record.sealed:
            raise BadRequest(
                f"the ground truth {ground_truth!r} is not sealed; a benchmark's test set is registered "
                "with sealed=true"
            )
        options = EvalOptions(protocol=protocol, classes=classes, threshold_sets=threshold_sets)
        config = options.config()  # the library's checks of the options
        class_names, sets = list(config.classes), list(config.threshold_sets)
        keys = [parse_column(k, class_names, sets) for k in key if k.strip()] or [DEFAULT_KEY]
        wanted = list(columns) or [f"{c}/3d/{d}" for c in class_names for d in _DIFFICULTIES]
        cols = list(dict.fromkeys(parse_column(c, class_names, sets) for c in wanted if c.strip()))
        if len(cols) > _MAX_COLUMNS:
            raise BadRequest(f"at most {_MAX_COLUMNS} columns")
        count, days = parse_quota(quota)
        if split_percent is not None and not 0 < split_percent < 100:
            raise BadRequest("split_percent is the public part of the test frames: more than 0 and less than 100")
        if len(description) > 20000 or len(title or "") > 200:
            raise BadRequest("a title is at most 200 characters, a description at most 20000")
        opens = _parse_time(opens_at, "opens") or datetime.now(timezone.utc)
        closes = _parse_time(closes_at, "closes")
        if closes is not None and closes <= opens:
            raise BadRequest("a benchmark closes after it opens")
        bench = BenchmarkRecord(
            name=name,
            title=title or name,
            description=description,
            gt_name=record.name,
            project=record.project,
            config={
                "protocol": protocol,
                "classes": ",".join(class_names),
                "sets": ",".join(sets),
                "key": keys,
                "columns": cols,
                "quota": [count, days],
                "split_percent": split_percent,
            },
            split_seed=secrets.token_hex(16) if split_percent is not None else None,
            public=public,
            opens_at=opens,
            closes_at=closes,
            closed=False,
            revealed=False,
            created_at=datetime.now(timezone.utc),
        )
        if not self.store.add_benchmark(bench):
            raise Conflict(f"a benchmark named {name!r} exists")
        self.accounts.audit(actor=actor, action="benchmark.add", target=name, client=client, detail=record.name)
        return self._get(name)

    def set_state(self, name: str, *, actor: str, client: str = "local", **values: bool) -> Benchmark:
        """close (closed=True), reopen (closed=False), reveal (revealed=True, only once closed)."""
        bench = self._get(name)
        if values.get("revealed") and bench.is_open():
            raise Conflict("the private ranking is revealed once the benchmark is closed")
        self.store.update_benchmark(name, **values)
        action = ",".join(f"{k}={v}" for k, v in sorted(values.items()))
        self.accounts.audit(actor=actor, action="benchmark.state", target=name, client=client, detail=action)
        return self._get(name)

    def all_submissions(self, name: str) -> list[dict[str, Any]]:
        self._get(name)
        return [_submission_view(r, full=False) for r in self.store.list_submissions(name)]

    def disqualify(self, name: str, submission_id: str, *, actor: str, client: str = "local") -> dict[str, Any]:
        record = self.store.get_submission(submission_id)
        if record is None or record.benchmark != name:
            raise NotFound(f"no submission {echo(submission_id)} in benchmark {echo(name)}")
        self.store.update_submission(submission_id, disqualified=True)
        self.accounts.audit(actor=actor, action="submission.disqualify", target=submission_id, client=client)
        again = self.store.get_submission(submission_id)
        assert again is not None
        return _submission_view(again, full=False)

    def rescore(self, name: str, *, actor: str, client: str = "local") -> dict[str, Any]:
        """Evaluate every stored submission again against the ground truth as registered now."""
        bench = self._get(name)
        record, gt = self._ground_truth(bench)
        done = failed = 0
        for row in self.store.list_submissions(name):
            content = self.store.prediction_content(row.pred_sha256)
            if content is None:
                failed += 1
                continue
            try:
                with self.service.scratch() as scratch:
                    upload = receive_upload(io.BytesIO(content), row.pred_filename, "predictions")
                    dt = load_upload(
                        upload, "detections", scratch, self.service.limits, known_frames=gt.frame_index()
                    ).annotations
                self._score(bench, record, gt, dt, row.id)
                done += 1
            except KittiEvalError:
                self.store.update_submission(row.id, status="failed")
                failed += 1
        self.accounts.audit(
            actor=actor, action="benchmark.rescore", target=name, client=client, detail=f"{done} rescored"
        )
        return {"benchmark": name, "rescored": done, "failed": failed, "ground_truth_sha256": record.sha256}

    # -- participants -------------------------------------------------------------------------------------
    def submit(self, name: str, predictions: FileIn, caller: Caller, *, client: str = "local") -> dict[str, Any]:
        """Validate, count against the quota and accept (one transaction), evaluate, store."""
        if self.service.draining.is_set():
            raise NotReady("the service is shutting down; submit again in a moment")
        if self.service.settings.auth != "accounts":
            raise Forbidden("benchmarks take submissions in accounts mode (KITTI_EVAL_AUTH=accounts)")
        if caller.token_id is None:
            raise Forbidden("a participant submits with their own token (kitti-eval admin token add USER)")
        bench = self.get(name, caller)
        if not bench.is_open():
            raise Conflict(f"the benchmark {name!r} is not open for submissions")
        record, gt = self._ground_truth(bench)
        with self.service.scratch() as scratch:
            upload = receive_upload(predictions.file, predictions.filename, "predictions")
            self._validate(upload.file, upload.filename, gt, scratch)
            count, days = bench.quota
            now = datetime.now(timezone.utc)
            window = timedelta(days=days)
            submission_id = new_id()
            accepted = SubmissionRecord(
                id=submission_id,
                benchmark=name,
                participant=caller.name,
                created_at=now,
                status="accepted",
                pred_filename=upload.filename,
                pred_sha256=upload.sha256,
                pred_size=upload.size,
            )
            try:
                self.store.accept_submission(accepted, limit=count, window_start=now - window, window=window)
            except QuotaRefused as e:
                retry = max(1, math.ceil((e.retry_at - datetime.now(timezone.utc)).total_seconds()))
                raise QuotaExceeded(
                    f"the quota of {count} accepted submissions per {days:g} days is used; the next one is "
                    f"accepted from {e.retry_at.isoformat()} (in {retry} s)",
                    retry,
                    e.retry_at,
                ) from None
            upload.file.seek(0)
            self.store.add_prediction_file(upload.sha256, upload.file.read())
            try:
                dt = load_upload(
                    upload, "detections", scratch / "pred", self.service.limits, known_frames=gt.frame_index()
                ).annotations
                self._score(bench, record, gt, dt, submission_id)
            except BaseException:
                self.store.update_submission(submission_id, status="failed")
                raise
        self.accounts.audit(
            actor=caller.actor, action="submission.add", target=f"{name} {submission_id}", client=client
        )
        return self.submission(name, submission_id, caller)

    def _validate(self, file: Any, filename: str, gt: Annotations, scratch: Path) -> None:
        """The CLI's checks (:func:`validate_submission`), their sentences naming the upload, not the scratch path."""
        shown = clean_filename(filename, "predictions")
        path = scratch / "submission"
        path.mkdir()
        target = path / "upload"
        file.seek(0)
        with open(target, "wb") as out:
            while chunk := file.read(1 << 20):
                out.write(chunk)
        file.seek(0)
        try:
            outcome = validate_submission(
                target, SubmissionRules(frames=tuple(gt.frame_ids)), limits=self.service.limits.archive
            )
        except InputError as e:
            raise type(e)(e.message.replace(str(target), shown), source=shown, frame=e.frame, field=e.field) from None
        if not outcome.ok:
            raise InvalidSubmission([line.replace(str(target), shown) for line in outcome.lines()])

    def _score(self, bench: Benchmark, record: GroundTruthRecord, gt: Annotations, dt: Annotations, sid: str) -> None:
        config = bench.options().config()
        columns = list(dict.fromkeys([*bench.columns, *bench.key]))
        doc = evaluate_document(gt, dt, config)
        scores: dict[str, dict[str, float | None]] = {"all": _scores(doc, columns)}
        percent = bench.split_percent
        if percent is not None and bench.split_seed:
            parts: dict[str, list[str]] = {"public": [], "private": []}
            for f in gt.frame_ids:
                parts["public" if in_public_part(bench.split_seed, f, percent) else "private"].append(f)
            for part, frames in parts.items():
                if frames:
                    part_doc = evaluate_document(gt.subset(frames), dt.subset(frames), config)
                    scores[part] = _scores(part_doc, columns)
                else:
                    scores[part] = dict.fromkeys(columns)
        self.store.update_submission(
            sid,
            status="scored",
            result=sealed_document(doc),
            scores=scores,
            gt_sha256=record.sha256,
            scored_at=datetime.now(timezone.utc),
        )

    def _own(self, name: str, submission_id: str, caller: Caller) -> SubmissionRecord:
        self.get(name, caller)
        record = self.store.get_submission(submission_id)
        if record is None or record.benchmark != name or (record.participant != caller.name and not caller.is_admin):
            raise NotFound(f"no submission of yours with id {echo(submission_id)}")
        return record

    def submission(self, name: str, submission_id: str, caller: Caller) -> dict[str, Any]:
        return _submission_view(self._own(name, submission_id, caller), full=True)

    def mine(self, name: str, caller: Caller) -> dict[str, Any]:
        bench = self.get(name, caller)
        records = self.store.list_submissions(name, participant=caller.name)
        count, days = bench.quota
        since = datetime.now(timezone.utc) - timedelta(days=days)
        used = sum(1 for r in records if r.created_at > since and r.status != "failed")
        return {
            "items": [_submission_view(r, full=False) for r in reversed(records)],
            "quota": {"submissions": count, "days": days, "used": used, "left": max(0, count - used)},
        }

    def publish(
        self,
        name: str,
        submission_id: str,
        caller: Caller,
        *,
        method: str,
        anonymous: bool = False,
        affiliation: str | None = None,
        link: str | None = None,
    ) -> dict[str, Any]:
        record = self._own(name, submission_id, caller)
        if record.status != "scored":
            raise Conflict("only a scored submission can be published")
        if record.disqualified:
            raise Conflict("the submission was disqualified")
        method = method.strip()
        if not 1 <= len(method) <= 100 or not method.isprintable():
            raise BadRequest("a method name is 1-100 printable characters")
        if affiliation is not None and (len(affiliation) > 200 or not affiliation.isprintable()):
            raise BadRequest("an affiliation is at most 200 printable characters")
        if link and not _LINK.fullmatch(link):
            raise BadRequest("a link is an http:// or https:// address of at most 500 characters")
        self.store.update_submission(
            submission_id,
            published=True,
            method=method,
            anonymous=anonymous,
            affiliation=affiliation or None,
            link=link or None,
            published_at=datetime.now(timezone.utc),
        )
        return self.submission(name, submission_id, caller)

    def withdraw(self, name: str, submission_id: str, caller: Caller) -> dict[str, Any]:
        self._own(name, submission_id, caller)
        self.store.update_submission(submission_id, published=False, published_at=None)
        return self.submission(name, submission_id, caller)

    # -- leaderboard -----------------------------------------------------------------------------------------
    def leaderboard(
        self, name: str, caller: Caller | None, *, sort: str | None = None, order: str | None = None
    ) -> dict[str, Any]:
        bench = self.get(name, caller)
        phase = bench.phase
        entries: list[dict[str, Any]] = []
        for row in self.store.list_submissions(name, published_only=True):
            if row.status != "scored":
                continue
            scores = (row.scores or {}).get(phase) or {}
            entries.append(
                {
                    "id": row.id,
                    "method": row.method,
                    "participant": None if row.anonymous else row.participant,
                    "affiliation": None if row.anonymous else row.affiliation,
                    "link": None if row.anonymous else row.link,
                    "anonymous": bool(row.anonymous),
                    "date": row.created_at.isoformat(),
                    "key": key_value(scores, bench.key),
                    "columns": {c: scores.get(c) for c in bench.columns},
                }
            )
        # the rank: by the key, best first, ties by submission time (the list is oldest first: sort is stable)
        ranked = sorted(entries, key=lambda e: (e["key"] is None, -(e["key"] or 0.0)))
        for i, entry in enumerate(ranked, 1):
            entry["rank"] = i
        sort = sort or "key"
        if sort not in ("key", "rank", "method", "date", *bench.columns):
            raise BadRequest(f"sort by rank, key, method, date or a column: {', '.join(bench.columns)}")
        order = order or ("asc" if sort in ("rank", "method", "date") else "desc")
        if order not in ("asc", "desc"):
            raise BadRequest("order is asc or desc")
        rows = ranked
        if sort not in ("key", "rank") or order != "desc" or sort == "rank":
            rows = self._sorted(ranked, sort, order)
        return {
            "benchmark": bench.name,
            "title": bench.title,
            "board": phase,
            "key": bench.key,
            "columns": bench.columns,
            "sort": sort,
            "order": order,
            "entries": rows,
        }

    @staticmethod
    def _sorted(entries: list[dict[str, Any]], sort: str, order: str) -> list[dict[str, Any]]:
        def value(e: dict[str, Any]) -> Any:
            if sort in ("key", "rank", "method", "date"):
                return e[sort]
            return e["columns"].get(sort)

        present = [e for e in entries if value(e) is not None]
        absent = [e for e in entries if value(e) is None]
        present.sort(key=lambda e: e["date"])  # ties by submission time
        if order == "desc":
            # stable descending sort that keeps earlier submissions first among ties
            present.sort(key=lambda e: _Desc(value(e)))
        else:
            present.sort(key=value)
        return present + absent

    def leaderboard_csv(self, board: Mapping[str, Any]) -> str:
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        key_name = "key (" + " + ".join(board["key"]) + ")" if len(board["key"]) > 1 else board["key"][0]
        writer.writerow(["rank", "method", "participant", "affiliation", "link", "date", key_name, *board["columns"]])
        for e in board["entries"]:
            cells = [e["rank"], e["method"], e["participant"], e["affiliation"], e["link"], e["date"], e["key"]]
            cells += [e["columns"].get(c) for c in board["columns"]]
            writer.writerow(["" if c is None else _cell(c) for c in cells])
        return out.getvalue()


class _Desc:
    """Reverses the order of a sort key (for a stable descending sort)."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __lt__(self, other: _Desc) -> bool:
        return bool(other.value < self.value)


def _cell(value: object) -> object:
    """A CSV cell that a spreadsheet does not read as a formula."""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value
