"""``kitti-eval gate``: AP rules on a result, exit 3 when one fails (for CI jobs)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from .common import EXIT_GATE, EXIT_OK, add_config_options, config, evaluate_doc, read_result_json, wrote


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "gate",
        help="check AP rules on a result (exit 3 when a rule fails)",
        description="Check AP rules on a result: floors, maximum drops against a baseline, required classes. "
        "Exit 0 when every rule passes, 3 when one fails, 1 on bad input, 2 on usage errors.",
        epilog="Values are named Class/metric/difficulty[/R40|R11[/strict|loose]] (default R40, strict). "
        "A rule on a value that is null (not evaluated) fails.",
    )
    src = p.add_argument_group("the result to gate: a saved JSON result, or ground truth and predictions")
    src.add_argument("--result", type=Path, help="a JSON result written by 'kitti-eval --format json'")
    src.add_argument("--gt", type=Path, help="ground truth (evaluated with --pred)")
    src.add_argument("--pred", type=Path, help="predictions to evaluate")
    src.add_argument(
        "--sharded",
        action="store_true",
        help="--gt, --pred and a --baseline given as predictions are quoted globs of shards of one set each",
    )
    add_config_options(p)
    rules = p.add_argument_group("rules")
    rules.add_argument(
        "--min",
        "--rule",
        dest="floors",
        action="append",
        default=[],
        metavar="RULE",
        help="a bound such as 'Car/3d/moderate/R40 >= 78.5' (any of >=, >, <=, <), or on an error type of the "
        "decomposition, 'Car/3d/moderate/localization <= 5' (then --gt/--pred are evaluated with it); repeatable",
    )
    rules.add_argument(
        "--max-drop",
        action="append",
        default=[],
        metavar="[VALUE=]N",
        help="largest allowed drop against --baseline, in AP points: N for every value, or "
        "Car/3d/moderate=N for one; repeatable",
    )
    rules.add_argument(
        "--require-class",
        action="append",
        default=[],
        metavar="CLASS",
        help="fail unless this class was evaluated; repeatable",
    )
    rules.add_argument("--rules", type=Path, help="rules from a TOML file (floor, max_drop, require_classes)")
    p.add_argument(
        "--baseline",
        type=Path,
        help="the result to compare with: a JSON result, or predictions evaluated against --gt; with --service, "
        "a stored evaluation's id (default: none)",
    )
    from .remote import add_service_arguments

    add_service_arguments(p)
    p.add_argument(
        "--baseline-label",
        metavar="KEY=VALUE",
        help="with --service: the baseline is the newest evaluation with this label (branch=main) against the "
        "same ground truth, from the service's history (default: none)",
    )
    sig = p.add_argument_group("significance")
    sig.add_argument(
        "--significant",
        action="store_true",
        help="fail a drop only if a paired bootstrap over frames says it is significant (95%%); "
        "needs --gt, --pred and --baseline as predictions",
    )
    sig.add_argument("--bootstrap", type=int, default=1000, metavar="N", help="resamples for --significant")
    sig.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    out = p.add_argument_group("reports")
    out.add_argument("--markdown", type=Path, help="also write the verdict as Markdown (CI job summaries)")
    out.add_argument("--junit", type=Path, help="also write the verdict as JUnit XML")
    out.add_argument("--show-passed", action="store_true", help="list passing checks too")
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.gate import (
        render_junit,
        render_verdict,
        render_verdict_markdown,
        rules_from_options,
        rules_from_toml,
        run_gate,
    )

    rules = rules_from_options(
        args.floors,
        args.max_drop,
        args.require_class,
        baseline=bool(args.baseline or args.baseline_label),
        also=rules_from_toml(args.rules) if args.rules else None,
    )
    if args.result and (args.gt or args.pred):
        raise ConfigError("give either --result or --gt with --pred, not both")
    if not args.result and not (args.gt and args.pred):
        raise ConfigError("give the result to gate: --result R.json, or --gt and --pred")

    intervals = None
    if args.service:
        from .remote import run_gate as evaluated_there

        current, baseline = evaluated_there(args, errors=rules.needs_errors)
    elif args.baseline_label:
        raise ConfigError("--baseline-label reads a service's history: add --service")
    elif args.sharded:
        current, baseline, intervals = _sharded(args, rules.needs_errors)
    elif args.significant:
        if not (args.gt and args.pred and args.baseline) or args.baseline.suffix.lower() == ".json":
            raise ConfigError("--significant needs --gt, --pred and a --baseline given as predictions")
        from ..analysis.bootstrap import paired_bootstrap
        from ..io.loaders import load_detections, load_ground_truth

        res_base, res_now, intervals = paired_bootstrap(
            load_ground_truth(args.gt),
            load_detections(args.baseline),
            load_detections(args.pred),
            config(args),
            resamples=args.bootstrap,
            seed=args.seed,
        )
        current, baseline = res_now.to_dict(), res_base.to_dict()
    else:
        current = (
            read_result_json(args.result) if args.result else evaluate_doc(args, args.pred, errors=rules.needs_errors)
        )
        baseline = None
        if args.baseline:
            baseline = (
                read_result_json(args.baseline)
                if args.baseline.suffix.lower() == ".json"
                else evaluate_doc(args, args.baseline)
            )
    verdict = run_gate(current, rules, baseline, intervals)
    sys.stdout.write(render_verdict(verdict, show_passed=args.show_passed))
    if args.markdown:
        args.markdown.write_text(render_verdict_markdown(verdict), encoding="utf-8")
        wrote(args.markdown)
    if args.junit:
        args.junit.write_text(render_junit(verdict), encoding="utf-8")
        wrote(args.junit)
    return EXIT_OK if verdict.passed else EXIT_GATE


def _sharded(args: argparse.Namespace, needs_errors: bool) -> tuple[dict, dict | None, dict | None]:
    """The documents (and with --significant the intervals) a gate reads, for sets given in shards."""
    from ..analysis.batch import expand_predictions
    from ..analysis.sharded import evaluate_sharded, paired_bootstrap_sharded

    if not (args.gt and args.pred) or args.result:
        raise ConfigError("--sharded gates predictions given in shards: --gt and --pred as globs")
    if needs_errors:
        raise ConfigError("rules on error types need the set in one piece (the decomposition is not sharded)")
    baseline_is_json = args.baseline is not None and args.baseline.suffix.lower() == ".json"
    if args.significant and (args.baseline is None or baseline_is_json):
        raise ConfigError("--significant needs a --baseline given as predictions")
    gts, preds = expand_predictions([args.gt]), expand_predictions([args.pred])
    if args.significant:
        base, now, intervals = paired_bootstrap_sharded(
            gts, expand_predictions([args.baseline]), preds, config(args), resamples=args.bootstrap, seed=args.seed
        )
        return now.to_dict(), base.to_dict(), intervals
    current = evaluate_sharded(gts, preds, config(args)).to_dict()
    if args.baseline is None:
        return current, None, None
    if baseline_is_json:
        return current, read_result_json(args.baseline), None
    return current, evaluate_sharded(gts, expand_predictions([args.baseline]), config(args)).to_dict(), None
