"""The `[camera]` section as a `CameraModel`: OpenCV calibration when there is one, else the HFOV pinhole.

A calibration is the camera matrix and the distortion coefficients `cv2.calibrateCamera` returns, given
inline (`camera_matrix`, `distortion`) or in `calibration_file`: a file `cv2.FileStorage` wrote (YAML,
XML or JSON with `camera_matrix` and `distortion_coefficients`, optionally `image_width`/`image_height`),
or a ROS `camera_calibration` YAML (`camera_matrix.data`, `distortion_coefficients.data`,
`image_width`, `image_height`). A calibration made at another resolution is scaled to `[camera]`
width x height (same aspect ratio required).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from behaviors.camera_model import DISTORTION_LENGTHS, CameraModel
from companion.config import CameraConfig


class CalibrationError(ValueError):
    """A calibration that cannot be used; the message names the file or key and what is wrong."""


@dataclass(frozen=True)
class Calibration:
    camera_matrix: tuple[float, ...]  # 9 values, row-major
    distortion: tuple[float, ...]
    size: tuple[int, int] | None  # (width, height) it was made at; None: the [camera] size


def camera_model(cam: CameraConfig) -> CameraModel:
    """The companion's camera: calibrated when `[camera]` has a calibration, else from `hfov_deg`."""
    calibration = load_calibration(cam)
    if calibration is None:
        return CameraModel.from_hfov(cam.width, cam.height, cam.hfov_deg, cam.mount_pitch_deg, cam.stabilised)
    fx, _, cx, _, fy, cy, *_ = calibration.camera_matrix
    if calibration.size is not None and calibration.size != (cam.width, cam.height):
        cal_w, cal_h = calibration.size
        sx, sy = cam.width / cal_w, cam.height / cal_h
        if not math.isclose(sx, sy, rel_tol=0.01):
            raise CalibrationError(
                f"[camera] calibration was made at {cal_w}x{cal_h}, which does not scale to {cam.width}x{cam.height}"
            )
        # Distortion is in normalised coordinates: it does not change with the resolution.
        fx, cx, fy, cy = fx * sx, (cx + 0.5) * sx - 0.5, fy * sy, (cy + 0.5) * sy - 0.5
    return CameraModel(
        cam.width,
        cam.height,
        fx,
        fy,
        cx,
        cy,
        math.radians(cam.mount_pitch_deg),
        cam.stabilised,
        calibration.distortion,
    )


def load_calibration(cam: CameraConfig) -> Calibration | None:
    if cam.calibration_file:
        return read_calibration_file(Path(cam.calibration_file).expanduser())
    if cam.camera_matrix:
        return _checked(cam.camera_matrix, cam.distortion, None, "[camera] camera_matrix/distortion")
    return None


def read_calibration_file(path: Path) -> Calibration:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise CalibrationError(f"[camera] calibration_file {path}: {exc.strerror or exc}") from None
    if text.lstrip().startswith(("%YAML", "<?xml")) or path.suffix.lower() in (".xml", ".json"):
        return _read_opencv(path)
    return _read_ros(path, text)


def _read_opencv(path: Path) -> Calibration:
    import cv2

    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not storage.isOpened():
        raise CalibrationError(f"[camera] calibration_file {path}: OpenCV cannot read it")
    try:
        matrix, coefficients = (
            storage.getNode("camera_matrix").mat(),
            storage.getNode("distortion_coefficients").mat(),
        )
        if matrix is None:
            raise CalibrationError(f"[camera] calibration_file {path}: no camera_matrix")
        width, height = storage.getNode("image_width"), storage.getNode("image_height")
        size = (int(width.real()), int(height.real())) if not width.isNone() and not height.isNone() else None
        distortion = [] if coefficients is None else coefficients.ravel().tolist()
        return _checked(matrix.ravel().tolist(), distortion, size, str(path))
    finally:
        storage.release()


def _read_ros(path: Path, text: str) -> Calibration:
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"[camera] calibration_file {path}: not YAML: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("camera_matrix"), dict):
        raise CalibrationError(
            f"[camera] calibration_file {path}: no camera_matrix (ROS camera_calibration "
            "YAML or a file cv2.FileStorage wrote)"
        )
    model = data.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CalibrationError(
            f"[camera] calibration_file {path}: distortion_model {model!r} is not supported "
            "(plumb_bob, rational_polynomial)"
        )
    size = (
        (int(data["image_width"]), int(data["image_height"]))
        if "image_width" in data and "image_height" in data
        else None
    )
    distortion = (data.get("distortion_coefficients") or {}).get("data") or []
    return _checked(data["camera_matrix"].get("data") or [], distortion, size, str(path))


def _checked(
    matrix: Sequence[Any], distortion: Sequence[Any], size: tuple[int, int] | None, source: str
) -> Calibration:
    try:
        k = tuple(float(v) for v in matrix)
        d = tuple(float(v) for v in distortion)
    except (TypeError, ValueError):
        raise CalibrationError(f"{source}: camera matrix and distortion must be numbers") from None
    # Trailing zero coefficients change nothing; drop them down to a length OpenCV's model has.
    while len(d) not in DISTORTION_LENGTHS and d and d[-1] == 0.0:
        d = d[:-1]
    if len(k) != 9 or not all(math.isfinite(v) for v in (*k, *d)):
        raise CalibrationError(
            f"{source}: camera matrix must be 9 finite numbers (row-major 3x3), got {len(k)}"
        )
    if k[0] <= 0 or k[4] <= 0 or k[1] != 0 or k[3] != 0 or k[6:] != (0.0, 0.0, 1.0):
        raise CalibrationError(f"{source}: camera matrix must be [fx 0 cx; 0 fy cy; 0 0 1] with fx, fy > 0")
    if len(d) not in DISTORTION_LENGTHS:
        raise CalibrationError(
            f"{source}: distortion takes 4, 5, 8 or 12 coefficients (OpenCV's order), got {len(d)}"
        )
    if size is not None and (size[0] <= 0 or size[1] <= 0):
        raise CalibrationError(f"{source}: image size {size[0]}x{size[1]} is not a size")
    return Calibration(k, d, size)
