"""The core install (`pip install .`, no extras) stays light enough for a Raspberry Pi 4."""

from __future__ import annotations

import re
from importlib import metadata

from packaging.requirements import Requirement

HEAVY = {
    "fastapi",
    "starlette",
    "uvicorn",
    "torch",
    "transformers",
    "flask",
    "django",
    "tensorflow",
    "grpcio",
    "mavsdk",
}


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(dist_name: str) -> set[str]:
    """Every distribution `pip install dist_name` (no extras) pulls in, read from installed metadata."""
    seen: set[str] = set()
    pending = [dist_name]
    while pending:
        name = _canonical(pending.pop())
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue  # not installed here; it is a leaf for this check
        for line in requires:
            req = Requirement(line)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                pending.append(req.name)
    return seen


def test_core_install_has_no_server_stack_or_torch() -> None:
    closure = _closure("cloudtrack")
    assert {"pymavlink", "opencv-contrib-python-headless", "onnxruntime", "numpy", "pyserial"} <= closure
    assert not closure & HEAVY, closure & HEAVY


def test_excluded_opencv_release_is_excluded() -> None:
    requires = [Requirement(r) for r in metadata.requires("cloudtrack") or []]
    opencv = next(r for r in requires if r.name == "opencv-contrib-python-headless")
    assert "4.12.0.88" not in opencv.specifier and "4.11.0.86" in opencv.specifier
    mavsdk = next(r for r in requires if r.name == "mavsdk")
    # 4.x is the in-process native binding; 3.x started mavsdk_server, a gRPC API on 0.0.0.0
    assert "4.1.0" in mavsdk.specifier and "3.17.4" not in mavsdk.specifier
