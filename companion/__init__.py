"""The onboard process on the drone: camera sources, trackers, the MAVLink link, the back-end session and the
main loop that runs the mission (`behaviors`), plus its tools (eval, bench, replay) and the ground tool
`cloudtrack-gcs`. It builds on `cloudtrack` and `behaviors` and never imports `backend` or `sitl`."""
