"""Mission logic with no I/O: state machine, control law, geometry and the small value types they share.

Nothing here may import sockets, threads, clocks, OpenCV or the adapters in `companion`, `backend` or
`sitl`; `tests/test_import_boundary.py` enforces it.
"""
