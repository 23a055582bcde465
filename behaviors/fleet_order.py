"""What one vehicle of a fleet mission does when the back-end orders it to after another vehicle's find.

The mission's `on_find` (set once at its start: `cloudtrack-gcs start --on-find`) says what the other
vehicles do once the supervisor confirmed a find: "continue" searching, "hold" where they are, or "return"
to launch; the vehicle that found the person is always told to continue (it stays with the person). The
back-end answers each vehicle its order (GET /v1/missions/{m}/fleet); the companion acts on a new order
once:
- the GCS always hears it ("FLEET HOLD: found by drone-2", "... (pilot)" where the pilot is to act);
- where the mission start allowed the companion to command the vehicle (`allow_engage`), it ends its
  mission (as the GCS's abort: it lets go, the vehicle belongs to the pilot and the GCS) and requests the
  autopilot's hold mode or RTL, which the pilot can always override;
- without that leave, it commands nothing: the line tells the pilot what the mission asks.
"""

from __future__ import annotations

from dataclasses import dataclass

from behaviors.actions import FlightMode
from behaviors.mission_commands import AbortMission

ORDERS = ("continue", "hold", "return")
ORDER_MODES = {"hold": FlightMode.LOITER, "return": FlightMode.RTL}


@dataclass(frozen=True)
class FleetResponse:
    message: str  # for the GCS (a STATUSTEXT: at most 50 characters)
    abort: AbortMission | None  # ends the companion's mission first (it lets go)
    mode: FlightMode | None  # then requested of the autopilot


def respond(order: str, found: str | None, allow_engage: bool) -> FleetResponse | None:
    """The response to the order the back-end gives (None: nothing to do, the search goes on). `found`:
    the confirmed find, "<vehicle>/<candidate>"."""
    if order not in ORDER_MODES or not found:
        return None
    finder = found.split("/", 1)[0][:18]  # the line fits a STATUSTEXT
    word = order.upper()
    if not allow_engage:
        return FleetResponse(f"FLEET {word}: found by {finder} (pilot)", None, None)
    return FleetResponse(
        f"FLEET {word}: found by {finder}",
        AbortMission(f"fleet {order}: found by {finder}"),
        ORDER_MODES[order],
    )
