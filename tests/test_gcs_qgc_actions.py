"""The QGroundControl custom-actions file: every button is a command the companion obeys."""

from __future__ import annotations

import json
from pathlib import Path

from behaviors.mission_commands import AbortMission, ConfirmCandidate, RejectCandidate
from cloudtrack.gcs_protocol import CMD_ABORT, CMD_CONFIRM, CMD_REJECT, CMD_STATUS
from tests.mavlink_harness import MainLoop, autopilot, gcs, receive_until, vehicle_link

ACTIONS = Path(__file__).resolve().parent.parent / "config" / "gcs" / "qgc-cloudtrack-actions.json"


def test_qgc_actions_file_sends_confirm_reject_abort_and_status() -> None:
    spec = json.loads(ACTIONS.read_text())
    assert spec["fileType"] == "MavlinkActions" and spec["version"] == 1
    actions = {a["label"]: a for a in spec["actions"]}
    assert {a["mavCmd"] for a in actions.values()} == {CMD_CONFIRM, CMD_REJECT, CMD_ABORT, CMD_STATUS}
    assert all(a["compId"] == 191 and a["description"] for a in actions.values())
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as qgc:
        for label in ("CloudTrack Confirm", "CloudTrack Reject", "CloudTrack Abort", "CloudTrack Status"):
            a = actions[label]
            params = [float(a.get(f"param{i}", 0.0)) for i in range(1, 8)]
            # what QGroundControl sends for a MAVLink action: COMMAND_LONG to the active vehicle and compId
            qgc.send(lambda m, a=a, p=params: m.command_long_send(1, a["compId"], a["mavCmd"], 0, *p))
            ack = receive_until(
                qgc, lambda m, a=a: m.get_type() == "COMMAND_ACK" and m.command == a["mavCmd"], 3.0
            )
            assert ack is not None and ack.result == 0, label
        assert link.commands() == [ConfirmCandidate("", by="gcs"), RejectCandidate(""), AbortMission("gcs")]
