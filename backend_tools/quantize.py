"""Static int8 quantisation of YOLOX-nano with onnxruntime's own tooling, calibrated on real frames.

    python -m backend_tools.quantize ../shared/data/sequences/* --model-dir ../shared/models \
        --out ~/.cache/cloudtrack/models/yolox_nano/yolox_nano_int8.onnx

The shared fp32 weights are read, never changed; the int8 model is written where `[detector] precision =
"int8"` looks for it (`<model_dir>/yolox_nano/yolox_nano_int8.onnx`) or to --out. Weights are never
committed. QDQ format, convolutions only, per-channel int8 weights, uint8 activations, MinMax calibration
on letterboxed frames exactly as the detector feeds them. What stays fp32, and why (measured on
uav123_person12_1, docs/benchmarks.md):
- the detection head's last convolutions and everything after them: box offsets (up to ~10) and
  probabilities (0-1) share one tensor there, and one uint8 scale for both wipes out the scores;
- the stem (the first STEM_CONVS convolutions): YOLOX takes unnormalised 0-255 pixels, so its first
  activations span hundreds of units and uint8 steps erase the small values SiLU depends on; quantising
  the first convolution alone dropped the person-score correlation with fp32 to 0.3;
- the SiLU activations (Sigmoid x Mul): quantised too, recall on uav123_person12_1 fell from 0.71 to 0.0.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from backend.detectors.factory import INT8_NAME

STEM_CONVS = 10


def calibration_frames(sequences: Sequence[Path], per_sequence: int) -> Iterator[np.ndarray]:
    """`per_sequence` frames spread evenly over each sequence (BGR)."""
    for seq in sequences:
        frames = sorted((seq / "frames").glob("*.jpg"))
        if not frames:
            raise ValueError(f"{seq}: no frames/*.jpg")
        for index in np.linspace(0, len(frames) - 1, min(per_sequence, len(frames))).round().astype(int):
            image = cv2.imread(str(frames[index]))
            if image is None:
                raise ValueError(f"cannot read {frames[index]}")
            yield image


def fp32_nodes(model_path: Path) -> list[str]:
    """Nodes kept in fp32: the stem's convolutions and the head from its prediction convolutions on."""
    import onnx

    graph = onnx.load(str(model_path)).graph
    stem = [node.name for node in graph.node if node.op_type == "Conv"][:STEM_CONVS]
    producer = {out: node for node in graph.node for out in node.output}
    names: list[str] = []
    todo = [o.name for o in graph.output]
    while todo:
        node = producer.get(todo.pop())
        if node is None or node.name in names:
            continue
        names.append(node.name)
        if node.op_type != "Conv":  # walk up until the prediction convolutions
            todo.extend(node.input)
    return stem + names


def quantize(
    model_path: Path, out: Path, sequences: Sequence[Path], per_sequence: int = 16
) -> dict[str, float]:
    """Write the int8 model to `out`; returns how many calibration frames and seconds it took."""
    import onnx
    import onnx.version_converter
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from backend.detectors.yolox import YoloxDetector

    start = time.perf_counter()
    letterbox = YoloxDetector(model_path, threads=1)
    blobs = [letterbox.preprocess(image)[0] for image in calibration_frames(sequences, per_sequence)]
    input_name = letterbox.input_name

    class Frames(CalibrationDataReader):  # type: ignore[misc]
        def __init__(self) -> None:
            self._items = iter(blobs)

        def get_next(self) -> dict[str, np.ndarray] | None:
            blob = next(self._items, None)
            return None if blob is None else {input_name: blob}

    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        # Per-channel QDQ needs DequantizeLinear's `axis` (opset 13); the 2022 export is opset 11.
        model = onnx.load(str(model_path))
        if max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) < 13:
            model = onnx.version_converter.convert_version(model, 13)
        upgraded, prepared = Path(tmp) / "opset13.onnx", Path(tmp) / "prepared.onnx"
        onnx.save(model, str(upgraded))
        quant_pre_process(str(upgraded), str(prepared), skip_symbolic_shape=True)
        quantize_static(
            str(prepared), str(out), Frames(), quant_format=QuantFormat.QDQ, per_channel=True,
            op_types_to_quantize=["Conv"], activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
            calibrate_method=CalibrationMethod.MinMax,
            nodes_to_exclude=fp32_nodes(prepared),
        )  # fmt: skip
    return {"calibration_frames": float(len(blobs)), "seconds": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> int:
    from cloudtrack.model_store import ModelError, require, resolve_model_dir

    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.quantize",
        description="Derive an int8 YOLOX-nano from the fp32 weights (static quantisation, calibrated on "
        'frames of the given sequences) for [detector] precision = "int8".',
        epilog="example:\n  python -m backend_tools.quantize ../shared/data/sequences/* "
        "--model-dir ../shared/models "
        "--out /tmp/models/yolox_nano/yolox_nano_int8.onnx",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sequences", nargs="+", type=Path, help="sequence folders with frames/*.jpg (calibration)"
    )
    parser.add_argument(
        "--model-dir",
        help="folder with yolox_nano/yolox_nano.onnx (default: $CLOUDTRACK_MODEL_DIR, then the cache)",
    )
    parser.add_argument(
        "--out", type=Path, help=f"int8 model to write (default: <model-dir>/yolox_nano/{INT8_NAME})"
    )
    parser.add_argument(
        "--frames-per-sequence", type=int, default=16, help="calibration frames per sequence (default 16)"
    )
    args = parser.parse_args(argv)
    try:
        model_dir = resolve_model_dir(args.model_dir)
        fp32 = require("yolox", model_dir)["yolox_nano.onnx"]
        out = args.out or fp32.with_name(INT8_NAME)
        info = quantize(fp32, out, args.sequences, args.frames_per_sequence)
    except (ModelError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(
        f"{out}: int8 from {fp32}, {info['calibration_frames']:.0f} calibration frames, "
        f"{info['seconds']:.1f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
