"""Prompt sets per model family, following the paper's strategy in our own words.

Strategy (CloudTrack, Blei et al. 2024): tell the model it supports a search-and-rescue team, that
missing a person is far worse than a false alarm ("if in doubt, rather say yes" - a human supervisor
checks every yes), and have it justify before answering so the answer follows from what it saw.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Family = Literal["gpt", "llava", "paligemma"]


@dataclass(frozen=True)
class PromptSet:
    family: Family
    system: str  # empty: the family takes no system message
    task: str  # format fields: {prompt}, {superset}


GPT = PromptSet(
    "gpt",
    system=(
        "You help a search-and-rescue team that flies drones to find missing people. You see small crops "
        "from a drone camera around objects a detector found. Overlooking the person we search for can cost "
        "a life, while a false alarm only costs a supervisor a glance: when the picture is small, blurred or "
        "ambiguous, lean towards yes."
    ),
    task=(
        "The crop shows a detected {superset} near its centre, with some surroundings. We are looking for: "
        '"{prompt}".\n'
        "First describe in one or two sentences what you can see of this {superset} that matters for the "
        "description (clothing colours, posture, surroundings). Then give your decision on a last line that "
        "reads exactly 'Answer: Yes' or 'Answer: No'. If in doubt, rather say Yes."
    ),
)

LLAVA = PromptSet(
    "llava",
    system="You assist drone search-and-rescue. Missing a person is worse than a false alarm.",
    task=(
        'Is this {superset} "{prompt}"? Say briefly what you see (colours, posture), then end with '
        "'Answer: Yes' or 'Answer: No'. If unsure, say Yes."
    ),
)

# PaliGemma is a single-turn model trained on "answer en ..." questions with one-word answers.
PALIGEMMA = PromptSet("paligemma", system="", task='answer en Is this {superset} "{prompt}"? yes or no')

PROMPT_SETS: dict[Family, PromptSet] = {"gpt": GPT, "llava": LLAVA, "paligemma": PALIGEMMA}


def family_for(model: str, configured: str = "auto") -> Family:
    """The prompt family from the configuration, or guessed from the model name."""
    for family in PROMPT_SETS:
        if configured == family:
            return family
    name = model.lower()
    if "paligemma" in name:
        return "paligemma"
    if "llava" in name or "bakllava" in name or "moondream" in name:
        return "llava"
    return "gpt"


def render(prompt_set: PromptSet, prompt: str, superset: str) -> tuple[str, str]:
    """(system, task) text for one verification; the description is quoted, never interpreted."""
    clean = " ".join(prompt.replace('"', "'").split())
    return prompt_set.system, prompt_set.task.format(prompt=clean, superset=superset)
