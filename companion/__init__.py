"""The onboard process on the drone: its runtime (main loop, run command, config, safety watchdog, flight
record) at the root, `mavlink/`, `vision/` and `cloud/` by capability, and `tools/` (eval, bench, replay)
apart. It builds on `cloudtrack` and `behaviors` and never imports `backend`, `sitl` or `gcs`."""
