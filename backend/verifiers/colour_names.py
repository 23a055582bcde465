"""Colour names for garment pixels: nearest named prototype in CIE Lab by CIEDE2000 (colour-science).

Every name starts from one prototype, the sRGB centre of the basic colour term under daylight. The
labelled crop set adds a second prototype per name where it has garments of that single colour: the
median Lab of those garments' pixels as the aerial camera saw them (haze, shade and white balance pull
colours toward grey). `calibrate` makes that table; the verifier loads the stored one.
"""

from __future__ import annotations

import hashlib
import json
import threading
import warnings
from collections import OrderedDict
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path

import numpy as np

with warnings.catch_warnings():
    # colour-science announces at import that its SciPy-based features are off; the conversions and
    # CIEDE2000 used here need none of them, and the back-end does not install SciPy.
    warnings.filterwarnings("ignore", message='.*"SciPy" related API features are not available')
    import colour

# Basic colour terms, sRGB 0-255 centres (the verifier's vocabulary; the prompt's synonyms map onto it).
BASIC_SRGB: dict[str, tuple[int, int, int]] = {
    "black": (25, 25, 25), "white": (240, 240, 240), "gray": (128, 128, 128), "red": (200, 30, 35),
    "orange": (240, 130, 30), "yellow": (240, 220, 40), "green": (40, 150, 60), "blue": (40, 80, 200),
    "purple": (120, 50, 150), "pink": (240, 150, 180), "brown": (120, 75, 40),
}  # fmt: skip
DARK_L = 35.0  # "dark": CIE L* below this (between black at ~10 and mid grey at ~54)
PROTOTYPES_PATH = Path(__file__).with_name("colour_prototypes.json")
SHADE_AND_SUN = (0.35, 2.0)
ACHROMATIC = {"black", "white", "gray"}
MAX_PIXELS = 800  # pixels judged per region: an even subsample keeps a crop in a few ms
# Regions whose shares a namer remembers: CIEDE2000 against every prototype is ~10 ms a region, and one
# region is named again for each colour a prompt gives it and for each prompt a study judges it on.
SHARES_CACHE = 512


WHITE_PERCENTILE = 97.0  # of the crop's brightest channel per pixel: taken as the scene's white
WHITE_LEVEL = 0.8  # linear value that white is brought to (L* about 92)
MAX_GAIN = 4.0


def white_gains(crop_bgr: np.ndarray) -> np.ndarray:
    """One linear gain for all channels that brings the bright end of the crop to WHITE_LEVEL (exposure).

    An aerial camera's exposure changes from scene to scene and frame to frame; the brightest surfaces
    around the person (pavement, foam, road marking) are the reference. The same gain on every channel
    keeps hues: balancing each channel on its own turns a green shirt yellow on grass.
    """
    linear = np.asarray(
        colour.cctf_decoding(crop_bgr.reshape(-1, 3)[:, ::-1].astype(np.float64) / 255.0, function="sRGB")
    )
    white = float(np.percentile(linear.max(axis=1), WHITE_PERCENTILE))
    return np.full(3, np.clip(WHITE_LEVEL / max(white, 1e-6), 1.0 / MAX_GAIN, MAX_GAIN))


def srgb_to_lab(pixels_bgr: np.ndarray, gains: np.ndarray | None = None) -> np.ndarray:
    """N x 3 uint8 BGR -> N x 3 CIE Lab (D65), after per-channel linear `gains` (see `white_gains`)."""
    linear = np.asarray(colour.cctf_decoding(pixels_bgr[:, ::-1].astype(np.float64) / 255.0, function="sRGB"))
    if gains is not None:
        linear = np.clip(linear * gains, 0.0, 1.0)
    xyz = colour.RGB_to_XYZ(linear, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    return np.asarray(colour.XYZ_to_Lab(xyz))


def subsample(pixels: np.ndarray, limit: int = MAX_PIXELS) -> np.ndarray:
    if len(pixels) <= limit:
        return pixels
    return np.asarray(pixels[np.linspace(0, len(pixels) - 1, limit).astype(int)])


class ColourNamer:
    def __init__(self, prototypes: Mapping[str, Iterable[Iterable[float]]] | None = None) -> None:
        table = {name: [list(v) for v in rows] for name, rows in (prototypes or {}).items()}
        for name, rgb in BASIC_SRGB.items():
            basic = srgb_to_lab(np.array([rgb[::-1]], np.uint8))
            table.setdefault(name, []).insert(0, list(basic[0]))
            if name not in ACHROMATIC:
                # The same colour in shade and in full sun (linear intensity x0.35 and x2): a bright green
                # is nearer to basic yellow than to basic green in CIEDE2000, but people call it green.
                for gain in SHADE_AND_SUN:
                    shade = srgb_to_lab(np.array([rgb[::-1]], np.uint8), np.full(3, gain))[0]
                    table[name].append(list(shade))
        self.names = list(table)
        self._owner = np.array([i for i, name in enumerate(self.names) for _ in table[name]])
        self._labs = np.array([v for name in self.names for v in table[name]], np.float64)
        self._remembered: OrderedDict[bytes, dict[str, float]] = OrderedDict()
        self._lock = threading.Lock()

    @classmethod
    def load(cls, path: Path = PROTOTYPES_PATH) -> ColourNamer:
        """The shipped calibration (a missing file is an error: the basic prototypes alone do much worse)."""
        return cls(json.loads(path.read_text())["calibrated"])

    def prototype(self, name: str) -> np.ndarray:
        """The first (basic) prototype of a name."""
        return np.asarray(self._labs[self.names.index(name) == self._owner][0])

    def shares(self, lab: np.ndarray) -> dict[str, float]:
        """Share of pixels whose nearest prototype is each name, plus "dark" (L* < DARK_L)."""
        if len(lab) == 0:
            return {}
        pixels = np.ascontiguousarray(lab, np.float64)
        digest = hashlib.blake2b(repr(pixels.shape).encode(), digest_size=16)
        digest.update(pixels.tobytes())
        key = digest.digest()
        with self._lock:
            known = self._remembered.get(key)
            if known is not None:
                self._remembered.move_to_end(key)
                return dict(known)  # a copy: the caller may change it
        result = self._name_pixels(pixels)
        with self._lock:
            self._remembered[key] = result
            if len(self._remembered) > SHARES_CACHE:
                self._remembered.popitem(last=False)
        return dict(result)

    def _name_pixels(self, lab: np.ndarray) -> dict[str, float]:
        distance = np.asarray(colour.delta_E(lab[:, None, :], self._labs[None, :, :], method="CIE 2000"))
        nearest = self._owner[np.argmin(distance, axis=1)]
        counts = np.bincount(nearest, minlength=len(self.names)) / len(lab)
        result = {name: float(counts[i]) for i, name in enumerate(self.names)}
        result["dark"] = float(np.mean(lab[:, 0] < DARK_L))
        return result


LEVELS = 3  # calibrated prototypes per name: garments in shade, in between, in sun


def _assign(namer: ColourNamer, names: list[str], lab: np.ndarray) -> dict[str, np.ndarray]:
    """Each pixel to the nearest prototype among `names`' own (a striped shirt's colours)."""
    owners = np.isin(np.array(namer.names)[namer._owner], names)
    distance = np.asarray(colour.delta_E(lab[:, None, :], namer._labs[owners][None], method="CIE 2000"))
    nearest = np.array(namer.names)[namer._owner[owners]][np.argmin(distance, axis=1)]
    return {name: lab[nearest == name] for name in names}


MIN_CHROMA = 6.0  # a calibrated prototype of a chromatic name keeps some colour...
MAX_HUE_SHIFT_DEG = 70.0  # ...and roughly its hue: calibration moves lightness and saturation, not hue


MAX_ACHROMATIC_CHROMA = 10.0  # and a grey stays a grey (a grey-blue shirt's pixels are not all grey)


def _keeps_its_hue(name: str, lab: np.ndarray) -> bool:
    if name in ACHROMATIC:
        return bool(np.hypot(lab[1], lab[2]) <= MAX_ACHROMATIC_CHROMA)
    basic = srgb_to_lab(np.array([BASIC_SRGB[name][::-1]], np.uint8))[0]
    shift = abs(np.degrees(np.arctan2(lab[2], lab[1]) - np.arctan2(basic[2], basic[1])))
    return bool(np.hypot(lab[1], lab[2]) >= MIN_CHROMA and min(shift, 360 - shift) <= MAX_HUE_SHIFT_DEG)


def _prototypes(per_name: dict[str, list[np.ndarray]]) -> dict[str, list[list[float]]]:
    """Per name, the median garment colour of each lightness tercile (LEVELS prototypes)."""
    table = {}
    for name, rows in sorted(per_name.items()):
        ordered = sorted(rows, key=lambda v: float(v[0]))
        groups = [
            np.median(g, axis=0)
            for g in np.array_split(np.array(ordered), min(LEVELS, len(ordered)))
            if len(g)
        ]
        kept = [[round(float(v), 2) for v in g] for g in groups if _keeps_its_hue(name, g)]
        if kept:
            table[name] = kept
    return table


def calibrate(samples: Iterable[tuple[Collection[str], np.ndarray]]) -> dict[str, list[list[float]]]:
    """Calibrated prototypes per colour name from labelled garments (label set, Lab pixels).

    First the garments of one colour: each garment's median Lab. Then the garments of several colours (a
    green-and-white striped shirt): each pixel goes to the nearest prototype of its own colours (the
    basic ones and those from the first step), each colour's pixels give that garment's median. A name's
    garments are split by lightness into LEVELS groups, each group's median a prototype: the same shirt
    is darker in shade. Colours the set never shows keep the basic prototype only.
    """
    garments = [([n for n in labels if n in BASIC_SRGB], lab) for labels, lab in samples]
    garments = [(names, lab) for names, lab in garments if names and len(lab)]
    per_name: dict[str, list[np.ndarray]] = {}
    for names, lab in garments:
        if len(names) == 1:
            per_name.setdefault(names[0], []).append(np.median(lab, axis=0))
    first = ColourNamer(_prototypes(per_name))
    for names, lab in garments:
        if len(names) > 1:
            for name, mine in _assign(first, names, lab).items():
                if len(mine) >= max(5, 0.1 * len(lab)):  # a colour the garment really shows
                    per_name.setdefault(name, []).append(np.median(mine, axis=0))
    return _prototypes(per_name)
