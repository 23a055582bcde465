"""`cloudtrack-companion run`: start the onboard process (camera, tracker, back-end, MAVLink, main loop).

The composition root: it reads the configuration, opens every adapter, hands them to
`companion.mission_runner.MissionRunner` and runs it until SIGTERM/SIGINT. Anything that cannot start
(bad configuration, missing weights, unknown camera source) ends with a clear message and status 2.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import os
import signal
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import IO, Any, NoReturn

from behaviors.mission_config import MissionConfig
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError, resolve_model_dir
from companion.config import CompanionConfig
from companion.config_command import add_config_flags, load_from_args

log = logging.getLogger(__name__)

# How long the stop waits for the back-end session's thread: it may be inside a request (a status POST can
# take a second on a loaded machine) that nobody needs once the companion is stopping; the thread is a daemon.
SESSION_STOP_WAIT_S = 0.2

EXAMPLES = """\
examples:
  cloudtrack-companion run --config /etc/cloudtrack/companion.toml
  cloudtrack-companion run --set mavlink.connection=udpout:127.0.0.1:14540 \\
      --set camera.source=rtsp://192.168.1.10:8554/cam --set backend.url=https://cloudtrack.example.org
  cloudtrack-companion run --set camera.source=sim+tcp://127.0.0.1:5600 --set tracker.name=csrt \\
      --events-out out/events.jsonl          # against `cloudtrack-sim` (SITL camera stream)
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "run",
        help="run the onboard process: track the described person and fly to keep them in view",
        description=(
            "Run the companion main loop. It never arms, takes off or lands; it flies only while the autopilot "
            "is in GUIDED (ArduPilot) or OFFBOARD (PX4), and stops on SIGTERM within 2 s (explicit stop, hold, "
            "GCS told)."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_flags(parser)
    parser.add_argument(
        "--model-dir", help="weights folder (default: tracker.model_dir, $CLOUDTRACK_MODEL_DIR, cache)"
    )
    parser.add_argument(
        "--events-out",
        type=Path,
        metavar="FILE",
        help="write every behaviour event and action as JSON lines to FILE ('-': stdout)",
    )
    parser.set_defaults(func=run)


class QueryService:
    """Lets the back-end worker carry the behaviour's query id: kept in the answer, not sent on the wire."""

    def __init__(self, client: Any) -> None:
        self._client = client

    def detect(self, image: Any, **fields: Any) -> Any:
        fields.pop("query_id", None)
        return self._client.detect(image, **fields)

    def detect_early(self, image: Any, **fields: Any) -> Any:
        fields.pop("query_id", None)
        return self._client.detect_early(image, **fields)


def mission_config(config: CompanionConfig) -> MissionConfig:
    from companion.vision.camera_calibration import camera_model

    sections = MissionConfig.from_sections(
        behavior=config.behavior.model_dump(),
        control=config.control.model_dump(),
        safety=config.safety.model_dump(),
        camera=config.camera.model_dump(),
        backend=config.backend.model_dump(),
    )
    # The lens calibration is read here (a file, OpenCV): the behaviours get the resulting numbers.
    # The front-end's re-initialisation policy decides how the mission hands it answers (docs/behavior.md);
    # set here too so that the flight record holds the config the mission really ran with (replay).
    verified = config.tracker.reinit_policy == "verified"
    return replace(sections, camera=camera_model(config.camera), verified_reinit=verified)


def run(args: argparse.Namespace) -> int:
    try:
        config = load_from_args(args)
        mission = mission_config(config)  # reads [camera] calibration_file, if any
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from cloudtrack.api_client import BackendClient
    from cloudtrack.service_notify import ServiceNotifier
    from companion.cloud.backend_session import BackendSession
    from companion.cloud.backend_worker import BackendWorker
    from companion.mavlink.vehicle_link import VehicleLink
    from companion.mission_runner import EventLogObserver, LoopObserver, LoopSettings, MissionRunner
    from companion.vision.frame_sources import SourceError, open_source
    from companion.vision.tracking_frontend import TrackingFrontend, curve_pod

    cam = config.camera
    model_dir = resolve_model_dir(args.model_dir or config.tracker.model_dir or None)
    try:
        frontend = TrackingFrontend.from_config(
            config.tracker,
            model_dir,
            support_pod=curve_pod(config.search.curve_file),
            keyframe_width=config.backend.max_keyframe_width,
        )
        frames = open_source(
            cam.source,
            width=cam.width,
            height=cam.height,
            fps=cam.fps,
            reconnect_interval_s=cam.reconnect_interval_s,
        )
    except (ModelError, SourceError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    events_file: IO[str] | None = None
    observers: list[LoopObserver] = []
    if args.events_out is not None:
        if str(args.events_out) == "-":
            events_file = sys.stdout
        else:
            args.events_out.parent.mkdir(parents=True, exist_ok=True)
            events_file = open(args.events_out, "a", buffering=1, encoding="utf-8")  # noqa: SIM115 - closed below
        observers.append(EventLogObserver(events_file.write))

    rec = config.recording
    record = None
    if rec.enabled:
        from companion.flight_record import FlightRecordObserver, open_record, records_dir

        record_dir = str(records_dir(rec.dir))
        record = FlightRecordObserver(
            mission,
            lambda mission_id: open_record(
                True, record_dir, rec.max_bytes, rec.video, config.vehicle.id, mission_id, video_fps=cam.fps
            ),
        )
        observers.append(record)

    from companion.operator_notices import OperatorNotices

    notices = OperatorNotices(config.mavlink.connection, config.backend.url)
    start_gate = None
    if config.backend.start_check_s > 0:
        from companion.cloud.start_check import StartCheck

        checker = BackendClient(
            config.backend.url,
            config.backend.token,
            config.backend.start_check_s,
            vehicle_id=config.vehicle.id,
        )
        start_gate = StartCheck(
            checker,
            on_verdict=lambda v: notices.set("start", None if v.accepted else f"start refused: {v.reason}"),
        )
    link = VehicleLink(config.mavlink, config.safety, (cam.width, cam.height), start_gate=start_gate)
    client = BackendClient(
        config.backend.url,
        config.backend.token,
        config.backend.timeout_s,
        config.backend.jpeg_quality,
        config.backend.max_keyframe_width,
        vehicle_id=config.vehicle.id,
        on_keyframe=record.keyframe if record is not None else None,
    )

    def backend_result(request: str, error: BaseException | None) -> None:
        if error is None:
            notices.backend_answered()
        else:
            notices.backend_failed(error, request)

    session = BackendSession(
        client, period_s=config.backend.status_interval_s, on_result=partial(backend_result, "status")
    )
    store = None
    if config.backend.outage_store_mb > 0:
        from companion.cloud.keyframe_store import KeyframeStore

        store = KeyframeStore(config.backend.outage_store_mb * 2**20, config.backend.outage_store_max_age_s)
    worker = BackendWorker(
        QueryService(client),
        max_in_flight=config.backend.max_requests_in_flight,
        on_result=partial(backend_result, "search"),
        store=store,
        encode=client.encode,
    )
    from companion.search_coverage import SearchCoverage

    coverage = SearchCoverage(
        mission.camera,
        cam.search_range_m,
        link.mission_link,
        lambda: link.autopilot_kind.value if link.autopilot_kind is not None else None,
        (config.mavlink.target_system, config.mavlink.source_component),
        config.search,
        config.backend.max_keyframe_width,
        config.behavior.accept_uncertain,
        config.safety.max_survey_distance_m,
    )
    settings = LoopSettings(
        frame_stale_s=config.safety.frame_stale_s, loop_stall_s=config.safety.loop_stall_s
    )
    runner = MissionRunner(
        mission,
        frames,
        frontend,
        link,
        worker,
        session,
        settings,
        observers,
        ServiceNotifier.from_environment(),
        video_sinks=[record.video_frame] if record is not None and rec.video else [],
        keyframe_max_width=config.backend.max_keyframe_width,
        coverage=coverage,
        notices=notices,
        keyframe_store=store,
    )
    signalled: list[float] = []  # when the first stop signal came (monotonic)

    def on_signal(*_: object) -> None:
        if not signalled:
            signalled.append(time.monotonic())
        runner.request_stop()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        link.start()
    except OSError as exc:
        print(f"error: cannot open the MAVLink link {config.mavlink.connection}: {exc}", file=sys.stderr)
        frames.close()
        worker.close()
        return 2
    if record is not None:
        from companion.flight_record import attach_tlog

        attach_tlog(link.endpoint.conn, record)  # every MAVLink message in and out goes into the record
    session.start()
    log.info(
        "companion %s: camera %s, tracker %s, back-end %s, MAVLink %s",
        config.vehicle.id,
        cam.source,
        config.tracker.name,
        config.backend.url,
        config.mavlink.connection,
    )
    try:
        # Returns once the vehicle is stopped and the GCS told (`MissionRunner._shutdown`).
        code = runner.run()
    finally:
        steps = [("loop", time.monotonic())]
        session.close(SESSION_STOP_WAIT_S)
        steps.append(("back-end", time.monotonic()))
        link.close()
        steps.append(("link", time.monotonic()))
        for obs in observers:
            close = getattr(obs, "close", None)
            if close is not None:
                close()
        if events_file is not None and events_file is not sys.stdout:
            events_file.close()
        steps.append(("record", time.monotonic()))
        since = signalled[0] if signalled else steps[0][1]
        log.info(
            "companion stopped %.2f s after the signal (%s)",
            steps[-1][1] - since,
            ", ".join(f"{name} {at - since:.2f} s" for name, at in steps),
        )
    exit_now(code)


def exit_now(code: int) -> NoReturn:
    """End the process at once once everything is closed: the interpreter's own teardown (freeing every
    module: OpenCV, onnxruntime, MAVSDK, pydantic...) took 0.2-1.7 s of a loaded machine for nothing, and
    the stop must end within 2 s of SIGTERM (docs/sitl.md). The exit handlers still run (logging's flush,
    multiprocessing's clean-up of an encoder process), and stdout/stderr are flushed."""
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # closed, or a broken pipe: nothing more to say
            stream.flush()
    os._exit(code)
