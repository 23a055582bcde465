"""Superset detectors: a keyframe in, boxes of the requested classes out (`SupersetDetector`)."""

from backend.detectors.interface import SupersetDetector

__all__ = ["SupersetDetector"]
