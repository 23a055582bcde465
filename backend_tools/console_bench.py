"""What the supervisor's console costs: `python -m backend_tools.console_bench [--vehicles 10]`.

1. The page's data: one vehicle's `vehicle` event and the whole snapshot for N vehicles that each flew a
   long search (3,000 status reports 5 m apart: the stored track is capped at 1,000 points, 300 shown),
   with a 200-vertex search area, 20 covered rings, a candidate and 5 finds; the snapshot's build time
   (first build, and again with nothing changed: one build serves every open stream).
2. A find to the rescuers' map: from the vehicle's status report to a TAK server's socket (a loopback TCP
   stand-in reading CoT XML), through the real app (`POST /v1/vehicles/{v}/status` over HTTP) and
   `cloudtrack/cursor_on_target.py`; median over 20 finds.
Everything in process, on loopback; SQLite in memory.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import threading
import time

import httpx

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, SessionConfig, TakConfig
from backend.serving import BackgroundServer
from backend.sessions import SessionStore
from backend.state_store import SqliteStore
from backend.supervisor_view import SupervisorView
from backend_tools.fleet_services import free_port
from cloudtrack.api_models import VehicleStatusIn

AREA = [[47.397 + 0.002 * (i % 2), 8.545 + 0.00001 * i] for i in range(200)]
COVERED = [[[47.397 + 0.0001 * j, 8.545 + 0.0001 * (k % 2)] for k in range(25)] for j in range(20)]


def page_data(vehicles: int) -> None:
    store = SessionStore(SqliteStore(":memory:"))
    for v in range(vehicles):
        vehicle = f"drone-{v}"
        for i in range(3000):
            store.set_status(
                vehicle,
                VehicleStatusIn(
                    mission_id="m1", state="SEARCHING", prompt="a man in a red jacket", reason="searching",
                    position=[47.397 + 0.000045 * i, 8.545 + 0.00001 * v],
                ),
            )  # fmt: skip
        for f in range(5):
            find = {"candidate_id": f"f{f}", "position": [47.39, 8.54 + f * 1e-4], "sigma_m": 2.0,
                    "time": 1.7e9, "prompt": "a man in a red jacket", "confirmed_by": "gcs"}  # fmt: skip
            store.set_status(vehicle, VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=find))
        store.set_status(
            vehicle,
            VehicleStatusIn(
                mission_id="m1", state="AWAITING_SUPERVISOR", position=[47.4, 8.545],
                search={"area": AREA, "covered": COVERED, "coverage": 0.4, "mission_item": 5,
                        "mission_items": 40, "mode": "AUTO"},
                progress={"keyframes": 3000, "candidates": 12, "rejected": 3},
                awaiting={"candidate_id": f"c{v}", "box": [1, 2, 30, 60], "position": [47.39, 8.54]},
            ),
        )  # fmt: skip
    view = SupervisorView(store)
    started = time.perf_counter()
    snapshot = view.snapshot()
    first_ms = (time.perf_counter() - started) * 1000
    started = time.perf_counter()
    for _ in range(100):
        view.snapshot()
    again_ms = (time.perf_counter() - started) * 10
    one = snapshot.vehicles[0]
    stored = store.mission_map("drone-0", "m1")
    print(
        f"page data: one vehicle's event {len(one.model_dump_json()):,} bytes ({len(one.track)} of "
        f"{len(stored.track) if stored else 0} stored track points shown); snapshot of {vehicles} vehicles "
        f"{len(snapshot.model_dump_json()):,} bytes, built in {first_ms:.1f} ms, again with nothing "
        f"changed {again_ms:.2f} ms"
    )


class _Unused:
    """No keyframe is sent here: the app needs a detector, none is asked."""

    name = "unused"

    def detect(self, image_bgr: object, classes: object, frame_id: int | None = None) -> list[object]:
        raise AssertionError("the console bench sends no keyframe")


class _TakSocket:
    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.arrivals: list[float] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        buffer = b""
        with conn:
            while True:
                data = conn.recv(65536)
                if not data:
                    return
                buffer += data
                while b"</event>" in buffer:
                    _, _, buffer = buffer.partition(b"</event>")
                    self.arrivals.append(time.perf_counter())


def find_to_tak(finds: int = 20) -> None:
    tak = _TakSocket()
    token, supervisor = "console-bench-vehicle-token", "console-bench-supervisor-token"
    config = BackendConfig(
        auth=AuthConfig(tokens={"drone-1": token}, supervisor_token=supervisor),
        sessions=SessionConfig(sqlite_path=":memory:"),
        tak=TakConfig(url=f"tcp://127.0.0.1:{tak.port}"),
    )
    app = create_app(config, detector=_Unused())  # type: ignore[arg-type]
    delays: list[float] = []
    with (
        BackgroundServer(app, port=free_port()) as server,
        httpx.Client(base_url=server.url, timeout=10) as http,
    ):
        for i in range(finds):
            find = {"candidate_id": f"c{i}", "position": [47.39, 8.54 + i * 1e-4], "sigma_m": 2.0,
                    "time": 1.7e9, "prompt": "a man in a red jacket", "confirmed_by": "gcs"}  # fmt: skip
            sent = time.perf_counter()
            answer = http.post(
                "/v1/vehicles/drone-1/status",
                json={"mission_id": "m1", "state": "CONFIRMED", "find": find},
                headers={"Authorization": f"Bearer {token}"},
            )
            answer.raise_for_status()
            deadline = time.monotonic() + 10
            while len(tak.arrivals) <= i and time.monotonic() < deadline:
                time.sleep(0.0005)
            delays.append((tak.arrivals[i] - sent) * 1000)
    print(
        f"find to TAK: status report to the TAK server's socket, median {statistics.median(delays):.1f} ms, "
        f"max {max(delays):.1f} ms over {finds} finds (HTTP, SQLite, CoT over TCP, loopback)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--vehicles", type=int, default=10)
    args = parser.parse_args()
    page_data(args.vehicles)
    find_to_tak()


if __name__ == "__main__":
    main()
