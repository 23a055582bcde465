"""Software-in-the-loop: a MAVLink autopilot simulator, a synthetic camera world and closed-loop scenarios."""
