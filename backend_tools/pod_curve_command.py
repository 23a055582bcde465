"""`cloudtrack-backend pod-curve`: the detection curve measured on sequences with ground truth
(`backend_tools.pod_curve`), written as a curve file, or a curve file checked against them."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from backend.images import ImageError
from backend.supersets import UnknownSupersetError
from backend_tools.pod_curve import (
    SequenceLooks,
    build_pipeline,
    check,
    configuration,
    fit_curves,
    look_dependence,
    measure,
    read_sequence,
    worst_error,
)
from behaviors.detection_curve import CurveError, DetectionCurve, curves_document, wilson_interval
from behaviors.scene_light import MIN_MEAN_LUMA
from cloudtrack.config_files import ConfigError
from cloudtrack.detection_curves import load_curves
from cloudtrack.model_store import MODEL_DIR_HELP, ModelError

CHECK_FORMAT = "cloudtrack-detection-curve-check/1"
# Sequences a class needs for a curve: one sequence is one target's curve and predicts no other, and the
# leave-one-sequence-out check must still predict each sequence from two.
MIN_SEQUENCES = 3


def _bin_label(lo: float, hi: float | None) -> str:
    return f"{lo:.0f}+" if hi is None or math.isinf(hi) else f"{lo:.0f}-{hi:.0f}"


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def print_curve(curve: DetectionCurve) -> None:
    sequences = len(curve.sequences)
    print(
        f"\n{curve.target_class}: {curve.samples} frames from {sequences} sequence(s). Frames of one sequence "
        "are one target under one description, not independent samples: the 95 % intervals (Wilson) treat "
        "them as independent and are too narrow."
    )
    print("| size px | frames | proposed | POD (yes) | 95 % interval | the curve | POD (yes or uncertain) |")
    print("|---|---|---|---|---|---|---|")
    fitted = curve.table()
    for b, at in zip(curve.bins, fitted, strict=True):
        n = b.samples
        ci = wilson_interval(b.yes, n)
        print(
            f"| {_bin_label(b.lo_px, b.hi_px)} | {n} | {_f(b.proposed / n if n else None)} | "
            f"{_f(b.probability())} | {f'{ci[0]:.2f}-{ci[1]:.2f}' if ci else '-'} | {_f(at)} | "
            f"{_f(b.probability(True))} |"
        )
    fit = curve.fit()
    if fit is not None:
        half = (
            f"found half the time at {fit.size50_px:.1f} px, slope {fit.slope:.2f}"
            if fit.size50_px
            else "flat"
        )
        print(f"the curve (what the map uses: the fit through every bin, at each bin's centre): {half}; "
              f"nothing claimed below {fit.min_size_px:.1f} px")  # fmt: skip


def print_low_light(measured: Sequence[SequenceLooks]) -> None:
    """The frames too dark for the curve, apart: in no bin, no fit, no check (behaviors/scene_light.py)."""
    dark = [(seq, seq.summary()["low_light"]) for seq in measured if seq.dark]
    if not dark:
        return
    print(f"\nLow light (keyframe mean luma < {MIN_MEAN_LUMA:g}, two stops under mid-grey): not fitted, not "
          "checked; the map claims nothing for such keyframes")  # fmt: skip
    print("| sequence | class | frames | mean luma | proposed | found |")
    print("|---|---|---|---|---|---|")
    for seq, d in dark:
        print(
            f"| {seq.name} | {seq.superset} | {d['frames']} | {d['mean_luma']:g} | {d['proposed']} | {d['found']} |"
        )


def print_looks(looks: Mapping[str, Any]) -> None:
    reading = "yes or uncertain" if looks["accept_uncertain"] else "yes"
    gaps = sorted(looks["gap_s_by_sequence"].values())
    apart = f"{gaps[0]:g}" if gaps[0] == gaps[-1] else f"{gaps[0]:g}-{gaps[-1]:g}"
    print(f"\nLooks {apart} s apart at the same target (found: {reading}):")
    print(
        "| class | pairs | P(found) | P(found, missed before) | size alone predicts | P(found, found before) |"
    )
    print("|---|---|---|---|---|---|")
    for name, g in looks["classes"].items():
        print(
            f"| {name} | {g['pairs']} | {_f(g['p_found'])} | {_f(g['p_found_after_miss'])} "
            f"({g['missed_before']}) | {_f(g['p_found_after_miss_by_size'])} | {_f(g['p_found_after_found'])} |"
        )


def print_check(classes: Mapping[str, Any], min_samples: int) -> None:
    for name, c in classes.items():
        print(f"\n{name}: predicted (the curve at each frame's size) minus observed, per bin")
        print("| size px | frames | predicted | observed | predicted - observed | size-blind - observed |")
        print("|---|---|---|---|---|---|")
        for r in c["bins"]:
            if r["samples"]:
                print(
                    f"| {_bin_label(r['lo_px'], r['hi_px'])} | {r['samples']} | {_f(r['predicted'])} | "
                    f"{_f(r['observed'])} | {r['error']:+.2f} | {r['baseline_error']:+.2f} |"
                )
        print(
            f"max |predicted - observed| in bins of >= {min_samples} frames: curve "
            f"{_f(c['max_abs_error'])}, size-blind {_f(c['baseline_max_abs_error'])}"
        )
        print("| sequence | frames | predicted | observed | fitted without it |")
        print("|---|---|---|---|---|")
        for seq, s in c["sequences"].items():
            held = "yes" if s["held_out"] else "no (not in the curve)"
            print(f"| {seq} | {s['samples']} | {_f(s['predicted'])} | {_f(s['observed'])} | {held} |")


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from backend.cli import add_config_flags

    parser = subparsers.add_parser(
        "pod-curve",
        help="measure the detection curve (POD by target size) on sequences with ground truth, or check one",
        description="For every frame where groundtruth.txt shows the target: the frame as a keyframe "
        "(downscaled to --keyframe-width, JPEG) through the back-end's own detection and verification with "
        "referring.txt as the prompt; counted by the target's size (sqrt(w*h) in keyframe pixels, the bins "
        "of behaviors/detection_curve.py): frames, proposed (a candidate with IoU >= 0.5), judged yes, "
        "judged uncertain. Writes one curve per class (--json), or with --check compares a curve's "
        "prediction to what these sequences show (leave-one-sequence-out for the sequences it was fitted on).",
        epilog="examples:\n"
        "  cloudtrack-backend pod-curve ../shared/data/sequences/* --model-dir ../shared/models --json curve.json\n"
        "  cloudtrack-backend pod-curve ../shared/data/sequences/* --model-dir ../shared/models "
        "--check curve.json --json check.json --max-error 0.10\n"
        "  cloudtrack-backend pod-curve new/seq1 new/seq2 --check cloudtrack/data/detection_curve.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sequences", nargs="+", type=Path, help="folders with frames/, groundtruth.txt, referring.txt"
    )
    parser.add_argument(
        "--json", type=Path, metavar="OUT", help="write the curve file (with --check: the check) as JSON"
    )
    parser.add_argument(
        "--check", type=Path, metavar="CURVE", help="compare this curve file's prediction to the sequences"
    )
    parser.add_argument(
        "--self-check",
        type=Path,
        metavar="OUT",
        help="with --json: also check the curves just fitted, leave-one-sequence-out on the same frames, and "
        "write it as --check --json would (one measurement for both)",
    )
    parser.add_argument(
        "--keyframe-width",
        type=int,
        default=640,
        help="downscale frames to this width as the companion does ([backend] max_keyframe_width, default 640)",
    )
    parser.add_argument(
        "--jpeg-quality",
        type=int,
        default=80,
        help="keyframe JPEG quality ([backend] jpeg_quality, default 80)",
    )
    parser.add_argument("--step", type=int, default=1, help="every STEP-th frame (default 1)")
    parser.add_argument(
        "--min-sequences",
        type=int,
        default=MIN_SEQUENCES,
        help=f"a class gets a curve from this many sequences on (default {MIN_SEQUENCES}: one sequence is one "
        "target's curve, so a curve is shipped only where leaving any one sequence out still leaves two to "
        "predict it by)",
    )
    parser.add_argument(
        "--accept-uncertain",
        action="store_true",
        help="count 'uncertain' as found (default: a miss, as the companion does not put uncertain "
        "candidates to the supervisor by default)",
    )
    parser.add_argument(
        "--max-error",
        type=float,
        metavar="E",
        help="with --check: exit 1 when a bin of --min-samples frames is off by more than E (default: no gate)",
    )
    parser.add_argument(
        "--min-samples", type=int, default=30, help="with --check: bins this large count (default 30)"
    )
    parser.add_argument("--model-dir", metavar="DIR", help=MODEL_DIR_HELP)
    add_config_flags(parser)
    parser.set_defaults(func=_pod_curve)


def _pod_curve(args: argparse.Namespace) -> int:
    from backend.cli import config_from_args

    extra = [f"detector.model_dir={json.dumps(args.model_dir)}"] if args.model_dir else []
    if not 64 <= args.keyframe_width <= 4096 or not 10 <= args.jpeg_quality <= 100 or args.step < 1:
        print("error: --keyframe-width 64-4096, --jpeg-quality 10-100, --step >= 1", file=sys.stderr)
        return 2
    try:
        curves_in = load_curves(args.check) if args.check else None
        config = config_from_args(args, *extra)
        sources = [read_sequence(p) for p in args.sequences]
        measured_for = configuration(config, args.keyframe_width, args.jpeg_quality)
        measured = []
        with ThreadPoolExecutor(config.verifier.concurrency) as pool:
            pipeline = build_pipeline(config, pool)
            for source in sources:
                start = time.perf_counter()
                seq = measure(
                    source, pipeline, args.keyframe_width, args.jpeg_quality,
                    config.server.max_image_pixels, args.step,
                )  # fmt: skip
                measured.append(seq)
                print(
                    f"{seq.name} ({seq.superset}, {seq.fps:g} fps): {len(seq.looks)} frames in "
                    f"{time.perf_counter() - start:.0f} s",
                    file=sys.stderr,
                )
    except (
        CurveError,
        ConfigError,
        ModelError,
        ImageError,
        UnknownSupersetError,
        ValueError,
        OSError,
    ) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    failed = sum(look.verifier_failed for seq in measured for look in seq.looks)
    if failed:
        print(f"warning: {failed} verdict(s) came from a verifier timeout or failure", file=sys.stderr)
    reading = (
        "'uncertain' counts as found"
        if args.accept_uncertain
        else "'uncertain' is a miss (the mission's default)"
    )
    print_low_light(measured)
    if curves_in is not None:
        return _report_check(args, curves_in, measured, measured_for, reading, failed, args.check, args.json)
    curves, left_out = fit_curves(measured, measured_for, args.min_sequences)
    for curve in curves.values():
        print_curve(curve)
    for name, why in left_out.items():
        print(f"\n{name}: no curve ({why})")
    looks = look_dependence(measured, curves, args.accept_uncertain)
    print_looks(looks)
    if args.json:
        document = curves_document(
            curves,
            measured={
                "sequences": {s.name: s.summary() for s in measured},
                "step": args.step,
                "verifier_failures": failed,
                "no_curve": left_out,
            },
            looks=looks,
        )
        if not _write(args.json, document):
            return 2
    if args.self_check and args.json:
        print("\nThe curves just fitted, each sequence predicted by the curve fitted without it:")
        return _report_check(
            args, curves, measured, measured_for, reading, failed, args.json, args.self_check
        )
    return 0


def _report_check(
    args: argparse.Namespace,
    curves: Mapping[str, DetectionCurve],
    measured: Sequence[SequenceLooks],
    measured_for: Mapping[str, str],
    reading: str,
    failed: int,
    curve_file: Path,
    out: Path | None,
) -> int:
    for curve in curves.values():
        differ = sorted(k for k, v in curve.configuration if measured_for.get(k, v) != v)
        if differ:
            print(
                f"warning: the {curve.target_class} curve was measured with other {', '.join(differ)} than this run",
                file=sys.stderr,
            )
    classes, skipped = check(measured, curves, args.accept_uncertain)
    if not classes:
        print(f"error: {curve_file} has no curve for any of these sequences' classes", file=sys.stderr)
        return 2
    for c in classes.values():
        c["max_abs_error"] = worst_error(c["bins"], "error", args.min_samples)
        c["baseline_max_abs_error"] = worst_error(c["bins"], "baseline_error", args.min_samples)
    print(f"reading: {reading}")
    print_check(classes, args.min_samples)
    for line in skipped:
        print(f"not checked: {line}")
    looks = look_dependence(measured, curves, args.accept_uncertain)
    print_looks(looks)
    off = [
        f"{name} {_bin_label(r['lo_px'], r['hi_px'])} px ({r['error']:+.2f})"
        for name, c in classes.items()
        for r in c["bins"]
        if args.max_error is not None
        and r["samples"] >= args.min_samples
        and abs(r["error"]) > args.max_error
    ]
    if out and not _write(
        out,
        {
            "format": CHECK_FORMAT,
            "curve_file": str(curve_file),
            "accept_uncertain": args.accept_uncertain,
            "min_samples": args.min_samples,
            "max_error": args.max_error,
            "verifier_failures": failed,
            "classes": classes,
            "not_checked": skipped,
            "looks": looks,
            "low_light": {seq.name: seq.summary()["low_light"] for seq in measured if seq.dark},
        },
    ):
        return 2
    if off:
        print(f"off by more than {args.max_error}: {'; '.join(off)}", file=sys.stderr)
        return 1
    return 0


def _write(path: Path, document: Mapping[str, Any]) -> bool:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(document, indent=1) + "\n")
    except OSError as exc:
        print(f"error: {path}: {exc.strerror or exc}", file=sys.stderr)
        return False
    return True
