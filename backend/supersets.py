"""Superset classes: what the detector looks for before the verifier checks the full description.

A superset is a broad class ("person", "vehicle", "boat") that the prompt's target belongs to. Closed-set
detectors (YOLOX, COCO-80) need it mapped to their own class names; open-vocabulary detectors take the
superset text as it is. An unmapped superset is an error, never a silent empty answer.
"""

from __future__ import annotations

import re

# The 80 COCO class names in YOLOX's output order (the names shipped beside the weights, coco.names).
COCO_CLASSES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorbike", "aeroplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "sofa", "pottedplant", "bed",
    "diningtable", "toilet", "tvmonitor", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip

# Superset name -> the COCO classes that make it up. Every COCO name also maps to itself.
SUPERSET_TO_COCO: dict[str, tuple[str, ...]] = {
    "person": ("person",),
    "vehicle": ("car", "truck", "bus", "motorbike", "bicycle"),
    "car": ("car", "truck"),  # a pick-up or van is often labelled truck by COCO detectors
    "boat": ("boat",),
    "animal": ("dog", "horse", "sheep", "cow", "cat", "bear", "bird"),
    "bag": ("backpack", "handbag", "suitcase"),
    "aircraft": ("aeroplane",),
}

# Words in a prompt that name a superset ("an injured man ..." -> person). Longest words first.
PROMPT_WORDS: dict[str, str] = {
    **{w: "person" for w in (
        "person", "people", "persons", "man", "men", "woman", "women", "child", "children", "kid", "boy",
        "girl", "human", "hiker", "climber", "skier", "swimmer", "surfer", "wakeboarder", "pedestrian",
        "runner", "cyclist", "victim", "casualty", "survivor", "rescuer", "worker", "individual",
    )},
    **{w: "car" for w in ("car", "cars", "van", "suv", "jeep", "pickup")},
    **{w: "vehicle" for w in ("vehicle", "vehicles", "truck", "lorry", "bus", "motorbike", "motorcycle")},
    **{w: "boat" for w in ("boat", "boats", "kayak", "canoe", "dinghy", "raft", "ship", "sailboat")},
    **{w: "animal" for w in ("animal", "dog", "horse", "cow", "sheep", "deer")},
    **{w: "bag" for w in ("bag", "backpack", "rucksack", "suitcase", "handbag")},
}  # fmt: skip


class UnknownSupersetError(ValueError):
    """A superset the detector cannot map to its classes; the message lists what is known."""


def known_supersets() -> list[str]:
    return sorted(SUPERSET_TO_COCO)


def coco_classes_for(name: str) -> tuple[str, ...]:
    """The COCO classes a superset (or a COCO class name itself) stands for."""
    key = name.strip().lower()
    if key in SUPERSET_TO_COCO:
        return SUPERSET_TO_COCO[key]
    if key in COCO_CLASSES:
        return (key,)
    raise UnknownSupersetError(
        f"superset {name!r} has no COCO mapping; use one of {', '.join(known_supersets())} "
        "or a COCO class name (e.g. 'truck'), or an open-vocabulary detector (grounding_dino, owlv2)"
    )


def superset_from_prompt(prompt: str) -> str | None:
    """The superset a prompt names ("the man in a gray shirt" -> "person"), or None when it names none.

    The first matching word wins, so "a man next to a car" is a person search.
    """
    words: list[str] = re.findall(r"[a-z]+", prompt.lower())
    for word in words:
        if word in PROMPT_WORDS:
            return PROMPT_WORDS[word]
        if word in COCO_CLASSES:
            return word
    return None
