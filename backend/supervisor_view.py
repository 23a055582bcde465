"""The supervisor page's view of the fleet: every vehicle's state and the candidate it awaits, with ages.

Built from the session store (the whole fleet, whichever replica answers); it remembers since when each
candidate waits, and forgets a candidate as soon as nobody waits on it, so it stays as small as the fleet.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from backend.schemas import CandidateView, LatLon, SupervisorSnapshot, VehicleView
from backend.sessions import SessionStore

_STATUS = {"confirm": "confirmed", "reject": "rejected"}


class SupervisorView:
    """Turns the session store into what the page shows, and remembers since when each candidate waits."""

    def __init__(self, store: SessionStore, clock: Callable[[], float] = time.time) -> None:
        self.store = store
        self._clock = clock
        self._first_seen: dict[tuple[str, str], float] = {}

    def snapshot(self) -> SupervisorSnapshot:
        now = self._clock()
        vehicles = []
        waiting: set[tuple[str, str]] = set()
        for status in self.store.statuses():
            candidates = []
            awaiting = status.awaiting
            if awaiting is not None:
                key = (status.vehicle_id, awaiting.candidate_id)
                waiting.add(key)
                first = self._first_seen.setdefault(key, min(now, status.updated_at))
                decided = [
                    d
                    for d in self.store.decisions(status.vehicle_id)
                    if d.candidate_id == awaiting.candidate_id
                ]
                candidates.append(
                    CandidateView(
                        id=awaiting.candidate_id,
                        verdict=awaiting.verdict,
                        justification=awaiting.justification,
                        position=LatLon(lat=awaiting.position[0], lon=awaiting.position[1])
                        if awaiting.position
                        else None,
                        box=awaiting.box,
                        age_s=round(max(0.0, now - first), 1),
                        crop_url=(
                            f"/supervisor/api/vehicles/{status.vehicle_id}/candidates/{awaiting.candidate_id}/crop.jpg"
                            if awaiting.crop_jpeg_b64
                            else None
                        ),
                        status=_STATUS[decided[-1].action] if decided else "awaiting",
                    )
                )
            vehicles.append(
                VehicleView(
                    id=status.vehicle_id,
                    state=status.state,
                    mission_id=status.mission_id,
                    prompt=status.prompt,
                    position=status.position,
                    altitude_m=status.altitude_m,
                    age_s=round(max(0.0, now - status.updated_at), 1),
                    candidates=candidates,
                )
            )
        for key in [k for k in self._first_seen if k not in waiting]:
            del self._first_seen[key]
        return SupervisorSnapshot(server_time=now, vehicles=vehicles)


def without_ages(snapshot: SupervisorSnapshot) -> str:
    """The snapshot's content minus what changes every second, to tell a real change from time passing."""
    ages = {
        "server_time": True,
        "vehicles": {"__all__": {"age_s": True, "candidates": {"__all__": {"age_s"}}}},
    }
    return snapshot.model_dump_json(exclude=ages)  # type: ignore[arg-type]
