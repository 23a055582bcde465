"""Software-in-the-loop: a MAVLink autopilot simulator, a synthetic camera world and closed-loop scenarios.

It drives the real companion and back-end, so it may import every package; nothing imports it."""
