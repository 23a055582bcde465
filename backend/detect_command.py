"""`cloudtrack-backend detect IMAGE --prompt TEXT`: the whole pipeline on one image, without a server."""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2

from backend.detectors.factory import build_detector
from backend.images import ImageError, decode_image
from backend.pipeline import Pipeline, PipelineResult
from backend.supersets import UnknownSupersetError, superset_from_prompt
from backend.verifiers.factory import build_verifier
from behaviors.detection import Verdict
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError

COLOURS = {Verdict.YES: (0, 200, 0), Verdict.NO: (0, 0, 230), Verdict.UNCERTAIN: (0, 200, 230)}


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from backend.cli import add_config_flags

    parser = subparsers.add_parser(
        "detect",
        help="run detection + verification on one image (no server), to try prompts",
        description="Detect the superset in IMAGE, crop each box with the configured margin and verify it "
        "against the prompt. Prints one line per candidate.",
        epilog="examples:\n"
        '  cloudtrack-backend detect ../shared/data/sequences/otb_Crossing/frames/000001.jpg --prompt "a person in dark clothes"\n'
        '  cloudtrack-backend detect frame.jpg --prompt "a red kayak" --superset boat --json out.json --draw out.jpg\n'
        '  OPENAI_API_KEY=... cloudtrack-backend detect frame.jpg --prompt "an injured hiker" --verifier vlm',
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("image", type=Path, help="JPEG or PNG file")
    parser.add_argument("--prompt", required=True, help="the full description of the target")
    parser.add_argument("--superset", help="detector class (default: derived from the prompt)")
    parser.add_argument("--verifier", choices=["none", "local", "local-hsv", "vlm", "cascade"], help="override [verifier] kind")
    parser.add_argument("--model-dir", help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the candidates as JSON")
    parser.add_argument("--draw", type=Path, metavar="OUT.jpg", help="write the image with boxes and verdicts")
    add_config_flags(parser)
    parser.set_defaults(func=_detect)


def _as_json(result: PipelineResult, image_path: Path) -> dict[str, object]:
    return {
        "image": str(image_path),
        "superset": result.superset,
        "models": {"detector": result.detector, "verifier": result.verifier},
        "timings": {"t_detect": result.t_detect, "t_verify": result.t_verify, "t_total": result.t_total},
        "candidates": [
            {
                "box": [round(v, 1) for v in c.detection.box.xyxy()],
                "score": round(c.detection.score, 4),
                "label": c.detection.label,
                "verdict": c.detection.verdict.value,
                "justification": c.detection.justification,
                "t_verify": round(c.t_verify, 4),
            }
            for c in result.candidates
        ],
    }


def _detect(args: argparse.Namespace) -> int:
    from backend.cli import config_from_args

    extra = [f"verifier.kind={json.dumps(args.verifier)}"] if args.verifier else []
    if args.model_dir:
        extra.append(f"detector.model_dir={json.dumps(args.model_dir)}")
    try:
        config = config_from_args(args, *extra)
        image = decode_image(args.image.read_bytes(), config.server.max_image_pixels)
        superset = args.superset or superset_from_prompt(args.prompt)
        if not superset:
            raise ValueError("the prompt names no known class; give --superset (e.g. person)")
        detector = build_detector(config.detector)
        verifier = build_verifier(config.verifier, config.vlm)
        with ThreadPoolExecutor(config.verifier.concurrency) as pool:
            pipeline = Pipeline(detector, verifier, pool, config.crops.margin_px, config.detector.max_candidates,
                                config.verifier.timeout_s, config.verifier.request_deadline_s, config.verifier.uncertain_policy)
            result = pipeline.run(image, args.prompt, superset)
    except (ConfigError, ModelError, ImageError, UnknownSupersetError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.image}: {len(result.candidates)} candidate(s) of {result.superset!r}; detector {result.detector}, "
          f"verifier {result.verifier}; t_detect {result.t_detect * 1000:.1f} ms, t_verify {result.t_verify * 1000:.1f} ms")
    for c in result.candidates:
        x1, y1, x2, y2 = c.detection.box.xyxy()
        print(f"  [{x1:.0f}, {y1:.0f}, {x2:.0f}, {y2:.0f}] score {c.detection.score:.2f} "
              f"{c.detection.verdict.value.upper():9s} {c.detection.justification}")
    if args.json:
        args.json.write_text(json.dumps(_as_json(result, args.image), indent=2))
    if args.draw:
        for c in result.candidates:
            colour = COLOURS[c.detection.verdict]
            x1, y1, x2, y2 = (int(round(v)) for v in c.detection.box.xyxy())
            cv2.rectangle(image, (x1, y1), (x2, y2), colour, 2)
            cv2.putText(image, f"{c.detection.verdict.value} {c.detection.score:.2f}", (x1, max(12, y1 - 4)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
        if not cv2.imwrite(str(args.draw), image):
            print(f"error: cannot write {args.draw}", file=sys.stderr)
            return 2
    return 0
