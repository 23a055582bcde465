"""`--plot`: a top-down picture of where the drone(s) and the target went (matplotlib, no display)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from sitl.metrics import FrameSample, TimedEvent


def plot_trajectories(
    out: Path,
    tracks: Mapping[str, Sequence[FrameSample]],
    events: Mapping[str, Sequence[TimedEvent]],
    title: str,
    others: Mapping[str, Sequence[tuple[float, float]]] | None = None,
) -> Path:
    """Drone paths (one per vehicle), the target's path and markers for confirmation and safety events.

    East is x and north is y, as on a map. `others` are fixed positions worth showing (distractors).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    target_drawn = False
    for i, (vehicle, samples) in enumerate(tracks.items()):
        if not samples:
            continue
        colour = ("tab:blue", "tab:purple", "tab:cyan")[i % 3]
        ax.plot(
            [s.drone_east for s in samples],
            [s.drone_north for s in samples],
            color=colour,
            lw=2,
            label=f"drone {vehicle}",
        )
        ax.plot(samples[0].drone_east, samples[0].drone_north, "o", color=colour)
        if not target_drawn:
            ax.plot(
                [s.target_east for s in samples],
                [s.target_north for s in samples],
                color="tab:green",
                lw=2,
                ls="--",
                label="target (green shirt)",
            )
            ax.plot(samples[-1].target_east, samples[-1].target_north, "*", color="tab:green", ms=14)
            target_drawn = True
        by_time = sorted(samples, key=lambda s: s.t)
        for ev in events.get(vehicle, ()):
            if ev.kind not in ("confirmed", "hold", "mode_change", "link_lost", "backend_lost", "reject"):
                continue
            near = min(by_time, key=lambda s: abs(s.t - ev.t))
            ax.plot(near.drone_east, near.drone_north, "x" if ev.kind != "confirmed" else "D", color="k")
            ax.annotate(
                ev.kind,
                (near.drone_east, near.drone_north),
                fontsize=7,
                xytext=(4, 4),
                textcoords="offset points",
            )
    for label, points in (others or {}).items():
        ax.plot([p[1] for p in points], [p[0] for p in points], ".", color="gray", ms=6)
        if points:
            ax.annotate(label, (points[-1][1], points[-1][0]), fontsize=7, color="gray")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
