"""A batch of search runs over seeds (`cloudtrack-sim run search --place random --seeds 1-20`): does the POD
map the companion reported predict the finds?

Each seed places the people anew and flies the survey to its end; per seed: found or not, the map's POD
where the described person was (`pod_at_target`) and the time to the find. Over the seeds: the mean
`pod_at_target` against the share found (a calibrated map has them equal, within what 20 coin flips
allow), and the mean POD of the persons found against those missed (a map that knows where it looked well
gives the found ones more). Runs that could not be scored (no POD map, the survey not flown) are listed and
left out of the figures.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any

MAX_SEEDS = 200
SEEDS_TEXT = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*$")


def parse_seeds(text: str) -> list[int]:
    """ "1-20", "3", "1,4,9-12" as a list of seeds in the order given; ValueError with one line otherwise."""
    compact = text.replace(" ", "")
    if not SEEDS_TEXT.match(compact):
        raise ValueError(f"--seeds takes N, N-M or a comma list of them, not {text[:40]!r}")
    seeds: list[int] = []
    for part in compact.split(","):
        first, _, last = part.partition("-")
        low, high = int(first), int(last or first)
        if high < low or high - low + len(seeds) >= MAX_SEEDS:
            raise ValueError(f"--seeds: {part} is not a range of at most {MAX_SEEDS} seeds")
        seeds += range(low, high + 1)
    return list(dict.fromkeys(seeds))


def seed_line(result: dict[str, Any]) -> dict[str, Any]:
    """One run's figures for the batch (its first vehicle)."""
    m: dict[str, Any] = next(iter(result.get("vehicles", {}).values()), {})
    return {
        "seed": result.get("seed"),
        "outcome": result.get("outcome"),
        "found": bool(m.get("found")),
        "pod_at_target": m.get("pod_at_target"),
        "time_to_find_s": m.get("time_to_find_s"),
        "posture": (m.get("target") or {}).get("posture"),
        "target_ne": [(m.get("target") or {}).get("north"), (m.get("target") or {}).get("east")],
        "detector_pod_at_target": m.get("detector_pod_at_target"),
        "pod_mean": m.get("pod_mean"),
        "scored": m.get("pod_at_target") is not None and m.get("survey_completed_s") is not None,
        "failures": result.get("failures", []),
    }


def _mean(values: Sequence[float]) -> float | None:
    return round(sum(values) / len(values), 4) if values else None


def totals(lines: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The batch's figures over the scored runs."""
    scored = [x for x in lines if x["scored"]]
    pods = [float(x["pod_at_target"]) for x in scored]
    found = [float(x["pod_at_target"]) for x in scored if x["found"]]
    missed = [float(x["pod_at_target"]) for x in scored if not x["found"]]
    mean_pod = _mean(pods)
    rate = round(len(found) / len(scored), 4) if scored else None
    model = [float(x["detector_pod_at_target"]) for x in scored if x["detector_pod_at_target"] is not None]
    return {
        "runs": len(lines),
        "scored": len(scored),
        "not_scored": [x["seed"] for x in lines if not x["scored"]],
        "found": len(found),
        "mean_pod_at_target": mean_pod,
        "find_rate": rate,
        "difference": None if mean_pod is None or rate is None else round(mean_pod - rate, 4),
        "mean_pod_found": _mean(found),
        "mean_pod_missed": _mean(missed),
        # The detector's own account of its looks at the person (its passes' best looks): the model's POD.
        "mean_detector_pod_at_target": _mean(model),
    }


def run_batch(
    run_one: Callable[[int], dict[str, Any]], seeds: Sequence[int], progress: Callable[[str], None] = print
) -> dict[str, Any]:
    """`run_one(seed)` for each seed in turn (a run that could not start counts as not scored)."""
    lines: list[dict[str, Any]] = []
    results: list[dict[str, Any]] = []
    for seed in seeds:
        try:
            result = run_one(seed)
        except (RuntimeError, OSError) as exc:
            result = {"seed": seed, "outcome": "error", "failures": [f"could not run: {exc}"], "vehicles": {}}
        results.append(result)
        line = seed_line(result)
        lines.append(line)
        progress(format_line(line))
    return {"seeds": list(seeds), "runs": lines, "totals": totals(lines), "results": results}


def format_line(line: dict[str, Any]) -> str:
    pod = line["pod_at_target"]
    took = line["time_to_find_s"]
    return (
        f"seed {line['seed']:>3}: {'FOUND ' if line['found'] else 'missed'} "
        f"pod_at_target {'-' if pod is None else f'{pod:.2f}'} "
        f"time to find {'-' if took is None else f'{took:.1f} s'} ({line['posture']}, {line['outcome']})"
    )


def format_totals(t: dict[str, Any]) -> str:
    def num(x: float | None) -> str:
        return "-" if x is None else f"{x:.3f}"

    return (
        f"{t['scored']} of {t['runs']} runs scored: found {t['found']}, find rate {num(t['find_rate'])}, "
        f"mean pod_at_target {num(t['mean_pod_at_target'])}, difference {num(t['difference'])}; mean POD "
        f"found {num(t['mean_pod_found'])}, missed {num(t['mean_pod_missed'])} (the detector's own "
        f"{num(t['mean_detector_pod_at_target'])})"
    )
