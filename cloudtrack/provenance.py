"""Who decided on a candidate and through what, said the same way everywhere a decision or a find is shown
or exported: the supervisor page, the GeoJSON and KML downloads, the Cursor-on-Target remarks, the GCS line.

Three ways a decision comes about:
- "supervisor page": the supervisor pressed Confirm or Reject on the back-end's page;
- "back-end API": a client holding the supervisor token posted it to the back-end's decision endpoint;
- "GCS via the vehicle": an operator decided at the ground station over MAVLink and the vehicle reported
  it. The back-end has only the vehicle's word for it, so it stays labelled as the vehicle's report, with
  the name the vehicle gave, whatever that name says ("supervisor page" included).
"""

from __future__ import annotations

from typing import Literal

Via = Literal["supervisor page", "back-end API", "GCS via the vehicle"]
SUPERVISOR_VIA = ("supervisor page", "back-end API")  # what a supervisor's decision may come through
PAGE = "supervisor page"  # the operator name the page sends; a client naming no operator gets "supervisor"


def decided_via(source: str, via: str) -> Via:
    """The way a decision came about, from its `source` ("supervisor" or "vehicle") and its `via`."""
    if source == "vehicle":
        return "GCS via the vehicle"
    return "supervisor page" if via == "supervisor page" else "back-end API"


def decision_text(via: Via, operator: str, vehicle_id: str) -> str:
    """Who decided and through what, for a person ("confirmed by <this>")."""
    if via == "GCS via the vehicle":
        who = "the GCS operator" if operator in ("", "gcs") else f'"{operator}" at the GCS'
        return f"{who}, as reported by {vehicle_id}"
    if via == "supervisor page":
        return PAGE if operator in ("", PAGE) else f"{operator} on the {PAGE}"
    return f"{operator or 'the supervisor'} through the back-end API (supervisor token)"


def gcs_text(via: Via, operator: str) -> str:
    """The same for the vehicle's GCS line (`FOUND: ... (confirmed by <this>)`), short: a STATUSTEXT."""
    if via == "supervisor page":
        return PAGE if operator in ("", PAGE) else f"{operator} on {PAGE}"[:64]
    if via == "back-end API":
        return f"{operator or 'supervisor'} via back-end API"[:64]
    return operator or "gcs"
