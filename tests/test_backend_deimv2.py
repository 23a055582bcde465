"""DEIMv2 (Atto, Femto) as the back-end's superset detector: real weights, real frames, real HTTP."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest

import backend.serving
from backend.cli import main as backend_main
from backend.config import DetectorConfig
from backend.detectors.deimv2 import Deimv2Detector
from backend.detectors.factory import build_detector
from backend.detectors.tiling import TiledDetector
from backend.supersets import COCO_THINGS
from backend_tools.detector_recall import main as recall_main
from behaviors.geometry import Box, iou
from cloudtrack.config_files import ConfigError, load_config
from cloudtrack.model_store import REGISTRY, ModelError
from tests.backend_fixtures import TOKENS, auth, detect_parts, frame, jpeg
from tests.live_backend import serve

KINDS = {"deimv2_atto": ("deimv2_hgnetv2_atto_coco", 320), "deimv2_femto": ("deimv2_hgnetv2_femto_coco", 416)}


@pytest.fixture(scope="module", params=sorted(KINDS))
def model(request: pytest.FixtureRequest, models_dir: Path) -> Deimv2Detector:
    detector = build_detector(DetectorConfig(kind=request.param, model_dir=str(models_dir), tiles=0))
    assert isinstance(detector, Deimv2Detector)
    return detector


def test_models_md_checksums_are_the_stores(shared_dir: Path) -> None:
    """The store verifies DEIMv2 against the sha256 and size MODELS.md publishes for the shared files."""
    rows = {
        cells[1]: cells
        for line in (shared_dir / "models" / "MODELS.md").read_text().splitlines()
        if (cells := [c.strip() for c in line.split("|")]) and len(cells) > 5
    }
    for name in ("deimv2_atto", "deimv2_femto"):
        (mf,) = REGISTRY[name].files
        assert rows[mf.relpath][3:5] == [str(mf.size), mf.sha256], name


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_finds_the_person_with_the_back_ends_tiling(kind: str, models_dir: Path, sequences_dir: Path) -> None:
    """uav123_person12_1 at 640x360, `tiles = 2` (the default): the walker (ground truth / 2) is boxed at
    IoU >= 0.5 in most frames (the whole frame alone, squeezed to 320 px, boxes it in 2 of 11 with Atto)."""
    model = build_detector(DetectorConfig(kind=kind, model_dir=str(models_dir), threads=1))
    rows = (sequences_dir / "uav123_person12_1" / "groundtruth.txt").read_text().split()
    hits = 0
    indices = range(1, len(rows) + 1, 20)
    for index in indices:
        truth = Box(*(float(v) / 2 for v in rows[index - 1].split(",")))
        found = model.detect(frame(sequences_dir, index=index), ["person"])
        assert all(d.label == "person" for d in found)
        assert all(d.score >= DetectorConfig().score_threshold for d in found)
        hits += any(iou(truth, d.box) >= 0.5 for d in found)
    assert hits >= 0.7 * len(indices), f"{hits} of {len(indices)}"


def test_vehicle_stand_ins_and_supersets_map_as_for_yolox(model: Deimv2Detector, sequences_dir: Path) -> None:
    """uavdt_S1606 (a queue of cars): `truck` and `bus` are searched among cars, `vehicle` holds every car box;
    the labels are only the superset's classes."""
    image = frame(sequences_dir, "uavdt_S1606", size=(640, 338))
    cars = model.detect(image, ["car"])
    assert cars and {d.label for d in cars} <= {"car", "truck"}
    trucks = model.detect(image, ["truck"])
    assert trucks and {d.label for d in trucks} <= {"car", "truck"}
    assert {d.label for d in model.detect(image, ["bus"])} <= {"bus", "truck", "car"}
    vehicles = model.detect(image, ["vehicle"])
    # A superset scores a box at least as high as any of its classes do (1 - prod(1 - p)): each car box is
    # kept or suppressed by a better one that NMS found overlapping it.
    for car in cars:
        covering = [v for v in vehicles if iou(car.box, v.box) >= model.nms_threshold - 1e-6]
        assert any(v.score >= car.score - 1e-6 for v in covering)
    both = {(d.box.xyxy(), d.score) for d in model.detect(image, ["car", "person"])}
    assert {(d.box.xyxy(), d.score) for d in cars} <= both  # each superset of a call as if asked alone
    bag = model.detect(frame(sequences_dir, "vot2015_bag", size=None), ["bag"])
    assert {d.label for d in bag} <= set(COCO_THINGS)  # a stand-in: never a person, an animal or a vehicle


def test_hostile_images_are_refused_or_answered(model: Deimv2Detector) -> None:
    with pytest.raises(ValueError, match="H x W x 3"):
        model.detect(np.zeros((32, 32), np.uint8), ["person"])
    with pytest.raises(ValueError, match="H x W x 3"):
        model.detect(np.zeros((0, 32, 3), np.uint8), ["person"])
    assert model.detect(np.zeros((1, 1, 3), np.uint8), ["person"]) == []  # nothing to see, no crash
    assert model.detect(np.full((20, 2000, 3), 128, np.uint8), ["person"]) == []  # extreme aspect ratio


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_factory_tiles_verifies_and_refuses_int8(kind: str, models_dir: Path, tmp_path: Path) -> None:
    name, size = KINDS[kind]
    tiled = build_detector(DetectorConfig(kind=kind, model_dir=str(models_dir)))  # tiles = 2 by default
    assert isinstance(tiled, TiledDetector) and tiled.columns == 2 and tiled.name == name
    assert tiled.min_side == size  # a frame the model sees whole at full resolution is not sliced
    with pytest.raises(ConfigError, match="int8 is for kind yolox only"):
        load_config(DetectorConfig, None, environ={}, assignments=[f"kind={kind}", "precision=int8"])
    (mf,) = REGISTRY[kind].files
    corrupt = tmp_path / mf.relpath
    corrupt.parent.mkdir(parents=True)
    data = bytearray((models_dir / mf.relpath).read_bytes())
    data[5000] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    with pytest.raises(ModelError, match=f"corrupt.*models download {kind}"):
        build_detector(DetectorConfig(kind=kind, model_dir=str(tmp_path)))
    shutil.rmtree(tmp_path / "deimv2")
    with pytest.raises(ModelError, match="missing"):
        build_detector(DetectorConfig(kind=kind, model_dir=str(tmp_path)))


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_serve_set_detector_kind_answers_v1_detect(
    kind: str, models_dir: Path, sequences_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`cloudtrack-backend serve --model-dir DIR --set detector.kind=KIND` on a loopback port: /v1/models
    names the model and /v1/detect finds the walker of uav123_person12_1 with it."""
    answers: dict[str, httpx.Response] = {}

    def serve_on_loopback(app: object, host: str, port: int, log_level: str) -> None:
        with serve(app) as url, httpx.Client(base_url=url, timeout=60) as client:
            answers["models"] = client.get("/v1/models", headers=auth())
            answers["detect"] = client.post(
                "/v1/detect", headers=auth(), **detect_parts(jpeg(frame(sequences_dir)), frame_id=3)
            )

    monkeypatch.setattr(backend.serving, "serve", serve_on_loopback)
    settings = [f"auth.tokens={json.dumps(TOKENS)}", f"detector.kind={kind}", "verifier.kind=none"]
    settings += ["detector.threads=1", 'sessions.sqlite_path=":memory:"']
    argv = ["serve", "--model-dir", str(models_dir), *(a for s in settings for a in ("--set", s))]
    assert backend_main(argv) == 0
    models = answers["models"].json()
    assert models["detector"] == KINDS[kind][0] and models["detector_kind"] == kind
    assert "person" in models["supersets"]  # closed set: the supersets it maps
    assert answers["detect"].status_code == 200, answers["detect"].text
    body = answers["detect"].json()
    assert body["models"]["detector"] == KINDS[kind][0] and body["superset"] == "person"
    # Ground truth of frame 1 is (490, 235, 34, 85) at 1280x720, about (245, 117, 262, 160) here.
    best = max(body["candidates"], key=lambda c: c["score"])
    x1, y1, x2, y2 = best["box"]
    assert best["label"] == "person" and 235 < (x1 + x2) / 2 < 275 and 120 < (y1 + y2) / 2 < 160


def test_recall_tool_compares_models_and_a_fallback(
    models_dir: Path, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One run: YOLOX-nano (the baseline, first), Atto, and Atto where YOLOX finds nothing; the fallback
    finds every frame its first model finds, and runs the second model only where the first found nothing."""
    out = tmp_path / "recall.json"
    argv = [str(sequences_dir / "otb_Crossing"), str(sequences_dir / "uavdt_S1606"), "--model-dir"]
    argv += [str(models_dir), "--variants", "yolox,atto,yolox/atto", "--step", "25", "--json", str(out)]
    assert recall_main(argv) == 0
    table = capsys.readouterr().out
    assert "| yolox |" in table and "| yolox/atto |" in table and "people <16 px" in table
    figures = json.loads(out.read_text())["variants"]
    yolox, atto, fallback = (figures[v] for v in ("yolox", "atto", "yolox/atto"))
    assert yolox["frames"] == atto["frames"] == fallback["frames"] == 9  # 5 + 4 frames, every 25th
    assert yolox["by_class"]["people"]["frames"] == 5 and yolox["by_class"]["vehicles"]["frames"] == 4
    assert yolox["recall"] <= fallback["recall"] <= yolox["recall"] + atto["recall"]
    assert recall_main([*argv[:4], "--variants", "yolox/atto/femto"]) == 2
    assert "one detector or a fallback" in capsys.readouterr().err
    assert recall_main([*argv[:4], "--variants", "nanodet"]) == 2
    assert "the model must be one of" in capsys.readouterr().err
