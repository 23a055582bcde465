"""The camera on the vehicle: intrinsics, lens distortion and how it is mounted."""

from __future__ import annotations

import math
from dataclasses import dataclass

# Newton steps of the inverse distortion; it stops once the point reproduces the pixel to within
# _UNDISTORT_TOLERANCE (normalised units: about 1e-9 px).
_UNDISTORT_ITERATIONS = 30
_UNDISTORT_TOLERANCE = 1e-12
# OpenCV's coefficient counts: (k1, k2, p1, p2), + k3, + (k4, k5, k6) rational, + (s1..s4) thin prism.
DISTORTION_LENGTHS = (0, 4, 5, 8, 12)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics in pixels, OpenCV's lens distortion and the mount's pitch (radians, negative looks down).

    Image axes: u to the right, v down. The camera looks along the body's forward axis, pitched by
    `mount_pitch`; with `stabilised` the gimbal holds that pitch against the vehicle's own pitch/roll.
    `distortion` holds OpenCV's coefficients (as `cv2.calibrateCamera` returns them); empty is an ideal
    pinhole, e.g. one derived from the horizontal field of view (`from_hfov`).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    mount_pitch: float = math.radians(-45.0)
    stabilised: bool = True
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if len(self.distortion) not in DISTORTION_LENGTHS:
            raise ValueError(
                f"distortion takes {', '.join(map(str, DISTORTION_LENGTHS[1:]))} coefficients, "
                f"got {len(self.distortion)}"
            )

    @classmethod
    def from_hfov(
        cls, width: int, height: int, hfov_deg: float, mount_pitch_deg: float = -45.0, stabilised: bool = True
    ) -> CameraModel:
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0, math.radians(mount_pitch_deg), stabilised)

    def normalised(self, u: float, v: float) -> tuple[float, float]:
        """Pixel (u, v) as undistorted normalised coordinates (x right, y down): its ray is (1, x, y) in the
        camera's forward-right-down axes.

        Inverts OpenCV's distortion model (what `cv2.undistortPoints` computes, here in the stdlib so the
        behaviours and their replay stay pure) by Newton's method on `pixel`, to about 1e-9 px. OpenCV's
        fixed-point iteration with its default few steps leaves errors of up to 1.6 px near the corners
        of a strongly distorted wide lens (tests/test_camera_calibration.py), exactly where a target is
        when the drone turns late.
        """
        x0 = (u - self.cx) / self.fx
        y0 = (v - self.cy) / self.fy
        if not self.distortion:
            return x0, y0
        x, y = x0, y0
        for _ in range(_UNDISTORT_ITERATIONS):
            ex, ey = self._distorted(x, y)
            rx, ry = ex - x0, ey - y0
            if abs(rx) + abs(ry) < _UNDISTORT_TOLERANCE:
                break
            # Jacobian of the lens map by central differences (cheap: a handful of multiplications).
            h = 1e-7
            ax, ay = self._distorted(x + h, y)
            bx, by = self._distorted(x - h, y)
            cx_, cy_ = self._distorted(x, y + h)
            dx_, dy_ = self._distorted(x, y - h)
            j11, j21 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
            j12, j22 = (cx_ - dx_) / (2 * h), (cy_ - dy_) / (2 * h)
            det = j11 * j22 - j12 * j21
            if not math.isfinite(det) or abs(det) < 1e-12:  # the model folds over here: no unique ray
                break
            step_x, step_y = (j22 * rx - j12 * ry) / det, (j11 * ry - j21 * rx) / det
            # Halve a step that would not reduce the residual (keeps Newton inside the model's range).
            for _ in range(30):
                nx, ny = x - step_x, y - step_y
                fx_, fy_ = self._distorted(nx, ny)
                if abs(fx_ - x0) + abs(fy_ - y0) < abs(rx) + abs(ry):
                    break
                step_x, step_y = step_x / 2, step_y / 2
            x, y = nx, ny
        return x, y

    def _distorted(self, x: float, y: float) -> tuple[float, float]:
        """OpenCV's lens model: undistorted normalised coordinates to distorted normalised coordinates."""
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (
            *self.distortion,
            *(0.0,) * (12 - len(self.distortion)),
        )
        r2 = x * x + y * y
        radial = (1 + ((k3 * r2 + k2) * r2 + k1) * r2) / (1 + ((k6 * r2 + k5) * r2 + k4) * r2)
        return (
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2,
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2,
        )

    def pixel(self, x: float, y: float) -> tuple[float, float]:
        """Undistorted normalised coordinates back to a pixel, through the lens (as `cv2.projectPoints`)."""
        if self.distortion:
            x, y = self._distorted(x, y)
        return self.cx + self.fx * x, self.cy + self.fy * y
