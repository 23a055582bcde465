"""A wide, distorted drone lens: OpenCV calibration in [camera], bearings and geolocation through it."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from behaviors.camera_model import CameraModel
from behaviors.control_law import horizontal_angle
from behaviors.geolocation import locate_pixel
from behaviors.geometry import Box
from behaviors.telemetry import Telemetry
from companion.config import CameraConfig
from companion.vision.camera_calibration import CalibrationError, camera_model
from tests.test_geolocation import LAT, LON, project

# A 1280x720 wide drone camera (about 85 degrees across the undistorted centre row, more at the edges)
# with strong barrel distortion, as cv2.calibrateCamera reports such lenses (k1, k2, p1, p2, k3).
K = [700.0, 0.0, 641.3, 0.0, 698.0, 357.8, 0.0, 0.0, 1.0]
DIST = [-0.28, 0.09, 0.0012, -0.0008, -0.012]
WIDE = CameraModel(1280, 720, 700.0, 698.0, 641.3, 357.8, math.radians(-40.0), True, tuple(DIST))


def _cv_pixel(camera: CameraModel, x: float, y: float) -> tuple[float, float]:
    """OpenCV's own projection of a normalised point through the lens (cv2.projectPoints)."""
    k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
    pixels, _ = cv2.projectPoints(
        np.array([[x, y, 1.0]]), np.zeros(3), np.zeros(3), k, np.array(camera.distortion)
    )
    return float(pixels[0, 0, 0]), float(pixels[0, 0, 1])


def test_camera_undistortion_matches_opencv_across_the_image() -> None:
    """Ours against cv2.undistortPoints wherever OpenCV's iteration converges, and against cv2.projectPoints
    (the forward model, always defined) everywhere, corners included."""
    k = np.array(K).reshape(3, 3)
    us, vs = np.meshgrid(np.linspace(0, 1279, 17), np.linspace(0, 719, 11))
    pixels = np.stack([us.ravel(), vs.ravel()], axis=1)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    opencv = cv2.undistortPoints(pixels.reshape(-1, 1, 2), k, np.array(DIST), criteria=criteria).reshape(
        -1, 2
    )
    ours = np.array([WIDE.normalised(float(u), float(v)) for u, v in pixels])
    converged = 0
    for pixel, theirs, mine in zip(pixels, opencv, ours, strict=True):
        assert np.allclose(_cv_pixel(WIDE, *mine), pixel, atol=1e-6), pixel  # ours: back onto the pixel
        if np.allclose(_cv_pixel(WIDE, *theirs), pixel, atol=1e-3):
            converged += 1
            assert np.abs(mine - theirs).max() * WIDE.fx < 1e-4, pixel
    assert converged >= len(pixels) // 2  # OpenCV's fixed-point iteration fails only near the corners
    for x, y in ours[::7]:
        assert np.allclose(WIDE.pixel(x, y), _cv_pixel(WIDE, x, y), atol=1e-6)


def test_camera_distortion_geolocation_near_the_corner_within_one_percent_of_range() -> None:
    """A person near the image corner (where a late turn leaves the target): with the calibration the
    located point is within 1 % of the range; the HFOV pinhole (no distortion) misses by far more."""
    height, yaw = 30.0, 0.4
    telemetry = Telemetry(0.0, LAT, LON, height, yaw=yaw)
    u, v = 1215.0, 668.0  # near the bottom-right corner
    # The truth: OpenCV undistorts the pixel (cv2.undistortPoints), an ideal pinhole casts that ray.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    x, y = cv2.undistortPoints(
        np.array([[[u, v]]]), np.array(K).reshape(3, 3), np.array(DIST), criteria=criteria
    )[0, 0]
    ideal = replace(WIDE, distortion=())
    pu, pv = ideal.cx + ideal.fx * float(x), ideal.cy + ideal.fy * float(y)
    true_point = locate_pixel(ideal, telemetry, pu, pv)
    assert true_point is not None
    north, east, truth = true_point.north_m, true_point.east_m, true_point.ground_range_m
    # And independently: the true ground point projects back onto that ideal pixel.
    back_u, back_v, _ = project(ideal, 0.0, 0.0, yaw, height, north, east)
    assert math.isclose(back_u, pu, abs_tol=1e-6) and math.isclose(back_v, pv, abs_tol=1e-6)

    calibrated = locate_pixel(WIDE, telemetry, u, v)
    assert calibrated is not None
    error = math.hypot(calibrated.north_m - north, calibrated.east_m - east)
    assert error < 0.01 * truth, f"{error:.2f} m off at {truth:.1f} m"

    hfov = CameraModel.from_hfov(1280, 720, math.degrees(2 * math.atan(640 / WIDE.fx)), -40.0)  # the fallback
    uncorrected = locate_pixel(hfov, telemetry, u, v)
    miss = (
        math.inf
        if uncorrected is None
        else math.hypot(uncorrected.north_m - north, uncorrected.east_m - east)
    )
    assert miss > 0.05 * truth, f"without the calibration the error is only {miss:.2f} m"
    # The bearing to the target bends the same way.
    box = Box(u - 20, v - 60, 40, 60)
    true_bearing = math.atan((pu - ideal.cx) / ideal.fx)  # box centre is near the foot: compare loosely
    assert abs(horizontal_angle(WIDE, box) - true_bearing) < abs(horizontal_angle(hfov, box) - true_bearing)


def _ros_yaml(path: Path, width: int, height: int, k: list[float]) -> Path:
    path.write_text(
        f"image_width: {width}\nimage_height: {height}\ncamera_name: front\n"
        f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {k}\n"
        "distortion_model: plumb_bob\n"
        f"distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {DIST}\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
    )
    return path


def test_camera_calibration_inline_ros_and_opencv_files_agree(tmp_path: Path) -> None:
    inline = camera_model(
        CameraConfig(width=1280, height=720, mount_pitch_deg=-40.0, camera_matrix=K, distortion=DIST)
    )
    assert inline == WIDE
    ros = camera_model(
        CameraConfig(
            width=1280,
            height=720,
            mount_pitch_deg=-40.0,
            calibration_file=str(_ros_yaml(tmp_path / "ost.yaml", 1280, 720, K)),
        )
    )
    assert ros == WIDE
    storage = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array(K).reshape(3, 3))
    storage.write("distortion_coefficients", np.array([DIST]))
    storage.write("image_width", 1280)
    storage.write("image_height", 720)
    storage.release()
    opencv = camera_model(
        CameraConfig(
            width=1280, height=720, mount_pitch_deg=-40.0, calibration_file=str(tmp_path / "calib.yaml")
        )
    )
    assert opencv == WIDE
    # Calibrated at 1280x720, flown at 640x360: focal lengths and centre scale, distortion does not.
    half = camera_model(
        CameraConfig(
            width=640, height=360, mount_pitch_deg=-40.0, calibration_file=str(tmp_path / "calib.yaml")
        )
    )
    assert half.fx == pytest.approx(350.0) and half.distortion == WIDE.distortion
    assert half.normalised(600.0, 340.0) == pytest.approx(WIDE.normalised(1200.5, 680.5), abs=1e-9)
    # No calibration: the HFOV pinhole, as before.
    assert camera_model(CameraConfig()) == CameraModel.from_hfov(640, 480, 70.0, -45.0)


def test_camera_calibration_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="no camera_matrix"):
        camera_model(CameraConfig(calibration_file=str(_write(tmp_path / "x.yaml", "foo: 1\n"))))
    with pytest.raises(CalibrationError, match="does not scale"):
        camera_model(
            CameraConfig(
                width=640, height=480, calibration_file=str(_ros_yaml(tmp_path / "o.yaml", 1280, 720, K))
            )
        )
    with pytest.raises(CalibrationError, match="missing.yaml"):
        camera_model(CameraConfig(calibration_file=str(tmp_path / "missing.yaml")))
    with pytest.raises(ValueError, match="camera_matrix takes 9"):
        CameraConfig(camera_matrix=[1.0, 2.0])
    with pytest.raises(ValueError, match="distortion takes"):
        CameraConfig(camera_matrix=K, distortion=[0.1, 0.2, 0.3])


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_camera_calibration_config_check_reads_the_file(tmp_path: Path) -> None:
    from companion.cli import main

    config = tmp_path / "companion.toml"
    config.write_text(f'[camera]\ncalibration_file = "{tmp_path / "nothere.yaml"}"\n')
    assert main(["config", "check", str(config)]) == 2
    _ros_yaml(tmp_path / "nothere.yaml", 640, 480, [350.0, 0.0, 320.0, 0.0, 349.0, 240.0, 0.0, 0.0, 1.0])
    assert main(["config", "check", str(config)]) == 0
