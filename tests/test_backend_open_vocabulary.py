"""Grounding DINO and OWLv2 wiring on tiny randomly initialised models built from configs (no download).

Random weights find nothing meaningful; these tests prove the real processors, the model call, the
post-processing, the box frame (clipped, in the caller's pixels), the labels, NMS, saving/loading
through `from_pretrained` on a local folder, and the app accepting any superset text.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from backend.cli import main
from backend.config import DetectorConfig
from backend.detectors.factory import build_detector
from backend.detectors.open_vocabulary import OpenVocabularyDetector
from tests.backend_fixtures import auth, backend_config, detect_parts, frame, jpeg

# torch + transformers and two models built in a fixture: seconds before the first test, so out of the inner loop.
pytestmark = pytest.mark.slow

WORDS = ["person", "car", "boat", "life", "raft", "a", "photo", "of", "man", "in", "gray", "shirt"]


# torch and transformers are imported inside the helpers: at module level they cost seconds of every
# `pytest --collect-only`, whichever tests are selected.
def tiny_grounding_dino(folder: Path) -> tuple[object, object]:
    import torch
    from transformers import (
        BertConfig,
        BertTokenizer,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        GroundingDinoImageProcessorPil,
        GroundingDinoProcessor,
        SwinConfig,
    )

    (folder / "vocab.txt").write_text(
        "\n".join(["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", *WORDS]) + "\n"
    )
    tokenizer = BertTokenizer(str(folder / "vocab.txt"))
    config = GroundingDinoConfig(
        backbone_config=SwinConfig(image_size=64, patch_size=4, embed_dim=16, depths=[1, 1, 1, 1], num_heads=[1, 2, 2, 4],
                                   window_size=4, out_features=["stage2", "stage3", "stage4"]),  # type: ignore[call-arg]
        text_config=BertConfig(vocab_size=len(WORDS) + 6, hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                               intermediate_size=37, max_position_embeddings=64),
        d_model=32, encoder_layers=1, decoder_layers=2, encoder_attention_heads=2, decoder_attention_heads=2,
        encoder_ffn_dim=32, decoder_ffn_dim=32, num_queries=30, encoder_n_points=2, decoder_n_points=2, max_text_len=32,
    )  # fmt: skip
    torch.manual_seed(0)
    model = GroundingDinoForObjectDetection(config)
    processor = GroundingDinoProcessor(  # type: ignore[no-untyped-call]
        image_processor=GroundingDinoImageProcessorPil(size={"shortest_edge": 64, "longest_edge": 96}),
        tokenizer=tokenizer,
    )
    return model, processor


def tiny_owlv2() -> tuple[object, object]:
    import torch
    from transformers import (
        CLIPTokenizer,
        Owlv2Config,
        Owlv2ForObjectDetection,
        Owlv2ImageProcessorPil,
        Owlv2Processor,
    )

    tokens = [
        "!",
        "<|startoftext|>",
        "<|endoftext|>",
        *(w + "</w>" for w in WORDS),
        *"abcdefghijklmnopqrstuvwxyz",
    ]
    tokenizer = CLIPTokenizer(vocab={t: i for i, t in enumerate(tokens)}, merges=[], model_max_length=16)
    text = dict(
        vocab_size=len(tokens),
        hidden_size=32,
        intermediate_size=37,
        num_hidden_layers=1,
        num_attention_heads=2,
        max_position_embeddings=16,
        bos_token_id=1,
        eos_token_id=2,
        pad_token_id=2,
    )
    vision = dict(
        hidden_size=32,
        intermediate_size=37,
        num_hidden_layers=1,
        num_attention_heads=2,
        image_size=64,
        patch_size=16,
    )
    torch.manual_seed(0)
    model = Owlv2ForObjectDetection(Owlv2Config(text_config=text, vision_config=vision, projection_dim=32))
    # Random box heads saturate the sigmoid into zero-size boxes; a zero last layer predicts the model's
    # own anchor boxes (one per patch), which exercises the same post-processing with valid boxes.
    with torch.no_grad():
        model.box_head.dense2.weight.zero_()
        model.box_head.dense2.bias.zero_()
    processor = Owlv2Processor(  # type: ignore[no-untyped-call]
        image_processor=Owlv2ImageProcessorPil(size={"height": 64, "width": 64}), tokenizer=tokenizer
    )
    return model, processor


@pytest.fixture(scope="module")
def detectors(tmp_path_factory: pytest.TempPathFactory) -> dict[str, OpenVocabularyDetector]:
    gd_model, gd_processor = tiny_grounding_dino(tmp_path_factory.mktemp("gd"))
    ow_model, ow_processor = tiny_owlv2()
    return {
        "grounding_dino": OpenVocabularyDetector(
            "grounding_dino", gd_model, gd_processor, score_threshold=0.05, text_threshold=0.0
        ),
        "owlv2": OpenVocabularyDetector("owlv2", ow_model, ow_processor, score_threshold=0.05),
    }


@pytest.mark.parametrize("kind", ["grounding_dino", "owlv2"])
def test_detections_are_in_the_callers_pixels_with_labels(
    kind: str, detectors: dict[str, OpenVocabularyDetector], sequences_dir: Path
) -> None:
    image = frame(sequences_dir, size=(320, 180))
    found = detectors[kind].detect(image, ["person", "car"])
    assert found, "the tiny model answered nothing above the threshold"
    for d in found:
        assert d.box.x >= 0 and d.box.x2 <= 320 and d.box.y >= 0 and d.box.y2 <= 180 and d.box.is_valid()
        assert d.label in {"person", "car"} and 0.05 <= d.score <= 1
    assert found == detectors[kind].detect(image, ["person", "car"])  # deterministic


def test_owlv2_boxes_use_the_padded_square(
    detectors: dict[str, OpenVocabularyDetector], sequences_dir: Path
) -> None:
    wide = frame(sequences_dir, size=(320, 120))
    assert all(d.box.y2 <= 120 for d in detectors["owlv2"].detect(wide, ["person"]))


def test_bad_input_is_refused(detectors: dict[str, OpenVocabularyDetector]) -> None:
    import torch

    with pytest.raises(ValueError, match="BGR"):
        detectors["owlv2"].detect(np.zeros((10, 10), np.uint8), ["person"])
    with pytest.raises(ValueError, match="no class"):
        detectors["owlv2"].detect(np.zeros((10, 10, 3), np.uint8), [" "])
    with pytest.raises(ValueError, match="kind"):
        OpenVocabularyDetector("yolo", torch.nn.Linear(1, 1), None)


def test_factory_loads_a_saved_model_folder(tmp_path: Path, sequences_dir: Path) -> None:
    model, processor = tiny_grounding_dino(tmp_path)
    model.save_pretrained(tmp_path / "gd-tiny")  # type: ignore[attr-defined]
    processor.save_pretrained(tmp_path / "gd-tiny")  # type: ignore[attr-defined]
    detector = build_detector(
        DetectorConfig(kind="grounding_dino", hf_model=str(tmp_path / "gd-tiny"), score_threshold=0.05)
    )
    assert detector.name == f"grounding_dino:{tmp_path / 'gd-tiny'}"
    assert all(d.label == "person" for d in detector.detect(frame(sequences_dir, size=(160, 90)), ["person"]))


def test_serve_names_a_model_folder_that_is_not_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "no-such-model"
    assert main(["serve", "--set", 'detector.kind="owlv2"', "--set", f'detector.hf_model="{missing}"']) == 2
    assert "no-such-model" in capsys.readouterr().err


def test_app_takes_any_superset_text_with_an_open_vocabulary_detector(
    models_dir: Path, detectors: dict[str, OpenVocabularyDetector], sequences_dir: Path
) -> None:
    app = create_app(backend_config(models_dir, 'detector.kind="owlv2"'), detector=detectors["owlv2"])
    with TestClient(app) as client:
        keyframe = jpeg(frame(sequences_dir, size=(320, 180)))
        response = client.post(
            "/v1/detect",
            headers=auth(),
            **detect_parts(keyframe, prompt="an orange life raft", superset="life raft"),
        )
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["superset"] == "life raft" and all(c["label"] == "life raft" for c in body["candidates"])
        assert json.loads(json.dumps(client.get("/v1/models", headers=auth()).json()))["supersets"] == []
