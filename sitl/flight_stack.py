"""What the scenario runner needs from a real SITL autopilot, so a scenario does not care which one flies it.

Two implement it: `sitl.arducopter_sitl.RealAutopilot` (the ArduCopter binary) and `sitl.px4_sitl.RealPx4`
(PX4 with SIH). The pilot's and the GCS's actions (arming, take-off, mode changes, the radio, a "fly to")
go over the autopilot's GCS link as a person would make them; the companion's link passes through a
`CompanionBridge` that records its setpoints. `start_flight_stack` picks one by name.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from sitl.camera_render import VehiclePose
from sitl.companion_bridge import BridgedSetpoint, CompanionBridge

REAL_AUTOPILOTS = ("arducopter", "px4-sitl")


class PoseSource(Protocol):
    """Where the camera renders from (started by the flight stack, stopped by the runner)."""

    def pose(self) -> VehiclePose: ...

    def stop(self) -> None: ...


class FlightStack(Protocol):
    name: str  # "arducopter" | "px4-sitl"
    system_id: int  # the MAVLink system id the companion and the GCS address
    offboard_mode: str  # the mode in which it flies the companion's setpoints (GUIDED / OFFBOARD)
    takeover_mode: str  # the mode a pilot's takeover selects, from the GCS or the radio
    bridge: CompanionBridge
    gcs: Any  # sitl.scenarios.ScriptedGcs on the autopilot's GCS link
    mode_history: list[tuple[float, str, str]]  # (monotonic time, mode, who): the pilot's requests

    @property
    def setpoints(self) -> list[BridgedSetpoint]: ...

    def camera_pose(self, origin: tuple[float, float]) -> PoseSource:
        """The pose the camera renders, in world coordinates (the vehicle's home lies at `origin`)."""
        ...

    def mode_name(self) -> str:
        """The mode the autopilot's last HEARTBEAT on the GCS link reported."""
        ...

    def mode_of(self, custom_mode: int | None) -> str:
        """A HEARTBEAT.custom_mode's name."""
        ...

    def custom_mode(self, name: str) -> int:
        """HEARTBEAT.custom_mode of a mode name (to find when the autopilot reported it)."""
        ...

    def set_mode(self, name: str, source: str = "pilot") -> bool: ...

    def rc_takeover(self) -> None:
        """The pilot takes over with the radio (ArduCopter: the mode switch; PX4: the sticks)."""
        ...

    def gcs_fly_to(self, north: float, east: float, down: float) -> None:
        """The GCS sends the vehicle to a point (metres from its home, NED), as "fly to here" does."""
        ...

    def set_link_down(self, name: str, down: bool) -> None: ...

    def ground_url(self) -> str:
        """Where a second ground station (the operator's laptop: `cloudtrack-gcs survey`) connects."""
        ...

    def fly_up(
        self, height_m: float, timeout_s: float = 90.0, progress: Callable[[str], None] = print
    ) -> float:
        """Arm and take off as the pilot would; the seconds it took."""
        ...

    def reuse(self, companion_port: int | None) -> None:
        """A vehicle a scenario has used, for the next one: the companion's link recorded afresh. Only PX4 is
        shared between runs; ArduCopter starts afresh each time."""
        ...

    def return_home(self, height_m: float, progress: Callable[[str], None] = print) -> float:
        """After `reuse`: back over home, facing north, hovering at `height_m`; the seconds it took."""
        ...

    def describe(self) -> str: ...

    def close(self) -> None: ...


def start_flight_stack(
    name: str,
    executable: Path,
    work_dir: Path,
    home: tuple[float, float, float],
    companion_port: int | None,
    speedup: float = 1.0,
    extra_params: dict[str, float] | None = None,
    system_id: int = 1,
) -> FlightStack:
    """Start `name` ("arducopter": `executable` is the binary; "px4-sitl": the package directory) and its GCS.
    `system_id`: ArduCopter's SYSID_THISMAV (PX4 takes its instance's, N+1)."""
    if name == "arducopter":
        from sitl.arducopter_sitl import start_arducopter

        return start_arducopter(executable, work_dir, home, companion_port, speedup, extra_params, system_id)
    if name == "px4-sitl":
        from sitl.px4_sitl import start_px4

        return start_px4(executable, work_dir, home, companion_port, extra_params)
    raise ValueError(f"unknown real autopilot {name!r}; use one of {REAL_AUTOPILOTS}")


def find_flight_stack(name: str, override: Path | None = None) -> Path:
    """Where `name`'s binary or package is; an error that says where to put it (never the mock instead)."""
    if name == "arducopter":
        from sitl.arducopter_sitl import find_binary

        return find_binary(override)
    if name == "px4-sitl":
        from sitl.px4_sitl import find_package

        return find_package(override)
    raise ValueError(f"unknown real autopilot {name!r}; use one of {REAL_AUTOPILOTS}")
