"""The synthetic world the simulated camera looks at: textured ground, walking people, vehicles, occluders.

Coordinates are local NED in metres (north, east, down) with the ground at down = 0, the same frame as the
autopilot's LOCAL_POSITION_NED. Everything is a pure function of the seed and the time, so two runs with
the same seed see the same world at the same instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Pose = Literal["standing", "sitting", "lying"]
Colour = tuple[int, int, int]  # BGR, as OpenCV draws

# Clothing colours a verifier can name; hue well apart so a colour check on pixels can tell them apart.
CLOTHING: dict[str, Colour] = {
    "green": (40, 170, 40),
    "red": (40, 40, 200),
    "blue": (200, 90, 30),
    "yellow": (30, 210, 230),
    "orange": (20, 120, 240),
    "purple": (150, 40, 130),
    "white": (235, 235, 235),
    "black": (30, 30, 30),
    "gray": (128, 128, 128),
}


@dataclass(frozen=True)
class Person:
    """One person. Walking people follow `waypoints` (north, east) at `speed`, then stand still.

    `start_s` delays the walk; with `loop` the path repeats from the first waypoint.
    """

    person_id: str
    shirt: str
    trousers: str = "black"
    pose: Pose = "standing"
    waypoints: tuple[tuple[float, float], ...] = ((0.0, 0.0),)
    speed: float = 0.0
    start_s: float = 0.0
    loop: bool = False

    @property
    def shirt_bgr(self) -> Colour:
        return CLOTHING[self.shirt]

    @property
    def trousers_bgr(self) -> Colour:
        return CLOTHING[self.trousers]

    def path_length(self) -> float:
        pts = self.waypoints
        return sum(math.dist(a, b) for a, b in zip(pts, pts[1:], strict=False))

    def state_at(self, t: float) -> tuple[float, float, float]:
        """(north, east, heading in radians) at time t."""
        pts = self.waypoints
        travelled = max(0.0, t - self.start_s) * self.speed
        total = self.path_length()
        if len(pts) == 1 or total <= 0:
            return pts[0][0], pts[0][1], 0.0
        if self.loop:
            closing = math.dist(pts[-1], pts[0])
            travelled %= total + closing
            pts = (*pts, pts[0])
        for a, b in zip(pts, pts[1:], strict=False):
            seg = math.dist(a, b)
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            if travelled <= seg or b is pts[-1]:
                f = min(1.0, travelled / seg) if seg > 0 else 1.0
                return a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), heading
            travelled -= seg
        return pts[-1][0], pts[-1][1], 0.0  # pragma: no cover - loop above always returns

    def velocity_at(self, t: float, dt: float = 0.05) -> tuple[float, float]:
        n0, e0, _ = self.state_at(t)
        n1, e1, _ = self.state_at(t + dt)
        return (n1 - n0) / dt, (e1 - e0) / dt


@dataclass(frozen=True)
class Block:
    """A solid axis-aligned box: a parked vehicle or an occluder (a roof is a box raised off the ground)."""

    kind: Literal["vehicle", "occluder"]
    north: float
    east: float
    length: float  # along north
    width: float  # along east
    height: float
    base: float = 0.0  # metres above the ground of the underside (a roof on poles)
    colour: Colour = (90, 90, 90)

    def corners(self) -> np.ndarray:
        """The eight corners as an (8, 3) NED array."""
        n0, n1 = self.north - self.length / 2, self.north + self.length / 2
        e0, e1 = self.east - self.width / 2, self.east + self.width / 2
        d0, d1 = -self.base, -(self.base + self.height)
        return np.array(
            [[n, e, d] for d in (d0, d1) for n, e in ((n0, e0), (n1, e0), (n1, e1), (n0, e1))],
            dtype=np.float64,
        )


@dataclass(frozen=True)
class World:
    seed: int
    people: tuple[Person, ...]
    blocks: tuple[Block, ...] = ()
    ground_size_m: float = 400.0
    ground_px: int = 2048
    target_id: str = ""
    extras: dict[str, str] = field(default_factory=dict)

    def person(self, person_id: str) -> Person:
        for p in self.people:
            if p.person_id == person_id:
                return p
        raise KeyError(person_id)


def ground_texture(seed: int, size_px: int) -> np.ndarray:
    """A grass-and-dirt texture (BGR): multi-scale noise, a few dirt patches and paths. Deterministic."""
    import cv2

    rng = np.random.default_rng(seed)
    base = np.zeros((size_px, size_px), np.float32)
    for scale, weight in ((8, 0.5), (32, 0.3), (128, 0.2)):
        small = rng.random((max(2, size_px // scale), max(2, size_px // scale))).astype(np.float32)
        base += weight * cv2.resize(small, (size_px, size_px), interpolation=cv2.INTER_CUBIC)
    fine = rng.random((size_px, size_px)).astype(np.float32)
    base = np.clip(0.75 * base + 0.25 * fine, 0, 1)
    # Dry grass: saturation below what a colour check calls chromatic, so the ground never reads as a
    # green (or any other) shirt and only clothing carries colour.
    grass = np.array([98, 112, 118], np.float32)
    dirt = np.array([70, 105, 135], np.float32)
    dirt_mask = np.zeros((size_px, size_px), np.float32)
    for _ in range(40):
        c = (int(rng.integers(0, size_px)), int(rng.integers(0, size_px)))
        axes = (int(rng.integers(10, 80)), int(rng.integers(10, 80)))
        cv2.ellipse(dirt_mask, c, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
    for _ in range(6):  # footpaths
        p0 = (int(rng.integers(0, size_px)), int(rng.integers(0, size_px)))
        p1 = (int(rng.integers(0, size_px)), int(rng.integers(0, size_px)))
        cv2.line(dirt_mask, p0, p1, 1.0, int(rng.integers(4, 10)))
    blurred = np.asarray(cv2.GaussianBlur(dirt_mask, (0, 0), 3), np.float32)[..., None]
    shade = (0.6 + 0.8 * base)[..., None]
    colour = (grass * (1 - blurred) + dirt * blurred) * shade
    return np.asarray(np.clip(colour, 0, 255), np.uint8)


def distractor_world(
    seed: int,
    target_shirt: str = "green",
    distractor_shirts: tuple[str, ...] = ("red", "blue", "purple"),
    target_speed: float = 1.5,
    target_start: tuple[float, float] = (20.0, 0.0),
    heading_deg: float = 0.0,
    walk_m: float = 60.0,
    occluder_at_m: float | None = None,
    vehicles: int = 2,
    turn_at_m: float = 20.0,
    turn_deg: float = 40.0,
) -> World:
    """A target walking from `target_start` along `heading_deg`, turning by `turn_deg` after `turn_at_m`.

    Distractors wear other colours.

    Distractors stand, sit or lie 4-12 m beside the start, so they are in the first frames with the target.
    With `occluder_at_m` a roof 5 m long spans the target's path that far along it (hidden about 3 s).
    """
    rng = np.random.default_rng(seed)
    h = math.radians(heading_deg)
    fwd = (math.cos(h), math.sin(h))
    side = (-math.sin(h), math.cos(h))
    n0, e0 = target_start
    bend = (n0 + turn_at_m * fwd[0], e0 + turn_at_m * fwd[1])
    h2 = h + math.radians(turn_deg)
    rest = max(0.0, walk_m - turn_at_m)
    end = (bend[0] + rest * math.cos(h2), bend[1] + rest * math.sin(h2))
    people = [Person("target", target_shirt, "black", "standing", ((n0, e0), bend, end), target_speed)]
    poses: tuple[Pose, ...] = ("standing", "sitting", "lying")
    for i, shirt in enumerate(distractor_shirts):
        lateral = (1 if i % 2 == 0 else -1) * float(rng.uniform(4.0, 9.0))
        along = float(rng.uniform(-3.0, 8.0))
        pos = (n0 + along * fwd[0] + lateral * side[0], e0 + along * fwd[1] + lateral * side[1])
        pose = poses[i % len(poses)]
        if pose == "standing":  # a standing distractor strolls back and forth
            other = (pos[0] + 3.0 * side[0], pos[1] + 3.0 * side[1])
            people.append(Person(f"person-{i + 1}", shirt, "blue", pose, (pos, other), 0.6, loop=True))
        else:
            people.append(Person(f"person-{i + 1}", shirt, "gray", pose, (pos,)))
    blocks: list[Block] = []
    for i in range(vehicles):
        along = float(rng.uniform(10.0, walk_m))
        lateral = (1 if i % 2 else -1) * float(rng.uniform(7.0, 14.0))
        colour = ((60, 60, 180), (170, 170, 170), (140, 80, 40))[i % 3]
        blocks.append(
            Block(
                "vehicle",
                n0 + along * fwd[0] + lateral * side[0],
                e0 + along * fwd[1] + lateral * side[1],
                4.5,
                1.9,
                1.5,
                colour=colour,
            )
        )
    if occluder_at_m is not None:
        cn, ce = n0 + occluder_at_m * fwd[0], e0 + occluder_at_m * fwd[1]
        along_n = abs(fwd[0]) > abs(fwd[1])
        blocks.append(
            Block(
                "occluder",
                cn,
                ce,
                5.0 if along_n else 8.0,
                8.0 if along_n else 5.0,
                0.4,
                base=2.6,
                colour=(70, 75, 95),
            )
        )
    return World(seed, tuple(people), tuple(blocks), target_id="target")


# The search scenario's area: a survey of 100 m (north) x 60 m (east) whose south edge lies 10 m north of
# the vehicle's home. Nobody stands within 55 m of home, beyond the camera's view from there (pitch -40 deg
# at 10 m sees the ground out to 45 m), so only a survey finds them. Home lies 2 m west of the area's middle:
# the planner begins at the lane end nearest the vehicle, and from the very middle that was a tie the
# take-off's drift decided (the real PX4 drifted 0.6 m east and flew the east lane first in some flights).
SEARCH_AREA_NE = ((10.0, -28.0), (110.0, 32.0))  # south-west and north-east corners (north, east), metres


Place = Literal["fixed", "random"]
SEARCH_CARS = (
    Block("vehicle", 95.0, 20.0, 4.5, 1.9, 1.5, colour=(60, 60, 180)),
    Block("vehicle", 30.0, -22.0, 4.5, 1.9, 1.5, colour=(170, 170, 170)),
)
# Random placement (`--place random`): nobody nearer the area's edge than this (the whole body inside the
# area and its POD map), nobody nearer another person than PEOPLE_APART_M (two people a look-alike's width
# apart would be one detection), nor nearer a parked car's centre than CAR_CLEAR_M (not under or in it).
EDGE_MARGIN_M = 1.5
PEOPLE_APART_M = 5.0
CAR_CLEAR_M = 5.0
RANDOM_POSTURES: tuple[Pose, ...] = ("standing", "lying")


def search_world(seed: int, lookalike_beside: bool = False, place: Place = "fixed") -> World:
    """The search scenario's world, the people where the scenario puts them (`place` "fixed") or anywhere in
    the area (`place` "random": `random_search_world`)."""
    if place == "random":
        return random_search_world(seed)
    return fixed_search_world(seed, lookalike_beside)


def random_search_world(
    seed: int, area_ne: tuple[tuple[float, float], tuple[float, float]] = SEARCH_AREA_NE
) -> World:
    """The search world's people placed anywhere in `area_ne` (uniformly, seeded), each standing still or
    lying at a random heading: the described person (green shirt, black trousers), the look-alike (green
    shirt, blue trousers) and three others in red, blue and purple. The parked cars stay where they are.
    `extras` records the place and the described person's posture (the run's JSON reports them)."""
    rng = np.random.default_rng([seed, 42])  # apart from the ground texture's stream of the same seed
    (s_n, w_e), (n_n, e_e) = area_ne
    dressed = (
        ("target", "green", "black"),
        ("decoy", "green", "blue"),
        ("person-1", "red", "gray"),
        ("person-2", "blue", "gray"),
        ("person-3", "purple", "gray"),
    )
    spots: list[tuple[float, float]] = []
    people: list[Person] = []
    for person_id, shirt, trousers in dressed:
        while True:
            spot = (
                float(rng.uniform(s_n + EDGE_MARGIN_M, n_n - EDGE_MARGIN_M)),
                float(rng.uniform(w_e + EDGE_MARGIN_M, e_e - EDGE_MARGIN_M)),
            )
            clear_of_cars = all(math.dist(spot, (b.north, b.east)) >= CAR_CLEAR_M for b in SEARCH_CARS)
            if clear_of_cars and all(math.dist(spot, other) >= PEOPLE_APART_M for other in spots):
                break
        spots.append(spot)
        pose = RANDOM_POSTURES[int(rng.integers(len(RANDOM_POSTURES)))]
        heading = float(rng.uniform(0.0, 2.0 * math.pi))
        # Still (speed 0): a second point 1 cm away only gives a lying body its heading.
        toward = (spot[0] + 0.01 * math.cos(heading), spot[1] + 0.01 * math.sin(heading))
        people.append(Person(person_id, shirt, trousers, pose, (spot, toward)))
    target = people[0]
    extras = {"place": "random", "target_posture": target.pose}
    return World(seed, tuple(people), SEARCH_CARS, target_id="target", extras=extras)


def fixed_search_world(seed: int, lookalike_beside: bool = False) -> World:
    """The search scenario's world: across the area, the described person (green shirt, black trousers,
    strolling slowly on the spot), a look-alike (green shirt, blue trousers, standing) the supervisor must
    reject, and people of the same class in other colours, lying, sitting and walking. With the scenario's
    survey (lanes 20 m apart at east -18, 2 and 22, the first, nearest home, flown north) the look-alike and,
    30 m further on, the described person lie close enough to the first lane to be judged (the local verifier
    judges a rendered person out to about 12 m from 10 m up), so the look-alike is met first; the find comes
    early in the survey to keep the flight short for CI. `lookalike_beside`: the look-alike stands 6 m short
    of the described person instead, so the survey sees both at once, the look-alike first.
    """
    decoy_at = (84.0, -17.0) if lookalike_beside else (60.0, -16.0)
    people = (
        Person("target", "green", "black", "standing", ((90.0, -15.0), (90.0, -12.0)), 0.4, loop=True),
        Person("decoy", "green", "blue", "standing", (decoy_at,)),
        Person("person-1", "red", "gray", "lying", ((45.0, 10.0),)),
        Person("person-2", "blue", "gray", "standing", ((106.0, -24.0), (106.0, -12.0)), 0.8, loop=True),
        Person("person-3", "purple", "gray", "sitting", ((58.0, 28.0),)),
    )
    return World(seed, people, SEARCH_CARS, target_id="target")
