"""``kitti-eval compare A B``: per-value differences between two results, with paired bootstrap
intervals when both are predictions."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import ConfigError, InputError
from .common import EXIT_OK, add_config_options, config, emit, evaluate_doc, read_result_json


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compare",
        help="per-value differences between two results",
        description="Per-value differences B - A between two results, with paired bootstrap intervals over "
        "frames when both are predictions (--gt) and --bootstrap N is given.",
    )
    p.add_argument("a", type=Path, help="result A: a JSON result, or predictions (with --gt)")
    p.add_argument("b", type=Path, help="result B: a JSON result, or predictions (with --gt)")
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
            doc_a, doc_b, intervals, args.bootstrap, args.seed if args.bootstrap else None, errors_only=args.errors
        ),
        args.format,
        every_value=args.all,
    )
    emit(text, args.output)
    return EXIT_OK
