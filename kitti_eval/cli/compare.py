"""``kitti-eval compare A B``: per-value differences between two results, with paired bootstrap
intervals when both are predictions. ``kitti-eval compare A B C ...`` (or ``--pred``): the results ranked by
one key, each with its interval, its rank range and whether it leads the next significantly."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import ConfigError, InputError
from .common import EXIT_OK, add_config_options, config, emit, evaluate_doc, read_result_json


class _Intermixed(argparse.ArgumentParser):
    """Results and options in any order (``compare A --gt GT B``), as when A and B were two positionals of
    their own: a positional that takes any number of values would otherwise stop at the first option."""

    _parsing = False

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        if self._parsing:  # parse_known_intermixed_args calls this again: the plain parse, then
            return super().parse_known_args(args, namespace)
        self._parsing = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._parsing = False


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compare",
        help="per-value differences between two results, or many results ranked",
        description="Per-value differences B - A between two results (the table's columns headed by their file "
        "names), with paired bootstrap intervals over "
        "frames when both are predictions (--gt) and --bootstrap N is given. With three results or more (or "
        "--pred, or --key): a table ranked by one key, with each result's 95% interval and rank range and "
        "whether its lead over the next is significant, from the same resamples for every result.",
    )
    p.__class__ = _Intermixed  # (a subparser of its own class: add_parser takes none)
    p.add_argument(
        "results",
        nargs="*",
        type=Path,
        metavar="RESULT",
        help="A B: a JSON result or predictions (with --gt) each; three or more: the results to rank",
    )
    p.add_argument(
        "--pred",
        nargs="+",
        action="extend",
        default=[],
        metavar="PRED",
        help="results to rank in one table: paths or quoted globs ('runs/*/result.pkl'), repeatable",
    )
    p.add_argument(
        "--key",
        action="append",
        default=[],
        metavar="KEY",
        help="the ranked table's key, e.g. Car/3d/moderate/R40/strict; repeated: their mean (default: the mean "
        "moderate 3D AP, R40 strict, of the classes)",
    )
    p.add_argument("--gt", type=Path, help="ground truth, to evaluate predictions given as A or B")
    p.add_argument("--bootstrap", type=int, default=0, metavar="N", help="paired bootstrap resamples (e.g. 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    p.add_argument("--all", action="store_true", help="every value, not only R40 with the strict thresholds")
    p.add_argument(
        "--errors",
        action="store_true",
        help="which error types changed: the error decomposition of A and B (kitti-eval errors) side by side",
    )
    p.add_argument(
        "--sharded",
        action="store_true",
        help="A, B and --gt are quoted globs of shards of one set each, evaluated (and bootstrapped) part by part",
    )
    p.add_argument("--format", choices=["table", "json", "markdown"], default="table")
    p.add_argument("--output", "-o", type=Path, help="write the comparison here instead of stdout")
    add_config_options(p)
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.bootstrap import paired_bootstrap
    from ..analysis.result_diff import compare_documents, render_comparison

    if args.bootstrap < 0:
        raise ConfigError("--bootstrap must be >= 0")
    if args.pred or args.key or len(args.results) > 2:
        return run_ranked(args)
    if len(args.results) != 2:
        raise ConfigError("compare takes two results (A B), or three or more (or --pred) to rank")
    args.a, args.b = args.results
    is_json = [p.suffix.lower() == ".json" for p in (args.a, args.b)]
    intervals = None
    if args.sharded:
        if args.gt is None or any(is_json) or args.errors:
            raise ConfigError("--sharded compares predictions given in shards: A, B and --gt as globs, no --errors")
        from ..analysis.batch import expand_predictions
        from ..analysis.sharded import evaluate_sharded, paired_bootstrap_sharded

        gts, preds_a, preds_b = (expand_predictions([x]) for x in (args.gt, args.a, args.b))
        if args.bootstrap:
            res_a, res_b, intervals = paired_bootstrap_sharded(
                gts, preds_a, preds_b, config(args), resamples=args.bootstrap, seed=args.seed
            )
        else:
            res_a, res_b = (evaluate_sharded(gts, p, config(args)) for p in (preds_a, preds_b))
        doc_a, doc_b = res_a.to_dict(), res_b.to_dict()
    elif args.bootstrap:
        if any(is_json) or args.gt is None:
            raise ConfigError("--bootstrap needs predictions for both A and B, and --gt")
        from ..io.loaders import load_detections, load_ground_truth

        gt = load_ground_truth(args.gt)
        res_a, res_b, intervals = paired_bootstrap(
            gt,
            load_detections(args.a),
            load_detections(args.b),
            config(args),
            resamples=args.bootstrap,
            seed=args.seed,
        )
        doc_a, doc_b = res_a.to_dict(), res_b.to_dict()
    else:
        doc_a, doc_b = (
            read_result_json(p) if j else evaluate_doc(args, p, errors=args.errors)
            for p, j in zip((args.a, args.b), is_json)
        )
    if args.errors:
        if args.bootstrap:
            raise ConfigError("--errors and --bootstrap are not given together")
        lacking = [str(p) for p, d in zip((args.a, args.b), (doc_a, doc_b)) if "errors" not in d]
        if lacking:
            raise InputError(f"no error decomposition in {', '.join(lacking)}: save it with --errors")
    text = render_comparison(
        compare_documents(
            doc_a,
            doc_b,
            intervals,
            args.bootstrap,
            args.seed if args.bootstrap else None,
            errors_only=args.errors,
            names=_column_names(args.a, args.b),
        ),
        args.format,
        every_value=args.all,
    )
    emit(text, args.output)
    return EXIT_OK


def _column_names(a: Path, b: Path) -> tuple[str, str]:
    """The table's headers for A and B: the files' names, or the paths as given when the names are the same
    (``run1/result.pkl`` and ``run2/result.pkl``)."""
    if a.name != b.name:
        return a.name, b.name
    return str(a), str(b)


def run_ranked(args: argparse.Namespace) -> int:
    """Several results ranked by a key: with ``--bootstrap N`` every result's key under the same N resamples of
    the frames of ``--gt``, whence its interval, its rank range and its lead over the next."""
    from ..analysis.batch import expand_predictions
    from ..analysis.bootstrap import frame_weights
    from ..analysis.ranking import Ranked, Ranking, evaluate_resampled, key_of, render_ranking
    from ..core.result import ValueKey
    from ..io.loaders import load_detections, load_ground_truth

    if args.errors or args.sharded or args.all:
        raise ConfigError("--errors, --sharded and --all compare two results, not a ranked table")
    paths = expand_predictions([*args.results, *args.pred])
    if len(paths) < 2:
        raise ConfigError("a ranked table needs two results or more")
    cfg = config(args)
    keys = [ValueKey.parse(k) for k in args.key] or [ValueKey(c, "3d", "moderate") for c in cfg.classes]
    ranked = []
    if args.bootstrap:
        if args.gt is None or any(p.suffix.lower() == ".json" for p in paths):
            raise ConfigError("--bootstrap needs predictions for every result, and --gt")
        gt = load_ground_truth(args.gt)
        weights = frame_weights(gt.num_frames, args.bootstrap, args.seed)
        for path in paths:
            result, values = evaluate_resampled(gt, load_detections(path), cfg, keys, weights)
            ranked.append(Ranked(str(path), key_of(result.to_dict(), keys), values))
    else:
        for path in paths:
            doc = read_result_json(path) if path.suffix.lower() == ".json" else evaluate_doc(args, path)
            ranked.append(Ranked(str(path), key_of(doc, keys)))
    ranking = Ranking(tuple(keys), tuple(ranked), args.bootstrap, args.seed if args.bootstrap else None)
    emit(render_ranking(ranking, args.format), args.output)
    return EXIT_OK
