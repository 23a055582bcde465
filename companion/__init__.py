"""The onboard process: camera sources, trackers, back-end client, MAVLink link and the main loop."""
