"""Whether a keyframe is lit well enough for the detection curve to say anything of it.

The detection curve (`behaviors.detection_curve`) is measured on daylight footage: the detector's chance of
finding a person there depends on size. In a dark keyframe it does not follow size at all (the dev set's
night scene, uavdt_S1301, mean luma 35-39: cars of 23-32 px proposed in 44 of 149 frames, none found, where
daylight cars of that size were found about three times in four), so the curve cannot judge it. A keyframe
whose mean luma (8-bit, Rec. 601 weights, as OpenCV's grey conversion) lies two stops or more under
mid-grey is "low light": the curve and the POD map claim nothing for it, and say so, rather than credit a
search the detector could not make.

Mid-grey is an 18 % reflectance, 118 in sRGB; two stops under it is 4.5 %, 60 in sRGB (the sRGB transfer
function). The rule is photographic (an exposure two stops under), not fitted: the dev set's other
sequences average 78-133, its night scene 35-39.
"""

from __future__ import annotations

MIN_MEAN_LUMA = 60.0  # two stops under mid-grey (see the module doc)


def too_dark(mean_luma: float) -> bool:
    """The keyframe is too dark for the detection curve (its mean luma under MIN_MEAN_LUMA)."""
    return mean_luma < MIN_MEAN_LUMA


def low_light_note(mean_luma: float, keyframes: int) -> str:
    """What the operator reads while keyframes are too dark: why the POD map claims nothing for them."""
    return (
        f"keyframes too dark for the detection curve (mean luma {mean_luma:.0f} < {MIN_MEAN_LUMA:.0f}, two "
        f"stops under mid-grey): the POD map claims nothing for them ({keyframes} so far)"
    )
