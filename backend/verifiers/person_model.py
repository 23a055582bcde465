"""Body keypoints and a person mask from MediaPipe's BlazePose GHUM "full" landmark model, on a CPU.

The model file (`pose_landmark_full.tflite`, 6.4 MB) is the one the mediapipe 0.10.14 wheel on PyPI ships
(newer wheels ship none). mediapipe itself is not installed: its wheel declares the GUI OpenCV build, jax
and sounddevice. `python -m backend.verifiers.person_model install` has pip fetch that wheel (no
dependencies) and copies the one file out of it, checked against its SHA-256; the `person` extra brings
the runtime (ai-edge-litert, the TFLite interpreter). Nothing is fetched at run time.

One forward pass on a 256 x 256 square around the person box gives 33 keypoints with visibility, a
body-present score and a 256 x 256 segmentation of the person (the model was trained on ROIs that
MediaPipe's own detector aligns; a YOLOX box padded to a square serves the same purpose for an upright
body, and a box wider than tall is also tried turned by 90 degrees either way, for a person lying down).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import queue
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

MODEL_NAME = "pose_landmark_full.tflite"
MODEL_SHA256 = "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f"
WHEEL = "mediapipe==0.10.14"
WHEEL_MEMBER = "mediapipe/modules/pose_landmark/pose_landmark_full.tflite"
INPUT = 256
ROI_SCALE = 1.5  # square side / longer box side: the whole body and some context, as the model was trained
MASK_LOGIT = 0.0  # segmentation logit above which a pixel is the person (probability 0.5)
# Landmark indices (BlazePose topology).
NOSE, L_SHOULDER, R_SHOULDER, L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE = (
    0,
    11,
    12,
    23,
    24,
    25,
    26,
    27,
    28,
)


class PersonModelUnavailable(RuntimeError):
    """The runtime or the model file is missing; the message says how to install it."""


def default_model_dir() -> Path:
    """`CLOUDTRACK_PERSON_MODELS`, else share/cloudtrack/person-models inside the Python environment."""
    env = os.environ.get("CLOUDTRACK_PERSON_MODELS")
    return Path(env) if env else Path(sys.prefix) / "share" / "cloudtrack" / "person-models"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def install_model(dest: Path) -> Path:
    """Fetch the mediapipe 0.10.14 wheel with pip (no dependencies) and copy the pose model out of it."""
    target = dest / MODEL_NAME
    if target.exists() and _sha256(target) == MODEL_SHA256:
        return target
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        # Any platform's wheel holds the same file: ask for one that exists whatever Python runs this.
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "-q",
                "--no-deps",
                "--only-binary=:all:",
                "--platform",
                "manylinux_2_17_x86_64",
                "--python-version",
                "3.11",
                "--implementation",
                "cp",
                "-d",
                tmp,
                WHEEL,
            ],
            check=True,
        )
        (wheel,) = Path(tmp).glob("mediapipe-*.whl")
        with zipfile.ZipFile(wheel) as archive:
            data = archive.read(WHEEL_MEMBER)
    if hashlib.sha256(data).hexdigest() != MODEL_SHA256:
        raise PersonModelUnavailable(f"{WHEEL_MEMBER} in {wheel.name} does not have the expected SHA-256")
    partial = target.with_suffix(".part")
    partial.write_bytes(data)
    partial.replace(target)
    return target


@dataclass(frozen=True)
class PersonPose:
    """What the model saw, in the pixels of the image it was given."""

    presence: float  # the model's body-present score, 0..1
    keypoints: np.ndarray  # 33 x 2 (x, y)
    visibility: np.ndarray  # 33, 0..1
    mask: np.ndarray  # bool, the image's height x width: pixels of the person (inside the square only)
    rotation: int  # degrees the square was turned before the model saw it (0, 90 or 270)


def _sigmoid(v: np.ndarray) -> np.ndarray:
    return np.asarray(1.0 / (1.0 + np.exp(-np.clip(v, -30, 30))))


@dataclass
class _Interpreter:
    interpreter: Any
    input: int
    landmarks: int
    flag: int
    segmentation: int


class PersonModel:
    """Loads the model once per interpreter; `estimate` takes a free interpreter (`instances` of them, 0:
    one per core, each with one thread), so candidates are judged in parallel up to that many."""

    def __init__(self, model_dir: Path | None = None, threads: int = 1, instances: int = 1) -> None:
        path = (model_dir or default_model_dir()) / MODEL_NAME
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError as exc:
            raise PersonModelUnavailable(
                "the local person verifier needs the TFLite runtime: pip install 'cloudtrack[person]'"
            ) from exc
        if not path.exists():
            raise PersonModelUnavailable(
                f"no {path}: run `python -m backend.verifiers.person_model install` "
                "(copies it from the mediapipe 0.10.14 wheel on PyPI)"
            )
        self._idle: queue.SimpleQueue[_Interpreter] = queue.SimpleQueue()
        for _ in range(instances or os.cpu_count() or 1):
            interpreter = Interpreter(str(path), num_threads=threads)
            interpreter.allocate_tensors()
            outputs = {d["name"]: d["index"] for d in interpreter.get_output_details()}
            self._idle.put(
                _Interpreter(
                    interpreter,
                    interpreter.get_input_details()[0]["index"],
                    outputs["Identity"],
                    outputs["Identity_1"],
                    outputs["Identity_2"],
                )
            )

    def _run(
        self, image_bgr: np.ndarray, box: tuple[float, float, float, float], rotation: int
    ) -> PersonPose:
        x, y, w, h = box
        side = max(w, h) * ROI_SCALE
        # image -> square: turn by `rotation` about the box centre, scale the square to INPUT pixels.
        forward = cv2.getRotationMatrix2D((x + w / 2, y + h / 2), float(rotation), INPUT / side)
        forward[:, 2] += np.array([INPUT / 2 - (x + w / 2), INPUT / 2 - (y + h / 2)])
        square = cv2.warpAffine(
            image_bgr, forward, (INPUT, INPUT), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0)
        )
        tensor = cv2.cvtColor(square, cv2.COLOR_BGR2RGB).astype(np.float32)[None] / 255.0
        slot = self._idle.get()  # blocks while every interpreter is busy
        try:
            slot.interpreter.set_tensor(slot.input, tensor)
            slot.interpreter.invoke()
            landmarks = slot.interpreter.get_tensor(slot.landmarks).reshape(39, 5)[:33].copy()
            presence = float(slot.interpreter.get_tensor(slot.flag).ravel()[0])
            logits = slot.interpreter.get_tensor(slot.segmentation)[0, :, :, 0].copy()
        finally:
            self._idle.put(slot)
        back = cv2.invertAffineTransform(forward)
        points = landmarks[:, :2] @ back[:, :2].T + back[:, 2]
        mask = cv2.warpAffine(
            (logits > MASK_LOGIT).astype(np.uint8),
            back,
            (image_bgr.shape[1], image_bgr.shape[0]),
            flags=cv2.INTER_NEAREST,
            borderValue=0,
        ).astype(bool)
        return PersonPose(presence, points, _sigmoid(landmarks[:, 3]), mask, rotation)

    def estimate(self, image_bgr: np.ndarray, box: tuple[float, float, float, float]) -> PersonPose:
        """The body in `box` (x, y, w, h); a box not clearly taller than wide is also tried turned 90 degrees."""
        best = self._run(image_bgr, box, 0)
        if box[3] < 1.3 * box[2]:
            for rotation in (90, 270):
                other = self._run(image_bgr, box, rotation)
                if other.presence > best.presence:
                    best = other
        return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m backend.verifiers.person_model",
        description="Install the person model of the local verifier.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    install = sub.add_parser("install", help=f"copy {MODEL_NAME} out of the {WHEEL} wheel (fetched by pip)")
    install.add_argument(
        "--dest",
        type=Path,
        default=None,
        help="folder (default: $CLOUDTRACK_PERSON_MODELS or <env>/share/cloudtrack/person-models)",
    )
    args = parser.parse_args(argv)
    print(install_model(args.dest or default_model_dir()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
