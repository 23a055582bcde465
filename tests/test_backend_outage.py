"""Outages lose nothing: the back-end worker keeps the search keyframes a real back-end could not be asked
about (`companion.cloud.keyframe_store`) and sends them, newest first, once it answers again; the real
back-end (YOLOX-nano) is served on a loopback port, stopped and served again on the same port.
Select: -k outage."""

from __future__ import annotations

import json
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from behaviors.geometry import Box
from behaviors.mission import MissionState
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult
from cloudtrack.api_client import BackendClient
from cloudtrack.api_models import VehicleStatusIn
from companion.cloud.backend_worker import BackendAnswer, BackendWorker
from companion.cloud.keyframe_store import KeyframeStore, StoreCounts, StoredKeyframe
from companion.mission_runner import EventLogObserver, MissionRunner
from companion.run_command import QueryService
from companion.vision.frame_sources import Frame
from tests.backend_fixtures import frame
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, free_port, serve

PROMPT = "a man in a white shirt"


def _now() -> float:
    """The store's clock: the keyframes' capture times (1, 2, ...) are seconds on it, none too old."""
    return 100.0


def _pose(t: float) -> Telemetry:
    return Telemetry(t, 47.0 + t * 1e-5, 8.0, 30.0, yaw=0.5)


def _wait(condition: Callable[[], Any], what: str, timeout_s: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"{what}: not within {timeout_s} s")


def _answers(worker: BackendWorker, count: int) -> list[BackendAnswer]:
    out: list[BackendAnswer] = []

    def more() -> bool:
        while (answer := worker.poll()) is not None:
            out.append(answer)
        return len(out) >= count

    _wait(more, f"{count} answers")
    return out


def _app(models_dir: Path) -> object:
    return create_app(
        BackendConfig(
            auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
            detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
            verifier=VerifierConfig(kind="none"),
            sessions=SessionConfig(sqlite_path=":memory:"),
        )
    )


def _client(port: int, token: str = VEHICLE_TOKENS["drone-1"], timeout_s: float = 30.0) -> BackendClient:
    return BackendClient(
        f"http://127.0.0.1:{port}", token, timeout_s, vehicle_id="drone-1", mission_id="m-outage"
    )


def test_outage_search_keyframes_are_kept_and_sent_newest_first_when_the_back_end_returns(
    models_dir: Path, sequences_dir: Path
) -> None:
    image = frame(sequences_dir, "uav123_person12_1", 1, size=(1280, 720))
    app, port = _app(models_dir), free_port()
    client = _client(port)
    store = KeyframeStore(64 * 2**20, 900.0, _now)
    # Two slots: a stored keyframe goes out only while the other is free, so they go one at a time.
    worker = BackendWorker(QueryService(client), max_in_flight=2, store=store, encode=client.encode)
    try:
        with serve(app, port):
            worker.submit(1, image, 1.0, _pose(1.0), prompt=PROMPT)
            (live,) = _answers(worker, 1)
            assert not live.stored and live.pose == _pose(1.0) and live.image is None
        # The back-end is gone (connection refused): search keyframes are kept with their poses; a
        # re-detection around a box and a keyframe given without a pose are not search keyframes.
        for k in range(2, 7):
            worker.submit(k, image, float(k), _pose(float(k)), prompt=PROMPT, query_id=k)
            _wait(lambda: store.counts().stored == k - 1, f"keyframe {k} stored")  # noqa: B023
        worker.submit(7, image, 7.0, _pose(7.0), prompt=PROMPT, roi=Box(10, 10, 50, 80))
        _wait(lambda: worker.health().consecutive_failures == 6, "the re-detection failed")
        worker.submit(8, image, 8.0, prompt=PROMPT)
        _wait(lambda: worker.health().consecutive_failures == 7, "the keyframe without a pose failed")
        assert worker.wait_idle(10) and worker.poll() is None
        counts = store.counts()
        assert counts == StoreCounts(stored=5, waiting=5, bytes=counts.bytes)
        print(f"outage store: {counts.bytes / counts.waiting / 1000:.1f} KB a keyframe (1280x720 -> 640)")
        assert "unreachable: connection refused" in worker.health().last_error
        with serve(app, port):  # back on the same address, same sessions
            worker.submit(9, image, 9.0, _pose(9.0), prompt=PROMPT)
            answers = _answers(worker, 6)
        assert [(a.frame_id, a.stored) for a in answers] == [
            (9, False),
            *((k, True) for k in (6, 5, 4, 3, 2)),  # the newest search area first
        ]
        for answer in answers[1:]:
            assert answer.pose == _pose(float(answer.frame_id)) and answer.capture_time == answer.frame_id
            assert answer.fields == {"prompt": PROMPT, "query_id": answer.frame_id} and answer.final
            # Candidates in the caller's pixels, and the keyframe to crop them from at that size.
            assert answer.detections and answer.image is not None and answer.image.shape == image.shape
            assert [d.box for d in answer.detections] == [d.box for d in answers[0].detections]  # same JPEG
        assert store.counts() == StoreCounts(stored=5, sent=5)
    finally:
        worker.close()


def test_outage_a_request_the_back_end_refuses_is_not_kept(models_dir: Path, sequences_dir: Path) -> None:
    """A 4xx is the request's own fault (here a token the back-end does not know): sending it again later
    would be refused again."""
    image = frame(sequences_dir)
    app, port = _app(models_dir), free_port()
    client = _client(port, token="not-a-vehicle-token")
    store = KeyframeStore(64 * 2**20, 900.0, _now)
    worker = BackendWorker(QueryService(client), store=store, encode=client.encode)
    try:
        with serve(app, port):
            worker.submit(1, image, 1.0, _pose(1.0), prompt=PROMPT)
            assert worker.wait_idle(30)
        assert "HTTP 401" in worker.health().last_error
        assert store.counts() == StoreCounts()
    finally:
        worker.close()


@contextmanager
def black_hole() -> Iterator[tuple[int, list[socket.socket]]]:
    """A server that accepts connections and never answers, until the test closes them: a back-end behind a
    link that swallows requests (each would time out)."""
    listener = socket.create_server(("127.0.0.1", 0))
    accepted: list[socket.socket] = []

    def accept() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            accepted.append(conn)

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1], accepted
    finally:
        listener.close()
        for conn in accepted:
            conn.close()


def test_outage_while_unreachable_one_request_tries_the_link_and_the_others_are_kept_untried(
    sequences_dir: Path,
) -> None:
    """Requests that would each wait out the timeout would hold every slot, and keyframes waiting for one
    would be replaced (lost): once the back-end is known unreachable only one tries at a time."""
    image = frame(sequences_dir)
    with black_hole() as (port, accepted):
        client = _client(port)
        store = KeyframeStore(64 * 2**20, 900.0, _now)
        worker = BackendWorker(QueryService(client), max_in_flight=4, store=store, encode=client.encode)
        try:
            worker.submit(1, image, 1.0, _pose(1.0), prompt=PROMPT)
            _wait(lambda: len(accepted) == 1, "the first request")
            accepted[0].close()  # the link drops it: unreachable
            _wait(lambda: store.counts().stored == 1, "the first keyframe kept")
            worker.submit(2, image, 2.0, _pose(2.0), prompt=PROMPT)
            _wait(lambda: len(accepted) == 2, "the request trying the link")
            for k in range(3, 7):  # one every 0.5 s in flight
                worker.submit(k, image, float(k), _pose(float(k)), prompt=PROMPT)
                _wait(lambda: store.counts().stored == k - 1, f"keyframe {k} kept untried")  # noqa: B023
            assert len(accepted) == 2 and worker.health().replaced == 0
            accepted[1].close()
            _wait(lambda: store.counts().stored == 6, "the one trying the link kept")
            assert [k.frame_id for k in iter(store.take_newest, None)] == [6, 5, 4, 3, 2, 1]
        finally:
            worker.close()


class GatedService:
    """Answers each request only when the test lets one through: which keyframes are out is deterministic."""

    def __init__(self) -> None:
        self.gate = threading.Semaphore(0)
        self.calls: list[int] = []

    def detect(self, image: Any, **fields: Any) -> list[Any]:
        self.calls.append(int(fields["frame_id"]))
        assert self.gate.acquire(timeout=10)
        return []

    def detect_early(self, image: Any, **fields: Any) -> tuple[list[Any], bool]:
        raise AssertionError("stored keyframes ask for final verdicts only")


def _stored(store: KeyframeStore, frame_ids: range) -> None:
    client = BackendClient("http://127.0.0.1:9", "t")
    encoded = client.encode(np.zeros((72, 128, 3), np.uint8))
    for k in frame_ids:
        store.put(
            StoredKeyframe(k, float(k), encoded, _pose(float(k)), {"prompt": PROMPT, "early_answer": True})
        )


def test_outage_stored_keyframes_never_take_the_last_free_slot() -> None:
    """Live tracking is not starved: with stored keyframes waiting and the link up, they go out only while a
    slot stays free for live keyframes, and a live keyframe waiting goes first."""
    service, store = GatedService(), KeyframeStore(64 * 2**20, 900.0, _now)
    worker = BackendWorker(
        service, max_in_flight=4, store=store, encode=BackendClient("http://x", "t").encode
    )
    image = np.zeros((72, 128, 3), np.uint8)
    try:
        worker.submit(1, image, 1.0, _pose(1.0))
        service.gate.release()
        _answers(worker, 1)  # the link is up
        # Stored and live arrive together: a worker thread woken late by the answer's notice would otherwise
        # find the stored ones before the live keyframe is submitted (seen once under `make check`).
        with worker._cond:  # the worker's own (re-entrant) lock, which `submit` takes too
            _stored(store, range(100, 110))
            worker.submit(2, image, 2.0, _pose(2.0))
        _wait(lambda: len(service.calls) == 4, "a live keyframe and two stored ones out")
        assert sorted(service.calls[1:]) == [2, 108, 109]  # the newest stored first
        assert store.counts().waiting == 8
        worker.submit(3, image, 3.0, _pose(3.0))  # the slot left free takes it at once
        _wait(lambda: len(service.calls) == 5, "the live keyframe out")
        assert service.calls[4] == 3
        for _ in range(12):
            service.gate.release()
        answers = _answers(worker, 12)
        assert sorted(a.frame_id for a in answers if a.stored) == list(range(100, 110))
        assert all(a.pose == _pose(float(a.frame_id)) for a in answers)
        assert store.counts() == StoreCounts(stored=10, sent=10)
    finally:
        worker.close()


def test_outage_with_a_single_slot_a_stored_keyframe_waits_for_the_live_ones() -> None:
    service, store = GatedService(), KeyframeStore(64 * 2**20, 900.0, _now)
    worker = BackendWorker(
        service, max_in_flight=1, store=store, encode=BackendClient("http://x", "t").encode
    )
    image = np.zeros((72, 128, 3), np.uint8)
    try:
        worker.submit(1, image, 1.0, _pose(1.0))
        _wait(lambda: service.calls == [1], "the first keyframe out")
        _stored(store, range(100, 103))
        worker.submit(2, image, 2.0, _pose(2.0))  # waits for the slot
        service.gate.release()
        _wait(lambda: len(service.calls) == 2, "the next request out")
        assert service.calls == [1, 2]  # the live keyframe waiting went first
        service.gate.release()
        # Stored keyframes go out only while the main loop keeps up with the answers (one an iteration).
        assert [a.frame_id for a in _answers(worker, 2)] == [1, 2]
        _wait(lambda: len(service.calls) == 3, "a stored keyframe out")
        assert service.calls[2] == 102
        for _ in range(3):
            service.gate.release()
        assert [a.frame_id for a in _answers(worker, 3)] == [102, 101, 100]
    finally:
        worker.close()


class Camera:
    """The frame source: `image` (switchable) with increasing ids, captured now."""

    def __init__(self, image: np.ndarray) -> None:
        self.image = image
        self.frames = 0

    def read(self, timeout_s: float) -> Frame:
        time.sleep(min(timeout_s, 0.02))  # a 50 Hz camera
        self.frames += 1
        return Frame(self.frames, time.monotonic(), self.image)

    def close(self) -> None:
        pass


class Frontend:
    """No tracker runs while the search only looks: every frame's result is 'nothing tracked'."""

    def feed(self, frame: Frame) -> TrackResult:
        return TrackResult(frame.frame_id, frame.capture_time, None, 0.0, False, "idle")


class Vehicle:
    """The autopilot hovering on its survey mission (AUTO) 30 m up; the GCS's lines are kept."""

    def __init__(self, *commands: Any) -> None:
        self.commands_due = list(commands)
        self.said: list[str] = []

    def telemetry(self) -> Telemetry:
        return Telemetry(
            time.monotonic(), 47.3977, 8.5456, 30.0, mode="AUTO", mission_active=True, mission_item=3
        )

    def commands(self) -> list[Any]:
        due, self.commands_due = self.commands_due, []
        return due

    def send_status(self, text: str, severity: int = 6) -> None:
        self.said.append(text)

    def safety_events(self) -> list[Any]:
        return []

    def __getattr__(self, name: str) -> Callable[..., None]:
        return lambda *args, **kwargs: None  # kick, report_frame, report_backend_ok, report_tracking, ...


def _drained(runner: MissionRunner) -> dict[str, int] | None:
    """The status's counts once every keyframe stored so far was sent and the loop took its answer (and the
    live ones' since), else None."""
    counts = runner._status()["keyframes"]
    return counts if counts["sent"] == counts["stored"] and counts["analysed"] > counts["sent"] else None


def looping(runner: MissionRunner, condition: Callable[[], Any]) -> Callable[[], Any]:
    """`condition` after one more iteration of the companion's main loop."""

    def after_an_iteration() -> Any:
        runner.iterate()
        return condition()

    return after_an_iteration


def test_outage_a_person_in_a_stored_keyframe_reaches_the_gcs_and_the_status(
    models_dir: Path, sequences_dir: Path
) -> None:
    """The whole companion path with the real back-end: the survey flies over a person while the back-end
    is down; once it is back the stored keyframes are analysed, and the person is put to the supervisor with
    where they were and how long ago (the GCS line, the status's `awaiting`), the counts in the status."""
    # The detector alone judges nothing: 'uncertain'. A search every 2 s leaves the stored keyframes slots on
    # a loaded machine (they never take one a live keyframe waits for).
    config = MissionConfig(accept_uncertain=True, search_interval_s=2.0)
    person = frame(sequences_dir, "uav123_person12_1", 1, size=(config.camera.width, config.camera.height))
    app, port = _app(models_dir), free_port()
    client = _client(port)  # 30 s: no live keyframe times out on a loaded machine (it would be stored)
    store = KeyframeStore(64 * 2**20, 900.0)
    worker = BackendWorker(QueryService(client), max_in_flight=4, store=store, encode=client.encode)
    camera, vehicle = Camera(person), Vehicle(StartMission(PROMPT, mission_id="m-outage"))
    log: list[str] = []  # the event log the simulator scores a flight by
    fakes: tuple[Any, Any, Any] = (camera, Frontend(), vehicle)  # only what the loop uses of each
    runner = MissionRunner(
        config, *fakes, worker, observers=[EventLogObserver(log.append)], keyframe_store=store
    )
    try:
        _wait(looping(runner, lambda: store.counts().stored >= 3), "search keyframes stored")
        assert runner.state.mode is MissionState.SEARCHING and runner.state.along_mission
        camera.image = np.zeros_like(person)  # the survey has flown on: nobody in view now
        with serve(app, port):
            line = _wait(
                looping(runner, lambda: next((s for s in vehicle.said if s.startswith("CANDIDATE")), None)),
                "the candidate on the GCS",
                120.0,
            )
            # Every stored keyframe sent and its answer taken by the loop (and the live ones since).
            counts = _wait(looping(runner, lambda: _drained(runner)), "the store sent and analysed", 120.0)
        assert runner.state.mode is MissionState.SEARCHING  # no track on a person long out of view
        # The frame shows three people: each stored keyframe puts the best one not yet put to the supervisor.
        lines = [s for s in vehicle.said if s.startswith("CANDIDATE")]
        assert lines[0] == line and len(lines) == len(runner.state.pending)
        entries = [json.loads(e) for e in log]
        reports = [e for e in entries if e["kind"] == "candidate_report"]
        assert any(e["kind"] == "answer" and e.get("stored") for e in entries)
        for said, pending, report in zip(lines, runner.state.pending, reports, strict=True):
            match = re.fullmatch(
                r"CANDIDATE AWAITING (\S+) at (-?[\d.]+),(-?[\d.]+); seen (\d+) s ago(;.*)?", said
            )
            assert match is not None, said
            assert pending.stored and pending.candidate_id == match[1] and pending.position is not None
            where = (round(pending.position.lat_deg, 6), round(pending.position.lon_deg, 6))
            assert (float(match[2]), float(match[3])) == where
            assert report["stored"] and report["seen_s"] == pending.position_s
            assert int(match[4]) == round(report["t"] - pending.position_s)  # how long ago, when said
        status = runner._status()
        VehicleStatusIn.model_validate(status)  # the back-end's own schema takes it
        shown = runner.state.pending[-1]
        assert shown.position is not None
        awaiting = status["awaiting"]
        assert awaiting["candidate_id"] == shown.candidate_id
        assert awaiting["crop_jpeg_b64"]  # cut from the stored keyframe
        assert awaiting["position"] == [shown.position.lat_deg, shown.position.lon_deg]
        age = runner.state.now_s - shown.position_s
        assert abs(time.time() - age - awaiting["seen_at"]) < 2.0
        # (A live keyframe timing out on a loaded machine is stored too: the counts when the store was drained.)
        assert counts["stored"] >= 3 and counts["waiting"] == counts["dropped"] == 0
    finally:
        worker.close()
