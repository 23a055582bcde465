"""The detection curves the product ships (`cloudtrack/data/detection_curve.json`, made by
`cloudtrack-backend pod-curve` on the dev sequences with the back-end's default configuration), or a curve
file of the operator's own (`[search] curve_file`, for another detector, tiling or keyframe width).

A curve file is read once, bounded in size before it is parsed, and refused with one line naming what is
wrong (`behaviors.detection_curve.CurveError`).
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from behaviors.detection_curve import CurveError, DetectionCurve, curves_from_document

SHIPPED = Path(__file__).with_name("data") / "detection_curve.json"
MAX_FILE_BYTES = 2_000_000


@lru_cache(maxsize=8)
def load_curves(path: Path = SHIPPED) -> dict[str, DetectionCurve]:
    """Every class's curve in a curve file (default: the shipped one)."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise CurveError(f"{path}: {exc.strerror or exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise CurveError(f"{path}: larger than {MAX_FILE_BYTES} bytes, not a curve file")
    try:
        data = json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise CurveError(f"{path}: not JSON ({str(exc)[:80]})") from None
    try:
        return curves_from_document(data)
    except CurveError as exc:
        raise CurveError(f"{path}: {exc}") from None


def curve_for(target_class: str = "person", path: Path | None = None) -> DetectionCurve:
    """The curve of one class; CurveError naming the classes the file has when it lacks this one."""
    curves = load_curves(path or SHIPPED)
    if target_class not in curves:
        raise CurveError(
            f"no detection curve for {target_class!r} in {path or SHIPPED} (it has: {', '.join(sorted(curves))})"
        )
    return curves[target_class]
