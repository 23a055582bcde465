"""One tracker interface over the single-object trackers the installed OpenCV provides.

`create_tracker(name, model_dir)` builds nano (NanoTrack v2), vit (VitTrack), dasiamrpn, csrt, kcf, mil,
or goturn where the build still has it (OpenCV 5.0 removed it). Every tracker answers `update(frame)`
with a `TrackerStep`: the box (None when the tracker gave up), a score only when the tracker has a
meaningful one (nano, vit, dasiamrpn; CSRT/KCF/MIL return -1 on OpenCV 5.0 and have no
`getTrackingScore` on 4.x, both mapped to None) and OpenCV's own ok flag.

API differences between OpenCV 4.10 and 5.x are handled by feature detection, never by version strings:
the class may be `cv2.TrackerX` with `.create`, a module-level `cv2.TrackerX_create`, or only
`cv2.legacy.TrackerX_create` (whose `init` returns a bool and takes float boxes); `init` returns None
on 4.x/5.x and a bool on legacy; `TrackerVit_Params.tracking_score_threshold` exists from 4.11 only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from behaviors.geometry import Box
from cloudtrack.model_store import require

# Trackers whose score is meaningful; the others report None.
SCORED_TRACKERS = frozenset({"nano", "vit", "dasiamrpn"})
ALL_TRACKERS = ("nano", "vit", "dasiamrpn", "csrt", "kcf", "mil", "goturn")


class TrackerUnavailableError(Exception):
    """A tracker this OpenCV build does not provide (or an unknown name); the message says which exist."""


@dataclass(frozen=True)
class TrackerStep:
    """One `update()`: box in frame pixels (None when the tracker failed), score or None, OpenCV's ok."""

    box: Box | None
    score: float | None
    ok: bool


class Tracker(Protocol):
    """A single-object tracker. `init` starts on `box` in `frame`; `update` follows it in the next frame."""

    name: str
    has_score: bool

    def init(self, frame: np.ndarray, box: Box) -> None: ...

    def update(self, frame: np.ndarray) -> TrackerStep: ...


def _factory(class_name: str) -> Callable[..., Any] | None:
    """The constructor for an OpenCV tracker class, wherever this build puts it; None when absent."""
    cls = getattr(cv2, class_name, None)
    if cls is not None and hasattr(cls, "create"):
        return cls.create  # type: ignore[no-any-return]
    fn = getattr(cv2, f"{class_name}_create", None)
    if fn is not None:
        return fn  # type: ignore[no-any-return]
    legacy = getattr(cv2, "legacy", None)
    if legacy is not None:
        fn = getattr(legacy, f"{class_name}_create", None)
        if fn is not None:
            return fn  # type: ignore[no-any-return]
    return None


def _params(class_name: str) -> Any:
    """The Params object of a DNN tracker (`cv2.TrackerNano_Params` on every supported version)."""
    cls = getattr(cv2, f"{class_name}_Params", None)
    if cls is None:
        nested = getattr(getattr(cv2, class_name, None), "Params", None)
        cls = nested
    if cls is None:
        raise TrackerUnavailableError(f"this OpenCV build ({cv2.__version__}) has no {class_name}_Params")
    return cls()


def _set_first(params: Any, names: tuple[str, ...], value: Any) -> None:
    """Set the first attribute of `names` that this OpenCV's Params has (names changed across releases)."""
    for name in names:
        if hasattr(params, name):
            setattr(params, name, value)
            return
    raise TrackerUnavailableError(
        f"OpenCV {cv2.__version__}: {type(params).__name__} has none of {', '.join(names)}"
    )


_CLASS_NAMES = {
    "nano": "TrackerNano",
    "vit": "TrackerVit",
    "dasiamrpn": "TrackerDaSiamRPN",
    "csrt": "TrackerCSRT",
    "kcf": "TrackerKCF",
    "mil": "TrackerMIL",
    "goturn": "TrackerGOTURN",
}


def available_trackers() -> list[str]:
    """The tracker names this OpenCV build can construct (weights may still be missing)."""
    return [name for name in ALL_TRACKERS if _factory(_CLASS_NAMES[name]) is not None]


class OpenCVTracker:
    """An OpenCV tracker behind the `Tracker` interface; builds a fresh OpenCV object on every `init`."""

    def __init__(self, name: str, make: Callable[[], Any]) -> None:
        self.name = name
        self.has_score = name in SCORED_TRACKERS
        self._make = make
        self._cv: Any = None

    def init(self, frame: np.ndarray, box: Box) -> None:
        if not box.is_valid():
            raise ValueError(f"{self.name}: cannot initialise on an invalid box {box}")
        # OpenCV keeps internal state across init calls on some trackers: a new object is the safe restart.
        self._cv = self._make()
        clamped = box.clamped(frame.shape[1], frame.shape[0])
        if not clamped.is_valid():
            raise ValueError(
                f"{self.name}: box {box} lies outside the {frame.shape[1]}x{frame.shape[0]} frame"
            )
        rect = tuple(int(round(v)) for v in clamped.xywh())
        try:
            result = self._cv.init(frame, rect)
        except cv2.error:
            # cv2.legacy trackers take a float Rect2d.
            result = self._cv.init(frame, tuple(float(v) for v in clamped.xywh()))
        if result is False:
            raise RuntimeError(f"{self.name}: OpenCV refused to initialise on {box}")

    def update(self, frame: np.ndarray) -> TrackerStep:
        if self._cv is None:
            raise RuntimeError(f"{self.name}: update() before init()")
        ok, rect = self._cv.update(frame)
        box = Box(*(float(v) for v in rect)) if ok else None
        if box is not None and not box.is_valid():
            box, ok = None, False
        return TrackerStep(box, self._score(), bool(ok))

    def _score(self) -> float | None:
        if not self.has_score:
            return None
        get = getattr(self._cv, "getTrackingScore", None)
        if get is None:
            return None
        score = float(get())
        # -1 is OpenCV's "this tracker has no score"; anything not finite is no score either.
        return score if math.isfinite(score) and score >= 0 else None


def _quietly(make: Callable[..., Any], params: Any) -> Callable[[], Any]:
    """Build a DNN tracker with OpenCV's log muted to errors: OpenCV 5's new DNN engine warns on every net
    it loads that preferable targets are unsupported, which is not actionable and floods the journal."""

    def build() -> Any:
        opencv_log = getattr(getattr(cv2, "utils", None), "logging", None)
        if opencv_log is None:
            return make(params)
        previous = opencv_log.getLogLevel()
        opencv_log.setLogLevel(opencv_log.LOG_LEVEL_ERROR)
        try:
            return make(params)
        finally:
            opencv_log.setLogLevel(previous)

    return build


def _builder(name: str, model_dir: Path) -> Callable[[], Any]:
    class_name = _CLASS_NAMES[name]
    make = _factory(class_name)
    if make is None:
        raise TrackerUnavailableError(
            f"tracker {name!r} ({class_name}) is not provided by this OpenCV build ({cv2.__version__}); "
            f"available here: {', '.join(available_trackers())}"
        )
    if name == "nano":
        files = require("nano", model_dir)
        params = _params(class_name)
        _set_first(params, ("backbone",), str(files["nanotrack_backbone_sim.onnx"]))
        _set_first(params, ("neckhead", "neck_head"), str(files["nanotrack_head_sim.onnx"]))
        return _quietly(make, params)
    if name == "vit":
        files = require("vit", model_dir)
        params = _params(class_name)
        _set_first(params, ("net", "model"), str(files["object_tracking_vittrack_2023sep.onnx"]))
        if hasattr(params, "tracking_score_threshold"):
            # 4.11+ makes update() fail below this score; our loss detection owns that decision on
            # every version, so keep OpenCV from second-guessing it.
            params.tracking_score_threshold = 0.0
        return _quietly(make, params)
    if name == "dasiamrpn":
        files = require("dasiamrpn", model_dir)
        params = _params(class_name)
        _set_first(params, ("model",), str(files["dasiamrpn_model.onnx"]))
        _set_first(params, ("kernel_cls1",), str(files["dasiamrpn_kernel_cls1.onnx"]))
        _set_first(params, ("kernel_r1",), str(files["dasiamrpn_kernel_r1.onnx"]))
        return _quietly(make, params)
    if name == "goturn":
        files = require("goturn", model_dir)
        params = _params(class_name)
        _set_first(params, ("modelTxt",), str(files["goturn.prototxt"]))
        _set_first(params, ("modelBin",), str(files["goturn.caffemodel"]))
        return _quietly(make, params)
    return make


def create_tracker(name: str, model_dir: Path) -> Tracker:
    """A ready-to-init tracker; ModelError (naming the file and the fix) when weights are missing,
    TrackerUnavailableError when this OpenCV build lacks it or the name is unknown."""
    if name not in _CLASS_NAMES:
        raise TrackerUnavailableError(f"unknown tracker {name!r}; known: {', '.join(ALL_TRACKERS)}")
    make = _builder(name, Path(model_dir))
    tracker = OpenCVTracker(name, make)
    # Build once now so a broken weight file fails here, not mid-flight.
    make()
    return tracker
