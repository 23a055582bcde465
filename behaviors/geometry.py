"""Image-plane boxes and the overlap measure used everywhere (tracking, evaluation, candidate choice)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in pixels: top-left corner (x, y), width w, height h."""

    x: float
    y: float
    w: float
    h: float

    @classmethod
    def from_xyxy(cls, x1: float, y1: float, x2: float, y2: float) -> Box:
        return cls(x1, y1, x2 - x1, y2 - y1)

    @classmethod
    def from_center(cls, cx: float, cy: float, w: float, h: float) -> Box:
        return cls(cx - w / 2.0, cy - h / 2.0, w, h)

    @property
    def x2(self) -> float:
        return self.x + self.w

    @property
    def y2(self) -> float:
        return self.y + self.h

    @property
    def cx(self) -> float:
        return self.x + self.w / 2.0

    @property
    def cy(self) -> float:
        return self.y + self.h / 2.0

    @property
    def area(self) -> float:
        return max(0.0, self.w) * max(0.0, self.h)

    def xyxy(self) -> tuple[float, float, float, float]:
        return (self.x, self.y, self.x2, self.y2)

    def xywh(self) -> tuple[float, float, float, float]:
        return (self.x, self.y, self.w, self.h)

    def is_valid(self) -> bool:
        """Finite, with positive size."""
        values = (self.x, self.y, self.w, self.h)
        return all(math.isfinite(v) for v in values) and self.w > 0 and self.h > 0

    def clamped(self, width: float, height: float) -> Box:
        """The part of the box inside a width x height image (may have zero size)."""
        x1 = min(max(self.x, 0.0), width)
        y1 = min(max(self.y, 0.0), height)
        x2 = min(max(self.x2, 0.0), width)
        y2 = min(max(self.y2, 0.0), height)
        return Box(x1, y1, x2 - x1, y2 - y1)

    def expanded(self, margin: float) -> Box:
        """The box grown by `margin` pixels on every side."""
        return Box(self.x - margin, self.y - margin, self.w + 2 * margin, self.h + 2 * margin)

    def scaled(self, sx: float, sy: float) -> Box:
        """The box in an image resized by (sx, sy)."""
        return Box(self.x * sx, self.y * sy, self.w * sx, self.h * sy)


def iou(a: Box, b: Box) -> float:
    """Intersection over union; 0 for invalid or disjoint boxes."""
    if not (a.is_valid() and b.is_valid()):
        return 0.0
    ix = max(0.0, min(a.x2, b.x2) - max(a.x, b.x))
    iy = max(0.0, min(a.y2, b.y2) - max(a.y, b.y))
    inter = ix * iy
    union = a.area + b.area - inter
    return inter / union if union > 0 else 0.0
