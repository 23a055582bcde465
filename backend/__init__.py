"""The cloud service: superset detection, margin crops, semantic verification, sessions for many vehicles,
and the supervisor page; FastAPI app in `app.py`, routes in `routers/`, what they need in `dependencies.py`.
It builds on `cloudtrack` and `behaviors` and never imports `companion` or `sitl`."""
