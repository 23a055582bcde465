"""One colour per vehicle of a mission, for every picture of a fleet (the exports, the page): the Okabe-Ito
palette (colour-blind safe), in an order that keeps the first vehicles apart on a map, its yellow last
(weak on light maps). Colours tell vehicles apart at a glance; the vehicle id always goes with them (every
feature and placemark is named with it), since a palette repeats past eight vehicles and not every reader
sees every colour.

A vehicle's colour is its place among the mission's vehicle ids, sorted: the same ids give the same colours
in every document.
"""

from __future__ import annotations

from collections.abc import Iterable

PALETTE: tuple[tuple[str, str], ...] = (
    ("#0072B2", "blue"),
    ("#E69F00", "orange"),
    ("#009E73", "green"),
    ("#CC79A7", "pink"),
    ("#56B4E9", "sky blue"),
    ("#D55E00", "vermillion"),
    ("#000000", "black"),
    ("#F0E442", "yellow"),
)


def vehicle_colours(vehicle_ids: Iterable[str]) -> dict[str, str]:
    """Each vehicle id's colour, "#RRGGBB" (the palette repeats past its eighth vehicle)."""
    return {v: PALETTE[i % len(PALETTE)][0] for i, v in enumerate(sorted(set(vehicle_ids)))}


def colour_name(colour: str) -> str:
    """A palette colour's word ("blue"), for a line of text; the colour itself for any other."""
    return next((name for hex_, name in PALETTE if hex_ == colour.upper()), colour)


def kml_colour(colour: str, alpha: int = 255) -> str:
    """A colour "#RRGGBB" as KML writes it: aabbggrr."""
    red, green, blue = colour[1:3], colour[3:5], colour[5:7]
    return f"{alpha:02x}{blue}{green}{red}".lower()
