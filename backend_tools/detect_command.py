"""`cloudtrack-backend detect IMAGE --prompt TEXT`: the whole pipeline on one image, without a server."""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from backend.detectors.factory import build_detector
from backend.images import ImageError, decode_image
from backend.pipeline import Pipeline, PipelineResult
from backend.supersets import UnknownSupersetError, superset_from_prompt
from backend.verifiers.factory import build_verifier
from behaviors.detection import Verdict
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import MODEL_DIR_HELP, ModelError

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
    parser.add_argument(
        "--verifier",
        choices=["none", "local", "local-hsv", "vlm", "cascade"],
        help="override [verifier] kind",
    )
    parser.add_argument("--model-dir", metavar="DIR", help=MODEL_DIR_HELP)
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the candidates as JSON")
    parser.add_argument(
        "--draw", type=Path, metavar="OUT.jpg", help="write the image with boxes and verdicts"
    )
    add_config_flags(parser)
    parser.set_defaults(func=_detect)


Rect = tuple[int, int, int, int]  # x1, y1, x2, y2 in pixels, exclusive ends


def draw_candidates(
    image: np.ndarray, items: list[tuple[tuple[float, float, float, float], str, tuple[int, int, int]]]
) -> list[Rect]:
    """Draw each (box xyxy, label, BGR colour) on image; returns where the labels went.

    Text and lines scale with the image (about 2.5 % of its shorter side: 18 px on 1280x720), each label
    sits on a filled box of its colour with dark or light text, whichever reads better, and a label never
    covers another: it goes above its box, else below, else inside, else is moved down past the others.
    """
    height, width = image.shape[:2]
    scale = max(0.4, min(width, height) / 900.0)
    thickness = max(1, round(scale * 2))
    line = max(2, round(min(width, height) / 300.0))
    pad = max(2, round(4 * scale))
    placed: list[Rect] = []
    for box, _, colour in items:
        x1, y1, x2, y2 = (int(round(v)) for v in box)
        cv2.rectangle(image, (x1, y1), (x2, y2), colour, line)
    for box, text, colour in items:
        x1, y1, x2, y2 = (int(round(v)) for v in box)
        (tw, th), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
        lw, lh = tw + 2 * pad, th + baseline + 2 * pad
        left = min(max(0, x1), max(0, width - lw))
        tops = [y1 - lh, y2, y1]  # above the box, below it, inside its top
        rect = next(
            (
                r
                for top in tops
                if 0 <= top <= height - lh and not _overlaps(r := (left, top, left + lw, top + lh), placed)
            ),
            None,
        )
        if rect is None:  # slide down past the labels in the way (wrapping to the top once), bounded
            start = top = min(max(0, y1 - lh), max(0, height - lh))
            for _ in range(2 * len(placed) + 2):
                blockers = [p for p in placed if _overlaps((left, top, left + lw, top + lh), [p])]
                if not blockers:
                    rect = (left, top, left + lw, top + lh)
                    break
                top = max(b[3] for b in blockers)
                if top + lh > height:
                    top = 0
            if rect is None:  # more labels than fit: overlap rather than lose one
                rect = (left, start, left + lw, start + lh)
        placed.append(rect)
        cv2.rectangle(image, rect[:2], (rect[2] - 1, rect[3] - 1), colour, cv2.FILLED)
        ink = (
            (0, 0, 0) if 0.114 * colour[0] + 0.587 * colour[1] + 0.299 * colour[2] > 110 else (255, 255, 255)
        )
        cv2.putText(
            image,
            text,
            (rect[0] + pad, rect[3] - pad - baseline),
            cv2.FONT_HERSHEY_SIMPLEX,
            scale,
            ink,
            thickness,
            cv2.LINE_AA,
        )
    return placed


def _overlaps(rect: Rect, others: list[Rect]) -> bool:
    return any(rect[0] < o[2] and o[0] < rect[2] and rect[1] < o[3] and o[1] < rect[3] for o in others)


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
            pipeline = Pipeline(
                detector,
                verifier,
                pool,
                config.crops.margin_px,
                config.detector.max_candidates,
                config.verifier.timeout_s,
                config.verifier.request_deadline_s,
                config.verifier.uncertain_policy,
            )
            result = pipeline.run(image, args.prompt, superset)
    except (ConfigError, ModelError, ImageError, UnknownSupersetError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(
        f"{args.image}: {len(result.candidates)} candidate(s) of {result.superset!r}; detector {result.detector}, "
        f"verifier {result.verifier}; t_detect {result.t_detect * 1000:.1f} ms, t_verify {result.t_verify * 1000:.1f} ms"
    )
    for c in result.candidates:
        x1, y1, x2, y2 = c.detection.box.xyxy()
        print(
            f"  [{x1:.0f}, {y1:.0f}, {x2:.0f}, {y2:.0f}] score {c.detection.score:.2f} "
            f"{c.detection.verdict.value.upper():9s} {c.detection.justification}"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_as_json(result, args.image), indent=2))
    if args.draw:
        draw_candidates(image, [
            (c.detection.box.xyxy(), f"{c.detection.verdict.value} {c.detection.score:.2f}", COLOURS[c.detection.verdict])
            for c in result.candidates
        ])  # fmt: skip
        args.draw.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(args.draw), image):
            print(f"error: cannot write {args.draw}", file=sys.stderr)
            return 2
    return 0
