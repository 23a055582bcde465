"""Building the configured superset detector (`[detector] kind`)."""

from __future__ import annotations

from backend.config import DetectorConfig
from backend.detectors.interface import SupersetDetector
from cloudtrack.model_store import ModelError, require, resolve_model_dir

# `precision = "int8"`: the weights `python -m backend_tools.quantize` derives from the fp32 ones, beside them.
INT8_NAME = "yolox_nano_int8.onnx"


def build_detector(config: DetectorConfig) -> SupersetDetector:
    """The detector for `config.kind`; heavy or optional dependencies are imported only when chosen."""
    if config.kind == "yolox":
        closed_set = _yolox(config)
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
        "backend.app.create_app(detector=...); use 'yolox', 'grounding_dino' or 'owlv2' for a standalone server"
    )


def _yolox(config: DetectorConfig) -> SupersetDetector:
    from backend.detectors.yolox import YoloxDetector

    model_dir = resolve_model_dir(config.model_dir or None)
    weights = require("yolox", model_dir)["yolox_nano.onnx"]
    if config.precision == "int8":
        weights = weights.with_name(INT8_NAME)
        if not weights.is_file():
            raise ModelError(
                f"detector precision int8: {weights} is missing; derive it from the fp32 weights with "
                f"`python -m backend_tools.quantize SEQUENCE_FOLDERS... --model-dir {model_dir}`"
            )
    yolox = YoloxDetector(weights, config.score_threshold, config.nms_threshold, threads=config.threads)
    if not config.tiles:
        return yolox
    from backend.detectors.tiling import TiledDetector

    return TiledDetector(
        yolox,
        config.tiles,
        config.tile_overlap,
        config.nms_threshold,
        min_side=yolox.input_size,
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
