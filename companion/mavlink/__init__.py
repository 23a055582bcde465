"""The companion's end of the MAVLink link: `VehicleLink` (reader, setpoint streamer, GCS commands,
status), telemetry decoding, setpoint encoding for ArduPilot and PX4, MAVSDK offboard. The wire
pieces the ground tool shares (connection, signing, modes, GCS protocol) live in `cloudtrack`."""
