"""SET_POSITION_TARGET_LOCAL_NED for body-frame velocity and yaw rate, per autopilot.

type_mask ignores position, acceleration and the yaw angle and always uses yaw_rate: ArduPilot 4.3+
falls back to its own yaw behaviour (turning towards the direction of travel) when both yaw fields are
ignored, so "not turning" is sent as yaw_rate 0. ArduPilot reads body velocities in
MAV_FRAME_BODY_OFFSET_NED and flies them only in GUIDED; PX4 reads them in MAV_FRAME_BODY_NED and needs
the stream running before OFFBOARD may be selected.
"""

from __future__ import annotations

from dataclasses import dataclass

from behaviors.setpoint import Setpoint
from cloudtrack.autopilot_modes import AutopilotKind
from cloudtrack.mavlink_connection import mavlink

MAV_FRAME_BODY_NED = int(mavlink.MAV_FRAME_BODY_NED)
MAV_FRAME_BODY_OFFSET_NED = int(mavlink.MAV_FRAME_BODY_OFFSET_NED)
# Ignore position, acceleration and the yaw angle; use velocity and yaw rate.
TYPE_MASK_VELOCITY_YAW_RATE = int(
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
)
PX4_MIN_PRESTREAM_S = 1.0  # setpoints streamed before OFFBOARD is requested


@dataclass(frozen=True)
class SetpointMessage:
    """The fields of one SET_POSITION_TARGET_LOCAL_NED that carry the command."""

    frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw_rate: float


def velocity_frame(kind: AutopilotKind) -> int:
    return MAV_FRAME_BODY_OFFSET_NED if kind is AutopilotKind.ARDUPILOT else MAV_FRAME_BODY_NED


def encode_velocity(kind: AutopilotKind, setpoint: Setpoint) -> SetpointMessage:
    """The message for a body-frame (forward, right, down) velocity and yaw rate (rad/s, clockwise)."""
    return SetpointMessage(
        velocity_frame(kind),
        TYPE_MASK_VELOCITY_YAW_RATE,
        float(setpoint.forward),
        float(setpoint.right),
        float(setpoint.down),
        float(setpoint.yaw_rate),
    )
