"""`cloudtrack-backend eval`: per-task AP of detector + verifier(s) on a COCO or SARD-style VOC set."""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from backend.detectors.factory import build_detector
from backend.pipeline import Pipeline
from backend.verifiers.factory import build_verifier
from backend_tools.evaluation import (
    DatasetError,
    EvalSet,
    evaluate,
    load_coco,
    load_sard_voc,
    load_sequences,
    markdown_table,
)
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from backend.cli import add_config_flags

    parser = subparsers.add_parser(
        "eval",
        help="per-task AP (11-point VOC, IoU > 0.5) + AP50 (faster-coco-eval), t_f and t_obj",
        description="Evaluate detector + verifier on a COCO set whose annotations carry 'referring' or "
        "'attributes' texts (one task per text), or on a SARD-style VOC folder with an attribute CSV. "
        "Prints a markdown table in the paper's layout.",
        epilog="examples:\n"
        "  cloudtrack-backend eval --coco set.json --images frames/ --verifier local --verifier none\n"
        "  cloudtrack-backend eval --sequences ../shared/data/sequences --step 5 --verifier local --verifier none\n"
        "  cloudtrack-backend eval --voc SARD/ --attributes sard_attributes.csv --verifier vlm "
        "--set vlm.model=gpt-4o-mini --markdown out/eval.md\n"
        "  cloudtrack-backend eval --coco set.json --images frames/ --verifier cascade --json out/eval.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--coco", type=Path, metavar="FILE", help="COCO annotations with referring/attributes texts"
    )
    source.add_argument(
        "--voc", type=Path, metavar="DIR", help="SARD-style VOC folder (JPEGImages/, Annotations/)"
    )
    source.add_argument(
        "--sequences",
        type=Path,
        metavar="DIR",
        help="tracking sequences (frames/, groundtruth.txt, referring.txt): one task per sequence",
    )
    parser.add_argument(
        "--step", type=int, default=5, help="with --sequences: every STEP-th frame (default 5)"
    )
    parser.add_argument("--images", type=Path, metavar="DIR", help="image folder for --coco")
    parser.add_argument(
        "--attributes", type=Path, metavar="CSV", help="image,xmin,ymin,xmax,ymax,attribute rows for --voc"
    )
    parser.add_argument(
        "--verifier",
        action="append",
        choices=["none", "local", "local-hsv", "vlm", "cascade"],
        help="verifier(s) to compare, one table row each (default: [verifier] kind)",
    )
    parser.add_argument(
        "--strict", action="store_true", help="count only 'yes' (default: 'uncertain' counts too)"
    )
    parser.add_argument("--model-dir", help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)")
    parser.add_argument("--markdown", type=Path, metavar="OUT", help="also write the table to this file")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the scores as JSON")
    add_config_flags(parser)
    parser.set_defaults(func=_eval)


def _load(args: argparse.Namespace) -> EvalSet:
    if args.sequences:
        if args.step < 1:
            raise DatasetError("--step must be at least 1")
        return load_sequences(args.sequences, args.step)
    if args.coco:
        if not args.images:
            raise DatasetError("--coco needs --images DIR")
        return load_coco(args.coco, args.images)
    if not args.attributes:
        raise DatasetError("--voc needs --attributes CSV")
    return load_sard_voc(args.voc, args.attributes)


def _eval(args: argparse.Namespace) -> int:
    from backend.cli import config_from_args

    extra = [f"detector.model_dir={json.dumps(args.model_dir)}"] if args.model_dir else []
    try:
        config = config_from_args(args, *extra)
        evalset = _load(args)
        detector = build_detector(config.detector)
        kinds = args.verifier or [config.verifier.kind]
        with ThreadPoolExecutor(config.verifier.concurrency) as pool:
            pipelines = {}
            for kind in kinds:
                verifier = build_verifier(config.verifier.model_copy(update={"kind": kind}), config.vlm)
                name = verifier.name if verifier is not None else "none"
                pipelines[name] = Pipeline(
                    detector,
                    verifier,
                    pool,
                    config.crops.margin_px,
                    config.detector.max_candidates,
                    config.verifier.timeout_s,
                    config.verifier.request_deadline_s,
                    config.verifier.uncertain_policy,
                )
            results = evaluate(
                evalset,
                detector,
                pipelines,
                count_uncertain=not args.strict,
                progress=lambda images: tqdm(images, desc="eval", unit="image", file=sys.stderr),
            )
    except (ConfigError, ModelError, DatasetError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = markdown_table(evalset, results, detector.name)
    print(table)
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(table + "\n")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "tasks": [asdict(t) for t in evalset.tasks],
            "images": len(evalset.images),
            "results": [{**asdict(r), "mAP": r.mean_ap, "mAP50_coco": r.mean_ap50} for r in results],
        }
        args.json.write_text(json.dumps(payload, indent=2))
    return 0
