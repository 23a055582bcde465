"""Rendering the world through the vehicle's pinhole camera with OpenCV, with ground-truth boxes.

The ground is one perspective warp of the world texture (a plane-to-image homography); people, vehicles
and occluders are projected polygons painted far to near. Ground truth comes from the same projection:
each person's box is the hull of their projected parts, and the visible fraction is counted on an id
mask painted in the same order, so a person under a roof reads as occluded.

Every frame carries its frame id in a timecode strip (a row of black/white cells along the bottom edge),
the way a test-pattern generator stamps video: the simulated detector reads it back from the keyframe
the back-end receives, whatever the companion did to the frame on the way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from behaviors.camera_model import CameraModel
from behaviors.geometry import Box
from sitl.world import Person, World, ground_texture

SKY_BGR = (215, 190, 160)
SKIN_BGR = (120, 160, 210)
HAIR_BGR = (30, 40, 60)
TIMECODE_BITS = 24
TIMECODE_CELL = 8  # pixels per bit
TIMECODE_ROWS = 6


@dataclass(frozen=True)
class VehiclePose:
    """Where the camera's vehicle is: local NED position (metres) and attitude (radians)."""

    north: float
    east: float
    down: float
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0


@dataclass(frozen=True)
class TruthBox:
    """One person as the camera sees them: box in pixels, visible fraction, and the world position."""

    person_id: str
    box: Box
    visible: float
    north: float
    east: float
    shirt: str


THUMB_SCALE = 0.5  # ground-truth thumbnails: half size, gray, enough to place a crop within the frame


@dataclass(frozen=True)
class FrameTruth:
    """What one frame showed, without its full pixels: kept for hundreds of frames per camera."""

    frame_id: int
    time_s: float
    truth: tuple[TruthBox, ...]
    pose: VehiclePose
    size: tuple[int, int]  # (width, height) of the rendered frame
    thumbnail: np.ndarray  # gray, THUMB_SCALE of the frame


@dataclass(frozen=True)
class RenderedFrame:
    frame_id: int
    time_s: float
    image: np.ndarray
    truth: tuple[TruthBox, ...]
    pose: VehiclePose

    def record(self) -> FrameTruth:
        h, w = self.image.shape[:2]
        gray = cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)
        thumb = cv2.resize(gray, (int(w * THUMB_SCALE), int(h * THUMB_SCALE)), interpolation=cv2.INTER_AREA)
        return FrameTruth(self.frame_id, self.time_s, self.truth, self.pose, (w, h), thumb)


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def camera_rotation(camera: CameraModel, pose: VehiclePose) -> np.ndarray:
    """Camera axes (forward, right, down) as columns in NED. A stabilised mount keeps only the yaw."""
    if camera.stabilised:
        body = _rot_z(pose.yaw)
    else:
        body = _rot_z(pose.yaw) @ _rot_y(pose.pitch) @ _rot_x(pose.roll)
    return np.asarray(body @ _rot_y(camera.mount_pitch))


class Projector:
    """World NED points to pixels for one camera pose."""

    def __init__(self, camera: CameraModel, pose: VehiclePose) -> None:
        self.camera = camera
        self.rotation = camera_rotation(camera, pose)
        self.centre = np.array([pose.north, pose.east, pose.down])
        self.k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) NED points to camera coordinates as (right, down, forward)."""
        frd = (points - self.centre) @ self.rotation
        return np.asarray(frd[:, [1, 2, 0]])

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and depth (N,) along the optical axis; pixels are meaningless where depth <= 0."""
        cam = self.to_camera(points)
        depth = cam[:, 2]
        safe = np.where(depth > 1e-3, depth, 1e-3)
        u = self.camera.fx * cam[:, 0] / safe + self.camera.cx
        v = self.camera.fy * cam[:, 1] / safe + self.camera.cy
        return np.stack([u, v], axis=1), depth

    def ground_homography(self) -> np.ndarray:
        """3x3 map from ground (north, east, 1) to image pixels."""
        r_t = self.rotation.T
        m = np.column_stack([r_t[:, 0], r_t[:, 1], -r_t @ self.centre])  # (fwd, right, down) rows
        return np.asarray(self.k @ m[[1, 2, 0], :])

    def horizon_coefficients(self) -> tuple[float, float, float]:
        """(a, b, c) with a*u + b*v + c > 0 where a pixel's ray points below the horizon."""
        r = self.rotation
        cam = self.camera
        # NED down component of the ray (1, (u-cx)/fx, (v-cy)/fy) in (fwd, right, down)
        a = r[2, 1] / cam.fx
        b = r[2, 2] / cam.fy
        c = r[2, 0] - r[2, 1] * cam.cx / cam.fx - r[2, 2] * cam.cy / cam.fy
        return a, b, c


def _clip_half_plane(
    poly: list[tuple[float, float]], a: float, b: float, c: float
) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: the part of a polygon where a*u + b*v + c >= 0."""
    out: list[tuple[float, float]] = []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        fp, fq = a * p[0] + b * p[1] + c, a * q[0] + b * q[1] + c
        if fp >= 0:
            out.append(p)
        if (fp >= 0) != (fq >= 0):
            t = fp / (fp - fq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _person_parts(
    person: Person, t: float, cam_right: np.ndarray, cam_ne: tuple[float, float] | None = None
) -> list[tuple[np.ndarray, tuple[int, int, int], str]]:
    """3D polygons (NED) of a person's body parts with colours; standing/sitting are billboards facing the
    camera (`cam_ne`: across the line of sight, as a round body shows its full width from any side; else
    along the camera's right axis), with a level top."""
    n, e, heading = person.state_at(t)
    base = np.array([n, e, 0.0])
    up = np.array([0.0, 0.0, -1.0])
    right = np.array([cam_right[0], cam_right[1], 0.0])
    if cam_ne is not None and math.hypot(n - cam_ne[0], e - cam_ne[1]) > 0.5:
        right = np.array([-(e - cam_ne[1]), n - cam_ne[0], 0.0])
    norm = float(np.linalg.norm(right))
    right = right / norm if norm > 1e-6 else np.array([0.0, 1.0, 0.0])

    def quad(bottom: float, top: float, half_w: float, offset: np.ndarray | None = None) -> np.ndarray:
        o = base if offset is None else base + offset
        return np.array(
            [
                o - half_w * right + bottom * up,
                o + half_w * right + bottom * up,
                o + half_w * right + top * up,
                o - half_w * right + top * up,
            ]
        )

    # A body has depth: from above, the shoulders and the top of the head show, not only a front. Without
    # them a standing person seen from a survey's height was about a fifth smaller than the person the POD
    # map sizes (a 1.7 x 0.5 x 0.3 m box, behaviors/apparent_size.py), so the sim found fewer than the map said.
    away = np.array([right[1], -right[0], 0.0])  # level, away from the camera

    def top(height: float, half_w: float, half_d: float) -> np.ndarray:
        o = base + height * up
        return np.array(
            [o + a * half_d * away + s * half_w * right for a, s in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        )

    def disc(centre_h: float, radius: float, second: np.ndarray) -> np.ndarray:
        """A circle `centre_h` up, in the plane of `right` and `second` (up: the head's face; away: its top)."""
        o = base + centre_h * up
        angles = np.linspace(0, 2 * math.pi, 10, endpoint=False)
        return np.array([o + radius * (math.cos(a) * right + math.sin(a) * second) for a in angles])

    shirt, trousers = person.shirt_bgr, person.trousers_bgr
    if person.pose == "standing":
        # Slight stride so walking legs read as two shapes.
        return [
            (quad(0.0, 0.9, 0.1, -0.12 * right), trousers, "legs"),
            (quad(0.0, 0.9, 0.1, 0.12 * right), trousers, "legs"),
            (quad(0.85, 1.5, 0.27), shirt, "torso"),
            (top(1.5, 0.27, 0.15), shirt, "torso"),
            (disc(1.64, 0.14, up), SKIN_BGR, "head"),
            (disc(1.64, 0.14, away), SKIN_BGR, "head"),
        ]
    if person.pose == "sitting":
        return [
            (quad(0.0, 0.5, 0.24), trousers, "legs"),
            (quad(0.45, 1.05, 0.27), shirt, "torso"),
            (top(1.05, 0.27, 0.15), shirt, "torso"),
            (disc(1.19, 0.14, up), SKIN_BGR, "head"),
            (disc(1.19, 0.14, away), SKIN_BGR, "head"),
        ]
    # Lying flat along the heading: parts are ground rectangles slightly above the grass.
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    across = np.array([-math.sin(heading), math.cos(heading), 0.0])
    lift = np.array([0.0, 0.0, -0.12])

    def flat(a0: float, a1: float, half_w: float) -> np.ndarray:
        return np.array(
            [base + lift + a * along + s * half_w * across for a, s in ((a0, -1), (a1, -1), (a1, 1), (a0, 1))]
        )

    return [
        (flat(-0.9, 0.0, 0.2), trousers, "legs"),
        (flat(-0.05, 0.6, 0.28), shirt, "torso"),
        (flat(0.6, 0.88, 0.14), SKIN_BGR, "head"),
    ]


def stamp_timecode(image: np.ndarray, frame_id: int) -> None:
    """Write frame_id into the bottom-left corner as black/white cells (LSB first)."""
    h = image.shape[0]
    for bit in range(TIMECODE_BITS):
        value = 255 if (frame_id >> bit) & 1 else 0
        x = bit * TIMECODE_CELL
        image[h - TIMECODE_ROWS : h, x : x + TIMECODE_CELL] = value


def read_timecode(image: np.ndarray, width: int | None = None) -> int:
    """The frame id stamped by `stamp_timecode`, also after JPEG coding or scaling to `width` pixels wide."""
    h, w = image.shape[:2]
    scale = w / float(width) if width else 1.0
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    row = max(0, h - max(1, int(round(TIMECODE_ROWS * scale / 2))))
    value = 0
    for bit in range(TIMECODE_BITS):
        x = int((bit + 0.5) * TIMECODE_CELL * scale)
        if x < w and int(gray[row, x]) > 127:
            value |= 1 << bit
    return value


# The most mask pixels `unoccluded_area` fills: a person right under or beside a low camera projects to tens
# of thousands of pixels across, and a mask that size (hundreds of megabytes, up to a second of the render
# thread) stalled the camera stream. Larger outlines are counted on a coarser grid, scaled back.
_COVERAGE_MAX_PX = 1 << 21


def unoccluded_area(polys: list[tuple[np.ndarray, tuple[int, int, int]]]) -> float:
    """Pixels a person's parts would cover with nothing in front and no image border."""
    allpix = np.round(np.vstack([p for p, _ in polys])).astype(np.int32)
    x0, y0 = allpix.min(axis=0)
    x1, y1 = allpix.max(axis=0)
    span = (float(x1 - x0) + 1.0) * (float(y1 - y0) + 1.0)
    scale = min(1.0, (_COVERAGE_MAX_PX / span) ** 0.5)
    mask = np.zeros((int((y1 - y0) * scale) + 1, int((x1 - x0) * scale) + 1), np.uint8)
    for pix, _ in polys:
        pts = np.round(pix).astype(np.int32) - [x0, y0]
        if scale < 1.0:
            pts = np.round(pts * scale).astype(np.int32)
        cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    return float(np.count_nonzero(mask)) / float(scale * scale)


class Renderer:
    """Draws 640x480 (or any size) frames of a world from a vehicle pose."""

    def __init__(self, world: World, camera: CameraModel) -> None:
        self.world = world
        self.camera = camera
        self.texture = ground_texture(world.seed, world.ground_px)
        px_per_m = world.ground_px / world.ground_size_m
        half = world.ground_px / 2.0
        # Texture pixel (col, row) <- ground (north, east): north up, east right, origin in the middle.
        self._ground_to_tex = np.array([[0.0, px_per_m, half], [-px_per_m, 0.0, half], [0.0, 0.0, 1.0]])

    def render(self, pose: VehiclePose, t: float, frame_id: int) -> RenderedFrame:
        cam = self.camera
        size = (cam.width, cam.height)
        proj = Projector(cam, pose)
        h_img = proj.ground_homography()
        tex_to_img = h_img @ np.linalg.inv(self._ground_to_tex)
        image = cv2.warpPerspective(
            self.texture,
            tex_to_img,
            size,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(60, 110, 80),
        )
        # Sky where the ray does not meet the ground within a few hundred metres.
        a, b, c = proj.horizon_coefficients()
        far = -pose.down / 300.0  # rays flatter than this reach past the texture
        sky = _clip_half_plane(
            [
                (0.0, 0.0),
                (float(cam.width), 0.0),
                (float(cam.width), float(cam.height)),
                (0.0, float(cam.height)),
            ],
            -a,
            -b,
            -(c - far),
        )
        if len(sky) >= 3:
            cv2.fillPoly(image, [np.round(np.array(sky)).astype(np.int32)], SKY_BGR)

        ids = np.zeros((cam.height, cam.width), np.uint8)
        cam_right = proj.rotation[:, 1]
        items: list[tuple[float, int, list[tuple[np.ndarray, tuple[int, int, int]]]]] = []
        people = self.world.people
        for idx, person in enumerate(people):
            parts = _person_parts(person, t, cam_right, (pose.north, pose.east))
            polys: list[tuple[np.ndarray, tuple[int, int, int]]] = []
            depth_sum = 0.0
            for pts3, colour, _ in parts:
                pix, depth = proj.project(pts3)
                if np.any(depth <= 0.3):
                    polys = []
                    break
                polys.append((pix, colour))
                depth_sum += float(depth.mean())
            if polys:
                items.append((depth_sum / len(polys), idx + 1, polys))
        for block in self.world.blocks:
            corners = block.corners()
            pix, depth = proj.project(corners)
            if np.any(depth <= 0.3):
                continue
            faces = ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
            shades = (0.5, 1.0, 0.75, 0.85, 0.7, 0.9)
            face_items: list[tuple[float, np.ndarray, tuple[int, int, int]]] = []
            for face, shade in zip(faces, shades, strict=True):
                fd = float(depth[list(face)].mean())
                b, g, r = (int(ch * shade) for ch in block.colour)
                face_items.append((fd, pix[list(face)], (b, g, r)))
            face_items.sort(key=lambda f: -f[0])
            items.append((float(depth.mean()), 255, [(p, col) for _, p, col in face_items]))

        items.sort(key=lambda it: -it[0])  # painter's algorithm: far first
        areas: dict[int, float] = {}
        for _, label, polys in items:
            for pix, colour in polys:
                pts = np.round(pix).astype(np.int32)
                cv2.fillConvexPoly(image, cv2.convexHull(pts), colour, lineType=cv2.LINE_AA)
                cv2.fillConvexPoly(ids, cv2.convexHull(pts), label)
            if label != 255:
                areas[label] = unoccluded_area(polys)

        truth: list[TruthBox] = []
        for _, label, polys in items:
            if label == 255:
                continue
            person = people[label - 1]
            allpix = np.vstack([p for p, _ in polys])
            x1, y1 = allpix.min(axis=0)
            x2, y2 = allpix.max(axis=0)
            box = Box.from_xyxy(float(x1), float(y1), float(x2), float(y2)).clamped(cam.width, cam.height)
            if not box.is_valid() or box.w < 1 or box.h < 1:
                continue
            region = ids[int(box.y) : int(math.ceil(box.y2)), int(box.x) : int(math.ceil(box.x2))]
            seen = float(np.count_nonzero(region == label))
            # Visible fraction: pixels of this person still on top, over the pixels they would cover unclipped.
            denom = max(1.0, areas[label])
            n, e, _ = person.state_at(t)
            truth.append(TruthBox(person.person_id, box, min(1.0, seen / denom), n, e, person.shirt))
        stamp_timecode(image, frame_id)
        return RenderedFrame(frame_id, t, image, tuple(truth), pose)
