"""Every COCO class reachable by its everyday words: the WordNet word table, plurals, the head-noun rule,
open-vocabulary routing and the nearest-class error (`pytest -k supersets`)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from backend.supersets import (
    COCO_CLASSES,
    SUPERSET_TO_COCO,
    VOCABULARY_FILE,
    UnknownSupersetError,
    coco_classes_for,
    superset_from_prompt,
    vocabulary,
)
from backend_tools.wordnet_vocabulary import WordNet, adjective_words, build, render
from tests.backend_fixtures import auth, backend_config, detect_parts, frame, jpeg

PROMPTS: list[tuple[str, str]] = [
    # people
    ("an injured man in a gray shirt", "person"),
    ("the woman in the red jacket", "person"),
    ("two men walking on the road", "person"),
    ("a group of women", "person"),
    ("the child near the river", "person"),
    ("lost children in the forest", "person"),
    ("a little boy with a blue cap", "person"),
    ("the girls on the bridge", "person"),
    ("a hiker with a large backpack", "person"),
    ("hikers on the ridge", "person"),
    ("a climber on the rock face", "person"),
    ("the swimmer in the lake", "person"),
    ("a surfer riding a wave", "person"),
    ("the wakeboarder behind the boat", "person"),
    ("a skier in a yellow suit", "person"),
    ("snowboarders on the slope", "person"),
    ("a runner in shorts", "person"),
    ("joggers in the park", "person"),
    ("a cyclist in a green jersey", "person"),
    ("a pedestrian crossing the road", "person"),
    ("the victim lying on the ground", "person"),
    ("casualties near the car", "person"),
    ("a survivor waving", "person"),
    ("a rescuer in orange", "person"),
    ("a firefighter", "person"),
    ("the policeman", "person"),
    ("a soldier", "person"),
    ("a fisherman on the pier", "person"),
    ("a lifeguard", "person"),
    ("the farmer in the field", "person"),
    ("an old lady", "person"),
    ("an elderly gentleman", "person"),
    ("a teenager", "person"),
    ("a toddler", "person"),
    ("a baby", "person"),
    ("someone lying next to a car", "person"),
    ("somebody in the water", "person"),
    ("people on the beach", "person"),
    ("a crowd of people", "person"),
    ("a person in a wheelchair", "person"),
    ("the kid on the skateboard", "person"),
    ("a horse rider", "person"),
    ("a dog walker", "person"),
    ("the bus driver", "person"),
    ("a young woman in a white dress", "person"),
    ("a kayaker", "person"),
    ("a paddler in a canoe", "person"),
    ("a rower", "person"),
    ("a skateboarder doing a trick", "person"),
    ("the tennis player", "person"),
    ("a motorcyclist", "person"),
    ("a mountain biker", "person"),
    ("a kitesurfer", "person"),
    ("the worker in a hard hat", "person"),
    ("a tourist with a camera", "person"),
    ("the referee", "person"),
    ("a student", "person"),
    ("a nurse", "person"),
    ("a doctor", "person"),
    ("a hunter in camouflage", "person"),
    ("a lone figure on the ridge", "person"),
    ("the subject was last seen near the lake", "person"),
    ("the injured lying near the car", "person"),
    ("a group of hikers", "person"),
    # vehicles
    ("a red car", "car"),
    ("cars in the parking lot", "car"),
    ("a white sedan", "car"),
    ("a black suv", "car"),
    ("a jeep on the dirt road", "car"),
    ("a taxi", "car"),
    ("an ambulance", "car"),
    ("a police car", "car"),
    ("a convertible", "car"),
    ("a station wagon", "car"),
    ("a truck", "truck"),
    ("trucks on the highway", "truck"),
    ("a pickup truck", "truck"),
    ("a fire engine", "truck"),
    ("a dump truck", "truck"),
    ("a tow truck", "truck"),
    ("a bus", "bus"),
    ("buses at the station", "bus"),
    ("a school bus", "bus"),
    ("a minibus", "bus"),
    ("a motorcycle", "motorbike"),
    ("motorbikes", "motorbike"),
    ("a scooter", "motorbike"),
    ("a quad bike", "motorbike"),
    ("a bicycle", "bicycle"),
    ("bikes on the rack", "bicycle"),
    ("a mountain bike", "bicycle"),
    ("a tandem", "bicycle"),
    ("a train", "train"),
    ("a freight train", "train"),
    ("a tractor in the field", "vehicle"),
    ("a white van", "vehicle"),
    ("a vehicle", "vehicle"),
    ("vehicles on the road", "vehicle"),
    ("a tank", "vehicle"),
    ("an airplane", "aeroplane"),
    ("a plane on the runway", "aeroplane"),
    ("a jet", "aeroplane"),
    ("a helicopter", "aircraft"),
    ("a glider", "aircraft"),
    # boats
    ("a red kayak near the shore", "boat"),
    ("kayaks on the beach", "boat"),
    ("a canoe", "boat"),
    ("canoes", "boat"),
    ("a sailboat", "boat"),
    ("a yacht", "boat"),
    ("yachts in the harbour", "boat"),
    ("a speedboat", "boat"),
    ("a motorboat", "boat"),
    ("a fishing boat", "boat"),
    ("a ferry", "boat"),
    ("ferries", "boat"),
    ("a rowboat", "boat"),
    ("a dinghy", "boat"),
    ("an inflatable dinghy", "boat"),
    ("a raft", "boat"),
    ("a life raft with two people", "boat"),
    ("a red life raft", "boat"),
    ("a lifeboat", "boat"),
    ("a ship", "boat"),
    ("a cargo ship", "boat"),
    ("a tugboat", "boat"),
    ("a trawler", "boat"),
    ("a catamaran", "boat"),
    ("a jet ski", "boat"),
    ("two jet skis", "boat"),
    ("a barge", "boat"),
    ("a pontoon", "boat"),
    ("a motor boat", "boat"),
    ("the white boat", "boat"),
    ("boats", "boat"),
    ("an orange kayak", "boat"),
    # animals
    ("a dog", "dog"),
    ("dogs in the yard", "dog"),
    ("a puppy", "dog"),
    ("a labrador retriever", "dog"),
    ("a german shepherd", "dog"),
    ("a poodle", "dog"),
    ("a cat", "cat"),
    ("kittens", "animal"),
    ("a kitten", "animal"),
    ("a horse", "horse"),
    ("horses in the field", "horse"),
    ("a pony", "horse"),
    ("a foal", "animal"),
    ("a sheep", "sheep"),
    ("a flock of sheep", "sheep"),
    ("a cow", "cow"),
    ("cows", "cow"),
    ("a bull", "cow"),
    ("cattle", "cow"),
    ("an ox", "cow"),
    ("oxen", "cow"),
    ("an elephant", "elephant"),
    ("elephants", "elephant"),
    ("a bear", "bear"),
    ("a grizzly", "bear"),
    ("a polar bear", "bear"),
    ("a zebra", "zebra"),
    ("zebras", "zebra"),
    ("a giraffe", "giraffe"),
    ("giraffes", "giraffe"),
    ("a bird", "bird"),
    ("birds", "bird"),
    ("a seagull", "bird"),
    ("geese on the lake", "bird"),
    ("a duck", "bird"),
    ("an eagle", "bird"),
    ("a swan", "bird"),
    ("a pigeon", "bird"),
    ("a chicken", "bird"),
    ("a deer in the field", "animal"),
    ("deer", "animal"),
    ("a herd of goats", "animal"),
    ("a moose", "animal"),
    ("a wolf", "animal"),
    ("wolves", "animal"),
    ("a fox", "animal"),
    ("a seal on the beach", "animal"),
    ("a whale", "animal"),
    ("a dolphin", "animal"),
    ("an animal", "animal"),
    ("animals", "animal"),
    ("a pig", "animal"),
    ("a donkey", "animal"),
    ("a tiger", "animal"),
    ("a lion", "animal"),
    ("a camel", "animal"),
    ("a rabbit", "animal"),
    ("mice", "mouse"),
    # sports gear and other COCO objects
    ("a surfboard", "surfboard"),
    ("surfboards", "surfboard"),
    ("a skateboard", "skateboard"),
    ("skis", "skis"),
    ("a pair of skis", "skis"),
    ("a snowboard", "snowboard"),
    ("a frisbee", "frisbee"),
    ("a kite", "kite"),
    ("kites on the beach", "kite"),
    ("a football", "sports ball"),
    ("a soccer ball", "sports ball"),
    ("a golf ball", "sports ball"),
    ("a tennis ball", "sports ball"),
    ("a baseball bat", "baseball bat"),
    ("a baseball glove", "baseball glove"),
    ("a tennis racket", "tennis racket"),
    ("a tennis racquet", "tennis racket"),
    ("a backpack", "backpack"),
    ("a rucksack", "backpack"),
    ("a knapsack", "backpack"),
    ("a handbag", "handbag"),
    ("a purse", "handbag"),
    ("a suitcase", "suitcase"),
    ("an umbrella", "umbrella"),
    ("umbrellas", "umbrella"),
    ("the white plastic bag on the ground", "bag"),
    ("a bottle", "bottle"),
    ("a bench", "bench"),
    ("a traffic light", "traffic light"),
    ("a fire hydrant", "fire hydrant"),
    ("a cell phone", "cell phone"),
    ("a mobile phone", "cell phone"),
    ("a laptop", "laptop"),
    ("a chair", "chair"),
    ("a couch", "sofa"),
    ("a teddy bear", "teddy bear"),
    ("an orange", "orange"),
    ("a potted plant", "pottedplant"),
    ("a dining table", "diningtable"),
    ("a television", "tvmonitor"),
]


def test_supersets_table_has_people_vehicles_boats_animals_and_gear() -> None:
    targets = [t for _, t in PROMPTS]
    assert len(PROMPTS) >= 150
    assert targets.count("person") >= 30 and targets.count("boat") >= 25
    assert sum(t in SUPERSET_TO_COCO["animal"] or t == "animal" for t in targets) >= 30


@pytest.mark.parametrize(("prompt", "target"), PROMPTS)
def test_supersets_prompt_names_its_class(prompt: str, target: str) -> None:
    assert superset_from_prompt(prompt) == target
    assert coco_classes_for(target)  # every answer is something YOLOX can look for


def test_supersets_every_coco_class_is_reachable_by_its_name_and_plural() -> None:
    for name in COCO_CLASSES:
        spoken = {
            "motorbike": "motorbike",
            "aeroplane": "aeroplane",
            "pottedplant": "potted plant",
            "diningtable": "dining table",
            "tvmonitor": "television",
            "sports ball": "ball",
        }.get(name, name)
        assert name in coco_classes_for(spoken), name
        plural = spoken if spoken.endswith("s") else spoken + ("es" if spoken.endswith(("sh", "ch")) else "s")
        assert name in coco_classes_for(superset_from_prompt(f"two {plural} near the road") or ""), plural


def test_supersets_user_given_superset_takes_any_word_for_a_class() -> None:
    assert coco_classes_for("Kayaks") == ("boat",)
    assert coco_classes_for("deer") == SUPERSET_TO_COCO["animal"]
    assert coco_classes_for("lorries") == SUPERSET_TO_COCO["vehicle"] or "truck" in coco_classes_for(
        "lorries"
    )
    assert coco_classes_for("Truck") == ("truck", "car")


def test_supersets_unmapped_prompt_gives_its_head_phrase_and_the_error_names_nearest_classes() -> None:
    assert superset_from_prompt("a life buoy floating near the rocks") == "life buoy"
    assert superset_from_prompt("a life buoy next to a man") == "life buoy"  # the head, not a later noun
    assert superset_from_prompt("the one in the red kayak") == "boat"  # a head with no noun: the rest decides
    assert superset_from_prompt("the the of") is None
    with pytest.raises(UnknownSupersetError, match=r"'kayk'.*nearest known classes: boat"):
        coco_classes_for("kayk")
    with pytest.raises(UnknownSupersetError, match=r"'sailbaot'.*nearest known classes: boat"):
        coco_classes_for("sailbaot")


def test_supersets_head_noun_rules() -> None:
    assert superset_from_prompt("an orange kayak") == "boat"  # colour word before a noun
    assert superset_from_prompt("an orange on the table") == "orange"
    assert superset_from_prompt("a horse rider") == "person"  # the compound's last noun is its head
    assert superset_from_prompt("a red life raft with two people") == "boat"  # the head phrase first
    assert superset_from_prompt("a man next to a car") == "person"


def test_supersets_table_loads_once_and_maps_fast() -> None:
    vocab = vocabulary()
    assert vocabulary() is vocab and len(vocab.words) > 15_000
    start = time.perf_counter()
    for _ in range(200):
        superset_from_prompt("an injured hiker in a gray shirt lying on the ground near a red car")
    per_prompt = (time.perf_counter() - start) / 200
    print(f"superset_from_prompt: {per_prompt * 1e6:.0f} us per prompt")


def test_supersets_committed_table_is_what_wordnet_gives() -> None:
    # Debian's wordnet-base (installed by `make test`); regenerate: `python -m backend_tools.wordnet_vocabulary`.
    wordnet = WordNet.read(Path("/usr/share/wordnet"))
    table = build(wordnet)
    assert render(table, adjective_words(wordnet, table)) == VOCABULARY_FILE.read_text(encoding="utf-8")


def test_supersets_closed_set_server_answers_422_naming_the_nearest_classes(
    models_dir: Path, sequences_dir: Path
) -> None:
    with TestClient(create_app(backend_config(models_dir))) as client:
        keyframe = jpeg(frame(sequences_dir, size=(320, 180)))
        response = client.post(
            "/v1/detect", headers=auth(), **detect_parts(keyframe, prompt="a sailbaot near the rocks")
        )
        assert response.status_code == 422 and "nearest known classes: boat" in response.text
        response = client.post(
            "/v1/detect", headers=auth(), **detect_parts(keyframe, prompt="a yacht near the rocks")
        )
        assert response.status_code == 200 and response.json()["superset"] == "boat"


@pytest.mark.slow  # torch and transformers (about 9 s to import), like test_backend_open_vocabulary
def test_supersets_unmapped_prompt_goes_to_the_open_vocabulary_detector(
    models_dir: Path, sequences_dir: Path
) -> None:
    """YOLOX answers what it maps; a prompt naming no COCO class goes to the configured open-vocabulary model."""
    from backend.detectors.open_vocabulary import OpenVocabularyDetector
    from backend.detectors.routing import RoutingDetector
    from backend.detectors.yolox import YoloxDetector
    from tests.test_backend_open_vocabulary import tiny_owlv2

    model, processor = tiny_owlv2()
    owlv2 = OpenVocabularyDetector("owlv2", model, processor, score_threshold=0.05)
    routing = RoutingDetector(YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1), owlv2)
    app = create_app(backend_config(models_dir, 'detector.open_vocabulary="owlv2"'), detector=routing)
    with TestClient(app) as client:
        keyframe = jpeg(frame(sequences_dir, size=(640, 360)))
        parts = detect_parts(keyframe, prompt="an orange life buoy near the rocks")
        response = client.post("/v1/detect", headers=auth(), **parts)
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["superset"] == "orange life buoy" and body["candidates"]
        assert all(c["label"] == "orange life buoy" for c in body["candidates"])
        response = client.post(
            "/v1/detect", headers=auth(), **detect_parts(keyframe, prompt="a man in a gray shirt")
        )
        assert response.status_code == 200, response.text
        body = response.json()  # the walker in uav123_person12_1, found by YOLOX
        assert body["superset"] == "person" and body["candidates"]
        assert all(c["label"] == "person" for c in body["candidates"])


@pytest.mark.slow  # torch and transformers (about 9 s to import), like test_backend_open_vocabulary
def test_supersets_factory_pairs_yolox_with_the_open_vocabulary_detector(
    models_dir: Path, tmp_path: Path
) -> None:
    from backend.config import DetectorConfig
    from backend.detectors.factory import build_detector
    from backend.detectors.routing import RoutingDetector
    from tests.test_backend_open_vocabulary import tiny_owlv2

    model, processor = tiny_owlv2()
    model.save_pretrained(tmp_path / "owlv2-tiny")  # type: ignore[attr-defined]
    processor.save_pretrained(tmp_path / "owlv2-tiny")  # type: ignore[attr-defined]
    config = DetectorConfig(
        model_dir=str(models_dir), open_vocabulary="owlv2", hf_model=str(tmp_path / "owlv2-tiny")
    )
    detector = build_detector(config)
    assert isinstance(detector, RoutingDetector)
    assert detector.name == f"yolox_nano+owlv2:{tmp_path / 'owlv2-tiny'}"


@pytest.mark.parametrize(
    ("prompt", "superset", "words"),
    [
        (
            "an orange life buoy",
            "person",
            "the prompt's 'orange life buoy' is no person (nor any COCO class)",
        ),
        ("a red kayak", "person", "the prompt names a boat, not a person"),
        ("a man in a kayak", "boat", "--superset person searches for a person"),
        ("a person in a green shirt", "person", None),
        ("injured man in a gray shirt lying on the ground", "person", None),
        ("a white van", "car", None),  # a van is a vehicle, of which car is one class
        ("an orange life buoy", "life buoy", None),  # an unmapped superset: the detector's own question
    ],
)
def test_supersets_prompt_outside_the_given_superset_is_warned_of(
    prompt: str, superset: str, words: str | None
) -> None:
    from backend.supersets import prompt_outside_superset

    warning = prompt_outside_superset(prompt, superset)
    if words is None:
        assert warning is None
    else:
        assert warning is not None and words in warning and len(warning) <= 200, warning
