"""Building the configured superset detector (`[detector] kind`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from backend.config import DetectorConfig
from backend.detectors.interface import SupersetDetector
from cloudtrack.model_store import ModelError, require, resolve_model_dir

if TYPE_CHECKING:
    from backend.detectors.deimv2 import Deimv2Detector
    from backend.detectors.yolox import YoloxDetector

# `precision = "int8"`: the weights `python -m backend_tools.quantize` derives from the fp32 ones, beside them.
INT8_NAME = "yolox_nano_int8.onnx"


# Closed-set (COCO-80 ONNX) kinds -> (model store name, weight file name).
CLOSED_SET_WEIGHTS = {
    "yolox": ("yolox", "yolox_nano.onnx"),
    "deimv2_atto": ("deimv2_atto", "deimv2_hgnetv2_atto_coco.onnx"),
    "deimv2_femto": ("deimv2_femto", "deimv2_hgnetv2_femto_coco.onnx"),
}


def build_detector(config: DetectorConfig) -> SupersetDetector:
    """The detector for `config.kind`; heavy or optional dependencies are imported only when chosen."""
    if config.kind in CLOSED_SET_WEIGHTS:
        closed_set = _closed_set(config)
        if not config.open_vocabulary:
            return closed_set
        from backend.detectors.routing import RoutingDetector

        return RoutingDetector(closed_set, _open_vocabulary(config, config.open_vocabulary))
    if config.kind in ("grounding_dino", "owlv2"):
        return _open_vocabulary(config, config.kind)
    # The SITL detector answers from the simulated world's ground truth, so only the simulator, which
    # owns that world, can build it: `cloudtrack-sim` passes it to create_app(detector=...).
    raise ValueError(
        "detector kind 'simulated' is built by the simulator (cloudtrack-sim), which passes it to "
        "backend.app.create_app(detector=...); use 'yolox', 'deimv2_atto', 'deimv2_femto', 'grounding_dino' "
        "or 'owlv2' for a standalone server"
    )


def closed_set_weights(config: DetectorConfig) -> Path:
    """The verified weight file of a closed-set kind (the int8 YOLOX file for `precision = "int8"`)."""
    store_name, file_name = CLOSED_SET_WEIGHTS[config.kind]
    model_dir = resolve_model_dir(config.model_dir or None)
    weights = require(store_name, model_dir)[file_name]
    if config.precision == "int8":
        weights = weights.with_name(INT8_NAME)
        if not weights.is_file():
            raise ModelError(
                f"detector precision int8: {weights} is missing; derive it from the fp32 weights with "
                f"`python -m backend_tools.quantize SEQUENCE_FOLDERS... --model-dir {model_dir}`"
            )
    return weights


def _closed_set(config: DetectorConfig) -> SupersetDetector:
    """YOLOX or DEIMv2 with the same threshold, NMS and tiling settings."""
    weights = closed_set_weights(config)
    model: YoloxDetector | Deimv2Detector
    if config.kind == "yolox":
        from backend.detectors.yolox import YoloxDetector

        model = YoloxDetector(weights, config.score_threshold, config.nms_threshold, threads=config.threads)
    else:
        from backend.detectors.deimv2 import Deimv2Detector

        model = Deimv2Detector(weights, config.score_threshold, config.nms_threshold, threads=config.threads)
    if not config.tiles:
        return model
    from backend.detectors.tiling import TiledDetector

    return TiledDetector(
        model,
        config.tiles,
        config.tile_overlap,
        config.nms_threshold,
        min_side=model.input_size,
        parallel=config.parallel_tiles,
    )


def _open_vocabulary(config: DetectorConfig, kind: str) -> SupersetDetector:
    from backend.detectors.open_vocabulary import OpenVocabularyDetector

    try:
        import torch  # noqa: F401
        import transformers  # noqa: F401
    except ImportError as exc:
        raise ValueError(
            f"detector kind {kind!r} needs the gpu extra: pip install 'cloudtrack[gpu]' ({exc})"
        ) from exc
    open_vocabulary: SupersetDetector = OpenVocabularyDetector.from_pretrained(
        kind, config.hf_model, config.device, config.score_threshold
    )
    return open_vocabulary
