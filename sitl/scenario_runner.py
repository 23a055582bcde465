"""Running one closed-loop scenario: every real part on one machine, scored from ground truth.

Per vehicle: the mock autopilot (`sitl.autopilot`, armed and hovering), a camera that follows it over
MAVLink and streams rendered frames on sim+tcp://, a fault proxy in front of the back-end, a scripted GCS
on the autopilot's GCS link, and the REAL companion process (`python -m companion.cli run`). Shared: one
world and the REAL back-end (FastAPI under uvicorn on loopback) with the simulated person detector and
the configured verifier (local colour verifier by default) judging the rendered pixels.

The companion writes its decisions as JSON lines (`--events-out`); the runner tails them for progress,
the video overlay and the scripted supervisor, and scores the run with `sitl.metrics` and the scenario's
checks. Times in the results are seconds since the mission started.
"""

from __future__ import annotations

import gc
import json
import math
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from itertools import pairwise
from pathlib import Path
from typing import Any

from behaviors.camera_model import CameraModel
from behaviors.geometry import Box, iou
from sitl.camera_render import FrameTruth, RenderedFrame, TruthBox, VehiclePose
from sitl.camera_server import CameraServer, PoseFollower
from sitl.fault_proxy import FaultProxy
from sitl.flight_stack import (
    REAL_AUTOPILOTS,
    FlightStack,
    PoseSource,
    find_flight_stack,
    start_flight_stack,
)
from sitl.metrics import (
    FrameSample,
    PoseSample,
    SetpointSample,
    TimedEvent,
    distance_coasted,
    estimate_error,
    following_intervals,
    heading_error_at,
    summarise,
)
from sitl.pause_monitor import PauseMonitor
from sitl.scenarios import (
    COASTING_FAULTS,
    MISSION_MODE,
    TAKEOVER_MODE,
    Fault,
    Scenario,
    ScriptedGcs,
    VehicleOutcome,
    assess,
    autopilot_names,
    for_autopilots,
)
from sitl.simulated_detector import DetectorNoise, SimulatedPersonDetector
from sitl.video_overlay import OverlayState, VideoWriter, draw_overlay

FRAME_ID_BITS = 20  # camera i numbers its frames from i << 20, so one detector serves every camera
EARTH_RADIUS = 6_378_137.0
ALTITUDE_M = 10.0
MOUNT_PITCH_DEG = -40.0  # at 10 m up and 12 m standoff the target sits near the image centre
STANDOFF_M = 12.0
VIDEO_DELAY_FRAMES = 20
VEHICLE_ORIGINS = (
    (0.0, 0.0),
    (0.0, -8.0),
    (0.0, 24.0),  # the third: nearer the east edge, so it flies the outer lane first
)  # where each vehicle's home lies in the world (north, east)
HOME_ALT_M = 488.0
HOME_LAT, HOME_LON = 47.397742, 8.545594  # the world's origin (PX4's SIH default home)
FOUND_TEXT = re.compile(r"FOUND (-?\d+\.\d+),(-?\d+\.\d+) \+-(\d+(?:\.\d+)?)m")  # VehicleLink.announce_find
GUID_TIMEOUT_S = 1.0  # what docs/operations.md recommends; the mock and the real SITL both run with it
FLOOD_SENDERS = 200
FLY_TO_OFFSET_M = (0.0, 15.0)  # the GCS "fly to" target, from where the vehicle is (north, east)
# After the survey's end: the last keyframes' answers, the status laying them and a decision on a candidate
# seen at the end (the supervisor's 1 s) still come in.
SURVEY_END_GRACE_S = 5.0
# A fleet's search (`Scenario.fleet`): the lines `cloudtrack-gcs survey --fleet` prints per vehicle and for the
# whole area (gcs/fleet_survey.py describe_fleet).
FLEET_PART = re.compile(
    r"^vehicle (?P<id>\S+): (?P<lanes>lanes? [\d-]+ of \d+), (?P<length>\d+) m over (?P<ha>[\d.]+) ha, transit "
    r"(?P<transit>\d+) m, about (?P<min>\d+) min (?P<sec>\d+) s at (?P<speed>[\d.]+) m/s, (?P<items>\d+) items$"
)
FLEET_WHOLE = re.compile(
    r"^whole area: about (?P<min>\d+) min (?P<sec>\d+) s \(vehicle (?P<last>\S+) finishes last\); one vehicle "
    r"alone: about (?P<amin>\d+) min (?P<asec>\d+) s \((?P<alone>\S+), the quickest alone\)$"
)
FLEET_POLL_S = 1.0  # the merged map and the drop-outs, asked as the supervisor page would

Progress = Callable[[str], None]


@dataclass(frozen=True)
class RunOptions:
    autopilot: str | None = None  # None: the scenario's own
    seed: int = 1
    json_out: Path | None = None
    video_out: Path | None = None
    plot_out: Path | None = None
    tracker: str | None = None  # None: nano when its weights are installed, else csrt (no download)
    model_dir: Path | None = None
    work_dir: Path | None = None
    verifier: str | None = None  # None: the scenario's (`Scenario.verifier`)
    # With verifier "vlm" or "cascade": an OpenAI-protocol emulator on loopback stands in for the hosted
    # VLM and answers this many seconds after each request.
    vlm_latency_s: float = 2.0
    startup_timeout_s: float = 90.0
    arducopter_binary: Path | None = None  # None: sitl.arducopter_sitl.default_binary()
    px4_package: Path | None = None  # None: sitl.px4_sitl.default_package()
    speedup: float = 10.0  # ArduCopter's speed-up while it boots and takes off (the mission runs at 1)
    companion_settings: tuple[str, ...] = ()  # more `--set section.key=value` for the companion
    # A real autopilot already running and airborne (tests share one PX4 this way): the runner resets it
    # for the scenario (`FlightStack.reset`) instead of starting one, and leaves it running afterwards.
    flight_stack: FlightStack | None = None


@dataclass(frozen=True)
class _Seen:
    """What one rendered frame showed, without its pixels (a run keeps thousands)."""

    frame_id: int
    time_s: float
    truth: tuple[TruthBox, ...]
    pose: VehiclePose


@dataclass
class _Vehicle:
    index: int
    vehicle_id: str
    autopilot: Any
    follower: PoseSource
    camera: CameraServer
    proxy: FaultProxy
    gcs: ScriptedGcs
    events_path: Path
    log_path: Path
    process: subprocess.Popen[bytes] | None = None
    offset: int = 0
    events: list[dict[str, Any]] = field(default_factory=list)
    frames: list[_Seen] = field(default_factory=list)
    # The same by frame id: a candidate from a keyframe stored through an outage is judged on its own frame.
    frame_by_id: dict[int, _Seen] = field(default_factory=dict)
    state: str = ""
    overlay: OverlayState = field(default_factory=OverlayState)
    decided: set[str] = field(default_factory=set)
    pending_decision: tuple[float, str, str, str] | None = None  # (due time, action, person id, candidate id)
    # The candidate the companion last put to the supervisor, until it is decided: what candidate 0 means.
    awaiting_id: str = ""
    judgements: dict[str, tuple[str, str]] = field(default_factory=dict)  # candidate id -> (action, person)
    decision_sent: tuple[float, str] | None = None  # (when, action) of a decision the companion has not taken
    confirmations: list[tuple[float, str]] = field(default_factory=list)
    rejections: list[tuple[float, str]] = field(default_factory=list)
    proposals: list[tuple[float, str]] = field(default_factory=list)
    ready: bool = False
    stop_s: float | None = None  # companion exit time after SIGTERM
    judged: str = "none"  # the person the supervisor last confirmed
    track_boxes: dict[int, Box | None] = field(default_factory=dict)  # the companion's box per frame id
    video_queue: deque[tuple[int, float, Any]] = field(default_factory=deque)
    start_sent: tuple[float, int] | None = None  # (when, mission id) of the last unacknowledged start
    origin: tuple[float, float] = (0.0, 0.0)
    companion_udp_port: int | None = None  # the companion listens here (udpin) in scenarios that need it
    stall_resumed: float | None = None  # monotonic time of SIGCONT
    fly_to: tuple[float, tuple[float, float], tuple[float, float]] | None = None  # (t, from, to) world n/e
    flood: dict[str, int] = field(default_factory=dict)
    # The back-end's view of the vehicle (search scenarios): (time, status) as the supervisor page polls it.
    statuses: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    survey: dict[str, Any] = field(default_factory=dict)  # the plan the pilot uploaded
    rejections_taken: list[float] = field(default_factory=list)  # when the companion took each rejection
    personality: str = ""  # its autopilot: a mock personality or a real one (REAL_AUTOPILOTS)

    @property
    def real(self) -> bool:
        return self.personality in REAL_AUTOPILOTS


def default_tracker(model_dir: Path) -> str:
    """nano when its weights are installed and verified, else CSRT (needs no weights, no download)."""
    from cloudtrack.model_store import ModelError, require

    try:
        require("nano", model_dir)
        return "nano"
    except ModelError:
        return "csrt"


def _home(origin: tuple[float, float], lat0: float = HOME_LAT, lon0: float = HOME_LON) -> tuple[float, float]:
    lat = lat0 + math.degrees(origin[0] / EARTH_RADIUS)
    lon = lon0 + math.degrees(origin[1] / (EARTH_RADIUS * math.cos(math.radians(lat0))))
    return lat, lon


class ScenarioRun:
    """Sets up, runs and tears down one scenario; `run()` returns the results dictionary."""

    def __init__(self, scenario: Scenario, options: RunOptions, progress: Progress = print) -> None:
        from cloudtrack.model_store import resolve_model_dir

        # One autopilot per vehicle: `--autopilot` names one for all or gives a comma list (a fleet of real
        # autopilots flies two vehicles: `for_autopilots`).
        if options.flight_stack is None:
            self.autopilots = autopilot_names(scenario, options.autopilot)
            scenario = for_autopilots(scenario, self.autopilots)
        else:
            self.autopilots = (options.flight_stack.name,)
        self.scenario = scenario
        self.options = options
        self.progress = progress
        # The autopilot flown (single-autopilot runs), or the comma list of a mixed fleet.
        self.personality = self.autopilots[0] if len(set(self.autopilots)) == 1 else ",".join(self.autopilots)
        self.world = scenario.build_world(options.seed)
        self.camera = CameraModel.from_hfov(640, 480, 70.0, MOUNT_PITCH_DEG, stabilised=True)
        self.model_dir = resolve_model_dir(options.model_dir)
        self.tracker = options.tracker or default_tracker(self.model_dir)
        self.verifier = options.verifier or scenario.verifier
        self.flight_stacks: dict[str, Path] = {}  # each real autopilot's binary or package, by name
        self.shared = options.flight_stack
        if self.shared is not None:
            self.personality = self.shared.name
            if scenario.vehicles != 1:
                raise ValueError(f"{scenario.name} flies {scenario.vehicles} vehicles: one shared autopilot")
        else:
            for name in dict.fromkeys(n for n in self.autopilots if n in REAL_AUTOPILOTS):
                override = options.arducopter_binary if name == "arducopter" else options.px4_package
                self.flight_stacks[name] = find_flight_stack(name, override)  # never the mock instead
        # A temp work dir is removed after the run (--work-dir keeps one).
        self._own_work = options.work_dir is None
        self.work = options.work_dir or Path(tempfile.mkdtemp(prefix=f"cloudtrack-sim-{scenario.name}-"))
        self.work.mkdir(parents=True, exist_ok=True)
        self.vehicles: list[_Vehicle] = []
        self.epoch: float | None = None
        self._pauses = PauseMonitor()
        self.fault_times: dict[str, float] = {}
        self.faults_done: set[int] = set()
        self._near_target: dict[float, float] = {}  # near_target_m -> when the lead vehicle came that near
        self.video: VideoWriter | None = None
        self.tokens = {f"drone-{i + 1}": secrets.token_hex(16) for i in range(scenario.vehicles)}
        self._backend: Any = None
        self.detector: SimulatedPersonDetector | None = None
        self._vlm: Any = None
        self._t_mission: float | None = None
        self._flood_threads: list[Any] = []
        self._stopping = False
        self._supervisor_token = secrets.token_hex(16)
        self._last_poll = -math.inf
        self._app: Any = None
        # A fleet's search: its figures (`_fleet_results`), the re-plan's process and when the pilot sends the
        # leaving vehicle home (monotonic).
        self._fleet: dict[str, Any] = {}
        self._fleet_last_poll = -math.inf
        self._leave_at = math.inf
        self._replan: tuple[subprocess.Popen[bytes], Path, float] | None = None
        self._fleet_files: tuple[Path, Path] | None = None  # the fleet file and the survey's configuration

    @property
    def real(self) -> bool:
        """Some vehicle flies a real autopilot (each vehicle's own: `_Vehicle.real`)."""
        return any(n in REAL_AUTOPILOTS for n in self.autopilots)

    # ----------------------------------------------------------------------------------------- helpers
    def now(self) -> float:
        """Seconds since the mission started (negative before)."""
        return time.monotonic() - (self.epoch if self.epoch is not None else time.monotonic())

    def say(self, text: str) -> None:
        self.progress(f"[{self.now():6.1f}s] {text}")

    def _truth_lookup(self, frame_id: int) -> FrameTruth | None:
        index = frame_id >> FRAME_ID_BITS
        if 0 <= index < len(self.vehicles):
            return self.vehicles[index].camera.truth(frame_id)
        return None

    # ------------------------------------------------------------------------------------------- setup
    def _start_backend(self) -> str:
        from backend.app import create_app
        from backend.config import AuthConfig, BackendConfig, SessionConfig, VerifierConfig, VlmConfig
        from backend.serving import BackgroundServer
        from backend_tools.vlm_emulator import VlmEmulator

        vlm = VlmConfig()
        kind = self.verifier
        if kind in ("vlm", "cascade"):
            self._vlm = VlmEmulator(latency_s=self.options.vlm_latency_s).start()
            vlm = VlmConfig(base_url=self._vlm.base_url)
        config = BackendConfig(
            auth=AuthConfig(tokens=self.tokens, supervisor_token=self._supervisor_token),
            verifier=VerifierConfig(kind=kind),
            vlm=vlm,
            sessions=SessionConfig(sqlite_path=":memory:"),  # each run starts with nothing remembered
        )
        # The reject scenario needs the look-alike in the first keyframe: no random misses there.
        noise = DetectorNoise(miss_rate=self.scenario.miss_rate)
        if self.scenario.detector_curve:
            from cloudtrack.detection_curves import curve_for

            noise = replace(noise, curve=curve_for("person"))
        survey = self.scenario.survey
        if self.scenario.detector_in_range and survey is not None:
            noise = replace(noise, look_range_m=survey.search_range_m)
        self.detector = SimulatedPersonDetector(
            self._truth_lookup, self.camera.width, noise, seed=self.options.seed
        )
        self._app = create_app(config, detector=self.detector)
        self._backend = BackgroundServer(self._app).start()
        return str(self._backend.url)

    def _start_vehicle(self, index: int, backend_url: str) -> _Vehicle:
        origin = VEHICLE_ORIGINS[index % len(VEHICLE_ORIGINS)]
        vid = f"drone-{index + 1}"
        udp_port = _free_udp_port() if self.scenario.companion_listens else None
        personality = self.autopilots[index % len(self.autopilots)]
        follower: Any
        if personality in REAL_AUTOPILOTS:
            autopilot = self._start_real(index, origin, udp_port, personality)
            gcs = autopilot.gcs
            follower = autopilot.camera_pose(origin)
        else:
            autopilot, gcs, camera_url = self._start_mock(origin, udp_port, personality)
            follower = PoseFollower(camera_url, origin=origin).start()
        camera = CameraServer(
            self.world, self.camera, follower.pose, fps=30.0, frame_id_base=index << FRAME_ID_BITS
        )
        camera.epoch = math.inf  # people hold their start positions until the mission starts
        host, port = backend_url.removeprefix("http://").split(":")
        proxy = FaultProxy((host, int(port))).start()
        v = _Vehicle(
            index,
            vid,
            autopilot,
            follower,
            camera,
            proxy,
            gcs,
            self.work / f"{vid}-events.jsonl",
            self.work / f"{vid}-companion.log",
            origin=origin,
            companion_udp_port=udp_port,
            personality=personality,
        )
        camera.add_hook(partial(self._on_frame, v))
        camera.start()
        return v

    def _start_mock(
        self, origin: tuple[float, float], udp_port: int | None, personality: str
    ) -> tuple[Any, ScriptedGcs, str]:
        from sitl.autopilot import AutopilotOptions, SimulatedAutopilot
        from sitl.autopilot_mission import MissionOptions

        lat, lon = _home(origin)
        survey = self.scenario.survey
        options = AutopilotOptions(
            personality=personality,
            start_height_m=ALTITUDE_M,
            home_lat=lat,
            home_lon=lon,
            guid_timeout_s=GUID_TIMEOUT_S,
            # The waypoint speed (WPNAV_SPEED / MPC_XY_CRUISE) the survey is flown at, after a resume too.
            mission=MissionOptions(speed_m_s=survey.speed_m_s if survey is not None else None),
        )
        # "ground": a second ground station's link, for `cloudtrack-gcs survey` (the operator's laptop).
        links = {name: "udpin:127.0.0.1:0" for name in ("gcs", "companion", "camera", "ground")}
        if udp_port is not None:
            links["companion"] = f"udpout:127.0.0.1:{udp_port}"  # the companion listens (udpin)
        autopilot = SimulatedAutopilot(options, links)
        autopilot.start()
        gcs = ScriptedGcs(f"udpout:127.0.0.1:{autopilot.link_port('gcs')}").start()
        return autopilot, gcs, f"udpout:127.0.0.1:{autopilot.link_port('camera')}"

    def _start_real(
        self, index: int, origin: tuple[float, float], udp_port: int | None, personality: str
    ) -> FlightStack:
        vid = f"drone-{index + 1}"
        if self.shared is not None:
            self.shared.reuse(udp_port)
            self.progress(f"{vid}: {self.shared.describe()}, used before")
            return self.shared
        lat, lon = _home(origin)
        survey = self.scenario.survey
        # AUTO flies at WPNAV_SPEED (cm/s) after a resume: a DO_CHANGE_SPEED before the break-off no longer holds.
        params = (
            {"WPNAV_SPEED": survey.speed_m_s * 100.0}
            if survey is not None and personality == "arducopter"
            else {}
        )
        autopilot = start_flight_stack(
            personality,
            self.flight_stacks[personality],
            self.work / f"{vid}-{personality}",
            (lat, lon, HOME_ALT_M),
            udp_port,
            speedup=self.options.speedup,
            extra_params=params,
            # A fleet's ArduCopters are system 1, 2, ... as a team's would be; other scenarios keep 1 (each
            # vehicle on its own links). PX4 takes its instance's (N+1) either way.
            system_id=index + 1 if self.scenario.fleet is not None else 1,
        )
        self.progress(f"{vid}: {autopilot.describe()}")
        return autopilot

    def _start_companion(self, v: _Vehicle) -> None:
        v.events_path.unlink(missing_ok=True)  # a work dir may be reused: only this run's events count
        settings = [
            f"vehicle.id={v.vehicle_id}",
            f"camera.source={v.camera.url}",
            f"camera.mount_pitch_deg={MOUNT_PITCH_DEG}",
            "camera.hfov_deg=70.0",
            f"mavlink.connection={self._companion_link(v)}",
            f"mavlink.target_system={v.autopilot.system_id if v.real else 1}",
            f"backend.url={v.proxy.url}",
            f"tracker.name={self.tracker}",
            f"tracker.model_dir={self.model_dir}",
            f"behavior.standoff_m={STANDOFF_M}",
            f"recording.dir={self.work / 'records'}",
            *self._world_settings(),
            *self.scenario.companion_settings,
            *self.options.companion_settings,
        ]
        cmd = [
            sys.executable,
            "-m",
            "companion.cli",
            "--log-level",
            "INFO",
            "run",
            "--events-out",
            str(v.events_path),
        ]
        for s in settings:
            cmd += ["--set", s]
        env = dict(os.environ, CLOUDTRACK_BACKEND__TOKEN=self.tokens[v.vehicle_id], PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)
        with open(v.log_path, "wb") as log_file:
            v.process = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, env=env)

    def _world_settings(self) -> list[str]:
        """The companion's POD map is for the described person's posture where the world chose it (a map for
        someone standing says nothing of finding them lying)."""
        posture = self.world.extras.get("target_posture")
        return [f"search.posture={posture}"] if posture else []

    def _companion_link(self, v: _Vehicle) -> str:
        if v.companion_udp_port is not None:
            return f"udpin:127.0.0.1:{v.companion_udp_port}"
        if v.real:
            return f"udpout:127.0.0.1:{v.autopilot.bridge.udp_port}"
        return f"udpout:127.0.0.1:{v.autopilot.link_port('companion')}"

    def _on_frame(self, v: _Vehicle, frame: RenderedFrame) -> None:
        if self.epoch is None:
            return
        seen = _Seen(frame.frame_id, frame.time_s, frame.truth, frame.pose)
        v.frames.append(seen)
        v.frame_by_id[frame.frame_id] = seen
        if self.video is not None and v.index == 0:
            # Written VIDEO_DELAY frames late, so each frame gets the box the companion tracked on it.
            v.video_queue.append((frame.frame_id, frame.time_s, frame.image))
            while len(v.video_queue) > VIDEO_DELAY_FRAMES:
                self._write_video_frame(v)

    def _write_video_frame(self, v: _Vehicle) -> None:
        assert self.video is not None
        frame_id, t, image = v.video_queue.popleft()
        box = next((v.track_boxes[i] for i in range(frame_id, frame_id - 10, -1) if i in v.track_boxes), None)
        overlay = OverlayState(v.overlay.state, v.overlay.prompt, v.overlay.verdict, box)
        self.video.write(draw_overlay(image, overlay, t, v.vehicle_id))

    # -------------------------------------------------------------------------------------- event feed
    def _read_events(self, v: _Vehicle) -> list[dict[str, Any]]:
        if not v.events_path.exists():
            return []
        with open(v.events_path, encoding="utf-8") as f:
            f.seek(v.offset)
            data = f.read()
        end = data.rfind("\n")
        if end < 0:
            return []
        v.offset += len(data[: end + 1].encode("utf-8"))
        new = []
        for line in data[: end + 1].splitlines():
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue
            new.append(entry)
        v.events.extend(new)
        return new

    def _world_t(self, monotonic_t: float) -> float:
        return monotonic_t - (self.epoch or 0.0)

    def _person_at(
        self, v: _Vehicle, box_xywh: list[float] | None, t_world: float, frame_id: int = -1
    ) -> str:
        """Which person a companion box shows, judged on that frame (else the one rendered nearest in time)."""
        if not box_xywh or not v.frames:
            return "none"
        box = Box(*box_xywh)
        recent = v.frames[-300:]
        frame = v.frame_by_id.get(frame_id) or min(recent, key=lambda f: abs(f.time_s - t_world))
        best, best_iou = "none", 0.1
        for tb in frame.truth:
            overlap = iou(box, tb.box)
            if overlap > best_iou:
                best, best_iou = tb.person_id, overlap
        return best

    def _handle_event(self, v: _Vehicle, e: dict[str, Any]) -> None:
        kind = e.get("kind")
        t = self._world_t(float(e.get("t", 0.0)))
        if (
            kind == "RememberRejection"
        ):  # the companion took the supervisor's rejection (and tells the back-end)
            v.rejections_taken.append(t)
        if kind == "health" and e.get("healthy"):
            v.ready = True
        elif kind == "command" and e.get("command") == "StartMission":
            v.start_sent = None
            v.awaiting_id = ""
        elif kind == "state":
            v.state = str(e.get("state", ""))
            v.overlay = OverlayState(v.state, str(e.get("prompt", "")), v.overlay.verdict, v.overlay.box)
            self.say(f"{v.vehicle_id}: {v.state} ({e.get('reason', '')})")
            if v.state == "confirmed" and "supervisor" in str(e.get("reason", "")):
                v.confirmations.append((t, v.judged))
            if v.state != "awaiting_supervisor":
                v.decision_sent = None  # taken (or overtaken): nothing to repeat
        elif kind == "track":
            box = Box(*e["box"]) if e.get("box") and e.get("trusted") else None
            v.track_boxes[int(e.get("frame_id", 0))] = box
            if len(v.track_boxes) > 300:
                v.track_boxes.pop(next(iter(v.track_boxes)))
        elif kind in ("tracker_init", "reinit"):
            pid = self._person_at(v, e.get("box"), t, int(e.get("keyframe_id", -1)))
            v.proposals.append((t, pid))
            if kind == "tracker_init":
                self.say(f"{v.vehicle_id}: tracking candidate {e.get('candidate_id')} -> {pid}")
        elif kind == "candidate_report":
            v.overlay = OverlayState(
                v.overlay.state,
                v.overlay.prompt,
                f"{e.get('verdict')}: {e.get('justification', '')[:40]}",
                v.overlay.box,
            )
            cid = str(e.get("candidate_id", ""))
            if e.get("status") == "confirmed":
                if v.state != "confirmed":
                    # Confirmed while the track was lost ("CONFIRMED while lost": the find is the track's kept
                    # estimate, and it re-detects), or after the search left it (out of view, the survey flew
                    # on): the state is not CONFIRMED, but it is a find.
                    v.confirmations.append((t, v.judged))
                if cid == v.awaiting_id:
                    v.awaiting_id = ""
            if e.get("status") == "queued" and cid not in v.judgements:
                # Seen beside the tracked one, decided once it is the one shown: judged now, on its keyframe.
                pid = self._person_at(v, e.get("box"), t, int(e.get("keyframe_id", -1)))
                v.proposals.append((t, pid))
                v.judgements[cid] = ("confirm" if pid == self.world.target_id else "reject", pid)
                self.say(f"{v.vehicle_id}: queued candidate {cid} -> {pid}")
            if e.get("status") == "awaiting":
                v.awaiting_id = cid
                if v.pending_decision is None or v.pending_decision[3] != cid:
                    # A new candidate (a decision due on the one before is dropped: candidate 0 now means
                    # this one). The box is the tracker's on one frame; judge that frame (its track event
                    # came first in the log), not the one rendered at the report's time: a companion lagging
                    # under load reports boxes of frames rendered well before.
                    # One put again out of view (left before a decision, once the one after it is decided)
                    # has no box in view: the supervisor judges it as when it was.
                    if v.state == "awaiting_supervisor" or cid not in v.judgements:
                        # A candidate reported with its keyframe is not the tracker's box (one from a keyframe
                        # stored through an outage, one put to the supervisor beside a confirmed find the
                        # tracker holds, one that left the view before its answer came): judged on that keyframe.
                        frame = int(e.get("keyframe_id", -1))
                        if frame < 0:
                            frame = self._frame_of(v, e.get("box"))
                        pid = self._person_at(v, e.get("box"), t, frame)
                        v.judgements[cid] = ("confirm" if pid == self.world.target_id else "reject", pid)
                    action, pid = v.judgements[cid]
                    v.pending_decision = (self.now() + self.scenario.supervisor_delay_s, action, pid, cid)
                    self.say(f"{v.vehicle_id}: supervisor sees {pid} ({e.get('verdict')}), will {action}")
        elif kind == "RememberRejection" and e.get("candidate_id") == v.awaiting_id:
            v.awaiting_id = ""
        elif kind == "hold":
            self.say(f"{v.vehicle_id}: HOLD ({e.get('reason')})")
        elif kind == "safety" and e.get("action") == "stop":
            self.say(f"{v.vehicle_id}: watchdog {e.get('reason')}: stop")

    @staticmethod
    def _frame_of(v: _Vehicle, box_xywh: list[float] | None) -> int:
        """The newest frame whose logged track box is `box_xywh` (both rounded alike by the companion); -1."""
        if not box_xywh:
            return -1
        box = Box(*box_xywh)
        return next((fid for fid, b in reversed(v.track_boxes.items()) if b == box), -1)

    def _send_start(self, v: _Vehicle, mission_id: int) -> None:
        v.start_sent = (self.now(), mission_id)
        v.gcs.start_mission(
            self.scenario.prompt, mission_id=mission_id, allow_engage=self.scenario.allow_engage
        )

    def _resend_start(self, v: _Vehicle) -> None:
        """A GCS operator repeats a start that the companion did not take (lost on a lossy link)."""
        if v.start_sent is not None and self.now() - v.start_sent[0] > 2.0:
            self.say(f"{v.vehicle_id}: no answer to mission start, sending it again")
            self._send_start(v, v.start_sent[1])

    def _supervise(self, v: _Vehicle) -> None:
        if v.decision_sent is not None and self.now() - v.decision_sent[0] > 2.0:
            # Still awaiting 2 s after the decision: the command was lost on the way (one COMMAND_LONG
            # through the autopilot's routing); a GCS operator presses the button again.
            action = v.decision_sent[1]
            self.say(f"{v.vehicle_id}: no answer to the supervisor's {action}, sending it again")
            if action == "confirm":
                v.gcs.confirm()
            else:
                v.gcs.reject()
            v.decision_sent = (self.now(), action)
        if v.pending_decision is None or self.now() < v.pending_decision[0]:
            return
        _, action, pid, cid = v.pending_decision
        v.pending_decision = None
        if cid != v.awaiting_id or v.state in ("idle", "aborted"):
            # Decided meanwhile (the page, a retry), or the mission ended. A candidate the search left
            # before the decision still awaits it: candidate 0 means it until another is put to the
            # supervisor, so the decision is sent whatever the vehicle does now.
            return
        if action == "confirm":
            v.judged = pid
            v.gcs.confirm()
        else:
            v.gcs.reject()
            v.rejections.append((self.now(), pid))
        if v.state == "awaiting_supervisor":
            v.decision_sent = (self.now(), action)
        self.say(f"{v.vehicle_id}: supervisor {action}s {pid}")

    def _fault_due(self, fault: Fault) -> float:
        """When `fault` is due in scenario seconds (infinity until its confirmation, or its approach to the
        described person, happened)."""
        if fault.near_target_m is not None:
            return self._near_target.get(fault.near_target_m, math.inf) + fault.after_confirm_s
        confirmations = self.vehicles[0].confirmations
        if len(confirmations) < fault.confirmation:
            return math.inf
        return confirmations[fault.confirmation - 1][0] + fault.after_confirm_s

    def _approach(self) -> None:
        """The first time the lead vehicle came within each fault's `near_target_m` of the described person."""
        lead = self.vehicles[0]
        if not lead.frames:
            return
        f = lead.frames[-1]
        tn, te, _ = self.world.person(self.world.target_id).state_at(f.time_s)
        distance = math.hypot(f.pose.north - tn, f.pose.east - te)
        for fault in self.scenario.faults:
            near = fault.near_target_m
            if near is not None and near not in self._near_target and distance <= near:
                self._near_target[near] = self.now()

    def _faults(self) -> None:
        self._approach()
        for i, fault in enumerate(self.scenario.faults):
            if i in self.faults_done or self.now() < self._fault_due(fault):
                continue
            self.faults_done.add(i)
            v = self.vehicles[fault.vehicle]
            self.fault_times[fault.kind] = self.now()
            self.say(f"FAULT {fault.kind} on {v.vehicle_id}")
            if fault.kind == "takeover":
                v.autopilot.set_mode(self._takeover_mode(v), source="pilot")
            elif fault.kind == "rc_takeover":
                self.fault_times["takeover"] = self.now()
                if v.real:
                    v.autopilot.rc_takeover()
                else:
                    from sitl.autopilot import RC_MODE_SWITCH_PWM

                    v.gcs.hold_rc_mode_switch(RC_MODE_SWITCH_PWM["LOITER"])
            elif fault.kind == "abort":
                v.gcs.abort()
            elif fault.kind == "fly_to":
                self._fly_to(v)
            elif fault.kind == "stall":
                assert v.process is not None
                os.kill(v.process.pid, signal.SIGSTOP)
            elif fault.kind == "resume":
                assert v.process is not None
                os.kill(v.process.pid, signal.SIGCONT)
                v.stall_resumed = time.monotonic()
            elif fault.kind == "flood":
                self._flood(v)
            elif fault.kind == "backend_down":
                v.proxy.cut()
            elif fault.kind == "backend_up":
                v.proxy.restore()
            elif fault.kind == "link_down":
                v.autopilot.set_link_down("companion", True)
            elif fault.kind == "link_up":
                v.autopilot.set_link_down("companion", False)
            elif fault.kind == "restart":
                v.pending_decision = None
                self._send_start(v, 2)

    def _takeover_mode(self, v: _Vehicle) -> str:
        return str(v.autopilot.takeover_mode) if v.real else TAKEOVER_MODE[v.personality]

    def _fly_to(self, v: _Vehicle) -> None:
        """The GCS takes the vehicle back: GUIDED, then a position target 15 m east of where it is."""
        pose = v.follower.pose()
        here = (pose.north, pose.east)
        there = (here[0] + FLY_TO_OFFSET_M[0], here[1] + FLY_TO_OFFSET_M[1])
        if v.real:
            v.autopilot.gcs_fly_to(there[0] - v.origin[0], there[1] - v.origin[1], pose.down)
        else:
            v.gcs.set_mode(4)  # GUIDED on ArduCopter
            time.sleep(0.1)
            v.gcs.fly_to(there[0] - v.origin[0], there[1] - v.origin[1], pose.down)
        v.fly_to = (self.now(), here, there)
        self.say(
            f"{v.vehicle_id}: GCS fly-to ({there[0]:.1f}, {there[1]:.1f}) from ({here[0]:.1f}, {here[1]:.1f})"
        )

    def _flood(self, v: _Vehicle) -> None:
        """200 one-datagram UDP senders at the companion's port (a GCS heartbeat, garbage, or a forged
        autopilot heartbeat in the pilot's takeover mode); each then listens for what comes back."""
        import threading

        assert v.companion_udp_port is not None, "the flood scenario needs the companion listening on UDP"
        from pymavlink import mavutil

        forged = self._forged_takeover_heartbeat(v)
        socks = []
        for i in range(FLOOD_SENDERS):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            mav = mavutil.mavlink.MAVLink(None, srcSystem=100 + i % 100, srcComponent=1)
            hb = mav.heartbeat_encode(
                mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            datagram = (hb.pack(mav), os.urandom(40), forged)[i % 3]
            s.sendto(datagram, ("127.0.0.1", v.companion_udp_port))
            socks.append(s)
        v.flood = {"senders": FLOOD_SENDERS, "datagrams": 0, "setpoints": 0}

        def listen() -> None:
            import select

            parser = mavutil.mavlink.MAVLink(None)
            parser.robust_parsing = True
            end = time.monotonic() + 6.0
            while time.monotonic() < end and not self._stopping:
                ready, _, _ = select.select(socks, [], [], 0.2)
                for s in ready:
                    try:
                        data = s.recv(65535)
                    except OSError:
                        continue
                    v.flood["datagrams"] += 1
                    try:
                        msgs = parser.parse_buffer(data) or []
                    except Exception:
                        msgs = []
                    v.flood["setpoints"] += sum(
                        1 for m in msgs if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
                    )
            for s in socks:
                s.close()

        t = threading.Thread(target=listen, name="flood-listener", daemon=True)
        t.start()
        self._flood_threads.append(t)

    def _forged_takeover_heartbeat(self, v: _Vehicle) -> bytes:
        """The autopilot's own system id announcing the pilot's takeover mode, from a stranger's socket: a
        companion that believed it would stop following (the flood check sees that)."""
        from pymavlink import mavutil

        px4 = "px4" in v.personality
        custom = self._mode_number(v, self._takeover_mode(v))
        mav = mavutil.mavlink.MAVLink(None, srcSystem=getattr(v.autopilot, "system_id", 1), srcComponent=1)
        heartbeat = mav.heartbeat_encode(
            mavutil.mavlink.MAV_TYPE_QUADROTOR,
            mavutil.mavlink.MAV_AUTOPILOT_PX4 if px4 else mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            custom,
            mavutil.mavlink.MAV_STATE_ACTIVE,
        )
        return bytes(heartbeat.pack(mav))

    def _finished(self) -> bool:
        if any(v.process is not None and v.process.poll() is not None for v in self.vehicles):
            self.say("a companion process exited early")
            return True
        if self.now() > self.scenario.max_s:
            self.say("time limit reached")
            return True
        if self.scenario.fleet is not None:
            return self._fleet_finished()
        if self.scenario.whole_survey:
            done = [self._survey_completed(v) for v in self.vehicles]
            ends = [t for t in done if t is not None]
            return len(ends) == len(done) and self.now() >= max(ends) + SURVEY_END_GRACE_S
        if not all(v.confirmations for v in self.vehicles):
            return False
        if len(self.faults_done) < len(self.scenario.faults):
            return False
        t_confirm = self.vehicles[0].confirmations[0][0]
        if self.scenario.survey is not None and "rejected_never_again" in self.scenario.checks:
            # A survey meets the look-alike and the described person in either order: both must be decided.
            if not all(v.rejections for v in self.vehicles):
                return False
            t_confirm = max(t_confirm, *(v.rejections[0][0] for v in self.vehicles))
        last_fault = max((self._fault_due(f) for f in self.scenario.faults), default=t_confirm)
        return self.now() >= max(t_confirm + self.scenario.follow_s, last_fault + 4.0)

    # ---------------------------------------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        # The runner is the world's real time: its camera, the autopilot bridge and the pilot are threads of
        # this process, so a full garbage collection stops them all. Over a long test session's heap one took
        # 0.61 s (760k objects), past PX4's COM_OF_LOSS_T and the companion's frame watchdog: the flight then
        # failed on the harness's pause, not the companion's. The objects that exist before the flight are
        # left out of collection while it runs.
        gc.freeze()
        self._pauses.start()
        try:
            return self._run()
        finally:
            self._teardown()
            self._pauses.stop()
            gc.unfreeze()

    def _run(self) -> dict[str, Any]:
        s = self.scenario
        self.progress(
            f"scenario {s.name}: {s.summary} ({self.personality}, seed {self.options.seed}, "
            f"tracker {self.tracker}, work dir {self.work})"
        )
        backend_url = self._start_backend()
        self.vehicles = [self._start_vehicle(i, backend_url) for i in range(s.vehicles)]
        for v in self.vehicles:
            self._start_companion(v)
        if self.shared is not None:  # the GCS brings it back while the companion starts
            took = self.shared.return_home(ALTITUDE_M, self.progress)
            self.progress(f"drone-1: back over home in HOLD after {took:.1f} s")
        elif self.real:
            for v in self.vehicles:  # the pilot arms and takes off; the companion never does
                if not v.real:
                    continue  # a mock autopilot starts airborne
                took = v.autopilot.fly_up(ALTITUDE_M, progress=self.progress)
                self.progress(
                    f"{v.vehicle_id}: airborne at {ALTITUDE_M:g} m in {v.autopilot.mode_name()} after "
                    f"{took:.1f} s, SITL at real time"
                )
        deadline = time.monotonic() + self.options.startup_timeout_s
        while not all(v.ready for v in self.vehicles):
            for v in self.vehicles:
                for e in self._read_events(v):
                    if e.get("kind") == "health" and e.get("healthy"):
                        v.ready = True
                if v.process is not None and v.process.poll() is not None:
                    raise RuntimeError(
                        f"{v.vehicle_id} companion exited during start-up:\n{self._log_tail(v)}"
                    )
            if time.monotonic() > deadline:
                raise RuntimeError(
                    "companions not ready in time:\n" + "\n".join(self._log_tail(v) for v in self.vehicles)
                )
            time.sleep(0.1)
        if s.fleet is not None:
            self._fly_fleet_survey()
        elif s.survey is not None:
            for v in self.vehicles:
                self._fly_survey(v)
        if self.options.video_out is not None:
            self.video = VideoWriter(self.options.video_out, 30.0, (self.camera.width, self.camera.height))
        self.epoch = time.monotonic()
        for v in self.vehicles:
            v.camera.epoch = self.epoch
            self._send_start(v, 1)
        self.say(f"mission started: {s.prompt!r}")
        while not self._finished():
            for v in self.vehicles:
                for e in self._read_events(v):
                    self._handle_event(v, e)
                self._supervise(v)
                self._resend_start(v)
            self._faults()
            self._poll_statuses()
            self._fleet_step()
            time.sleep(0.05)
        end_t = self.now()
        for t in self._flood_threads:
            t.join(timeout=7.0)
        self._stop_companions()
        for v in self.vehicles:
            for e in self._read_events(v):
                self._handle_event(v, e)
        return self._results(end_t)

    # ------------------------------------------------------------------------------------------ survey
    def _fly_survey(self, v: _Vehicle, timeout_s: float = 30.0) -> None:
        """As the operator and the pilot would: upload the survey over the scenario's area with
        `cloudtrack-gcs survey` (a second ground station's link, the camera and safety sections of the
        companion's configuration), then select AUTO (ArduPilot) / Mission (PX4); returns once the autopilot
        flies it."""
        spec = self.scenario.survey
        assert spec is not None
        (s_n, w_e), (n_n, e_e) = spec.area_ne
        o_n, o_e = v.origin  # the area is given from the vehicle's home; the world is from the first home
        centre = _home((o_n + (s_n + n_n) / 2.0, o_e + (w_e + e_e) / 2.0))
        vehicle_config = self.work / f"{v.vehicle_id}-survey.toml"
        vehicle_config.write_text(
            f"[camera]\nhfov_deg = {math.degrees(2 * math.atan(self.camera.cx / self.camera.fx)):.6f}\n"
            f"mount_pitch_deg = {MOUNT_PITCH_DEG}\nsearch_range_m = {spec.search_range_m}\n"
        )
        for msg_id, hz in ((0, 10.0), (42, 4.0)):  # HEARTBEAT (modes), MISSION_CURRENT (the item flown)
            v.gcs.request_interval(msg_id, hz)
        cmd = [
            sys.executable, "-m", "gcs.cli", "--connect", self._ground_url(v), "--timeout", "15", "--system",
            str(v.autopilot.system_id if v.real else 1),
            "survey", "--centre", f"{centre[0]:.7f},{centre[1]:.7f}", "--size", f"{e_e - w_e:g}x{n_n - s_n:g}",
            "--altitude", f"{spec.altitude_m:g}", "--overlap", f"{spec.overlap:g}", "--speed",
            f"{spec.speed_m_s:g}", "--companion-config", str(vehicle_config),
        ]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=dict(os.environ))
        lines = [line.strip() for line in (done.stdout + done.stderr).splitlines() if line.strip()]
        for line in lines:
            self.progress(f"{v.vehicle_id}: cloudtrack-gcs survey: {line}")
        if done.returncode != 0:
            raise RuntimeError(
                f"{v.vehicle_id}: cloudtrack-gcs survey exited {done.returncode}: {lines[-1:]}"
            )
        v.survey = {"command": " ".join(cmd[2:]), "output": lines}
        self._select_mission_mode(v, timeout_s)

    def _select_mission_mode(self, v: _Vehicle, timeout_s: float = 30.0) -> None:
        """The pilot selects AUTO / Mission; returns once the autopilot flies its mission."""
        mode = MISSION_MODE[v.personality]
        v.autopilot.set_mode(mode, source="pilot")
        deadline = time.monotonic() + timeout_s
        while not (v.gcs.modes and v.gcs.modes[-1][1] == self._mode_number(v, mode)):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{v.vehicle_id}: the autopilot did not enter {mode} for the survey")
            time.sleep(0.1)
        time.sleep(0.5)  # the companion's telemetry shows the mission flying before the mission starts
        self.progress(f"{v.vehicle_id}: the pilot switched to {mode}: flying the survey")

    def _survey_completed(self, v: _Vehicle) -> float | None:
        """When the autopilot reported the survey complete (scenario seconds); None while it has not."""
        at = v.gcs.mission_complete_at
        return None if at is None or self.epoch is None or at < self.epoch else at - self.epoch

    # ------------------------------------------------------------------------------------------- fleet
    def _survey_config(self, name: str) -> Path:
        """The camera section `cloudtrack-gcs survey` / `replan` plan the lanes with (the companion's)."""
        spec = self.scenario.survey
        assert spec is not None
        path = self.work / name
        path.write_text(
            f"[camera]\nhfov_deg = {math.degrees(2 * math.atan(self.camera.cx / self.camera.fx)):.6f}\n"
            f"mount_pitch_deg = {MOUNT_PITCH_DEG}\nsearch_range_m = {spec.search_range_m}\n"
        )
        return path

    def _fly_fleet_survey(self, timeout_s: float = 30.0) -> None:
        """As a team would: ONE `cloudtrack-gcs survey --fleet FILE` splits the area over the vehicles and
        uploads each part to its own autopilot (each on its own second ground link), then each pilot selects
        AUTO / Mission. The area is the world's (from the first vehicle's home)."""
        spec, fleet = self.scenario.survey, self.scenario.fleet
        assert spec is not None and fleet is not None
        (s_n, w_e), (n_n, e_e) = spec.area_ne
        centre = _home(((s_n + n_n) / 2.0, (w_e + e_e) / 2.0))
        config = self._survey_config("fleet-survey.toml")
        members = []
        for v in self.vehicles:
            lat, lon = _home(v.origin)
            system = v.autopilot.system_id if v.real else 1
            members.append(
                {"id": v.vehicle_id, "connect": self._ground_url(v), "speed": spec.speed_m_s,
                 "lat": round(lat, 7), "lon": round(lon, 7), "system": system}
            )  # fmt: skip
            for msg_id, hz in ((0, 10.0), (42, 4.0)):  # HEARTBEAT (modes), MISSION_CURRENT (the item flown)
                v.gcs.request_interval(msg_id, hz)
        fleet_file = self.work / "fleet.json"
        fleet_file.write_text(json.dumps({"vehicles": members}, indent=2))
        self._fleet_files = (fleet_file, config)
        cmd = [
            sys.executable, "-m", "gcs.cli", "--timeout", "15",
            "survey", "--centre", f"{centre[0]:.7f},{centre[1]:.7f}", "--size", f"{e_e - w_e:g}x{n_n - s_n:g}",
            "--altitude", f"{spec.altitude_m:g}", "--overlap", f"{spec.overlap:g}", "--companion-config", str(config),
            "--fleet", str(fleet_file),
        ]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=dict(os.environ))
        lines = [line.strip() for line in (done.stdout + done.stderr).splitlines() if line.strip()]
        for line in lines:
            self.progress(f"cloudtrack-gcs survey --fleet: {line}")
        parts: dict[str, dict[str, Any]] = {}
        whole: dict[str, Any] = {}
        for line in lines:
            if (m := FLEET_PART.match(line)) is not None:
                parts[m["id"]] = {
                    "lanes": m["lanes"], "length_m": int(m["length"]), "area_ha": float(m["ha"]),
                    "transit_m": int(m["transit"]), "time_s": 60 * int(m["min"]) + int(m["sec"]),
                    "speed_m_s": float(m["speed"]), "items": int(m["items"]), "line": line,
                }  # fmt: skip
            elif (m := FLEET_WHOLE.match(line)) is not None:
                whole = {
                    "whole_area_s": 60 * int(m["min"]) + int(m["sec"]),
                    "finishes_last": m["last"],
                    "one_vehicle_alone_s": 60 * int(m["amin"]) + int(m["asec"]),
                    "one_vehicle_alone": m["alone"],
                }
        self._fleet = {
            "mission_id": str(fleet.mission_id),
            "survey": {
                "command": "cloudtrack-gcs " + " ".join(cmd[3:]),
                "exit_code": done.returncode,
                "output": lines,
                "parts": parts,
                "whole_area_s": whole.get("whole_area_s"),
                "one_vehicle_alone_s": whole.get("one_vehicle_alone_s"),
                **{k: v for k, v in whole.items() if k not in ("whole_area_s", "one_vehicle_alone_s")},
            },
            "dropout": {"vehicle": self.vehicles[fleet.leaves].vehicle_id},
            "replan": None,
            "coverage_history": [],
            "coverage_at_end": None,
            "time_to_cover_s": None,
        }
        if done.returncode != 0:
            raise RuntimeError(f"cloudtrack-gcs survey --fleet exited {done.returncode}: {lines[-1:]}")
        for v in self.vehicles:
            v.survey = {"part": parts.get(v.vehicle_id)}
            self._select_mission_mode(v, timeout_s)
            if v.index == fleet.leaves:
                part_s = (parts.get(v.vehicle_id) or {}).get("time_s", 0.0)
                self._leave_at = time.monotonic() + fleet.leaves_at * part_s

    def _fleet_step(self) -> None:
        """The fleet's pilot and operator: the leaving vehicle sent home on time, the back-end's merged map
        and drop-outs read, the re-plan run once the drop-out is listed (in the background: the supervisor
        goes on meanwhile), its result collected."""
        fleet = self.scenario.fleet
        if fleet is None or self.epoch is None:
            return
        dropout = self._fleet["dropout"]
        leaving = self.vehicles[fleet.leaves]
        if "rtl_s" not in dropout and time.monotonic() >= self._leave_at:
            leaving.autopilot.set_mode("RTL", source="pilot")
            dropout["rtl_s"] = round(self.now(), 2)
            self.fault_times["rtl"] = self.now()
            self.say(f"FAULT rtl on {leaving.vehicle_id}: the pilot sends it home")
        if self._replan is not None:
            proc, out_path, started = self._replan
            if proc.poll() is not None:
                lines = [x.strip() for x in out_path.read_text(errors="replace").splitlines() if x.strip()]
                for line in lines:
                    self.progress(f"cloudtrack-gcs replan: {line}")
                self._fleet["replan"].update(
                    exit_code=proc.returncode, output=lines, took_s=round(time.monotonic() - started, 2)
                )
                self._replan = None
        if self.now() - self._fleet_last_poll < FLEET_POLL_S:
            return
        self._fleet_last_poll = self.now()
        merged = self._supervisor_get(f"/v1/missions/{fleet.mission_id}/map")
        coverage = None if merged is None else merged.get("coverage")
        if merged is not None and coverage is not None:
            history = self._fleet["coverage_history"]
            if not history or history[-1][1] != round(coverage, 3):
                history.append([round(self.now(), 2), round(coverage, 3)])
            self._fleet["coverage_at_end"] = round(coverage, 4)
            self._fleet["merged_vehicles"] = merged.get("vehicles")
            if self._fleet["time_to_cover_s"] is None and coverage >= fleet.min_coverage:
                self._fleet["time_to_cover_s"] = round(self.now(), 2)
                self.say(f"the merged coverage is {coverage:.3f}: the area is covered")
        if "rtl_s" in dropout and "listed_s" not in dropout:
            answer = self._supervisor_get(f"/v1/missions/{fleet.mission_id}/dropouts")
            listed = [
                d for d in (answer or {}).get("dropouts", []) if d.get("vehicle_id") == leaving.vehicle_id
            ]
            if listed:
                d = listed[0]
                (self.work / "dropouts.json").write_text(  # what the re-plan was given, and the map then
                    json.dumps({"dropouts": answer, "map": merged}, indent=1)
                )
                dropout.update(
                    listed_s=round(self.now(), 2), kind=d.get("kind"), reason=d.get("reason"),
                    unflown_m2=d.get("area_m2") if d.get("area_known", True) else None,
                    searching=answer.get("searching") if answer else None,
                )  # fmt: skip
                self.say(
                    f"the back-end lists {leaving.vehicle_id} as dropped out ({d.get('reason')}, "
                    + (
                        f"{d.get('area_m2', 0.0):.0f} m2 unflown"
                        if d.get("area_known", True)
                        else "its part unknown: it reported no search area"
                    )
                    + "): re-planning"
                )
                self._start_replan()

    def _start_replan(self) -> None:
        """`cloudtrack-gcs replan` as the operator runs it: the fleet file the survey took, the back-end and its
        supervisor token from a file; its output is collected by `_fleet_step` when it exits."""
        spec, fleet = self.scenario.survey, self.scenario.fleet
        assert spec is not None and fleet is not None and self._fleet_files is not None
        fleet_file, config = self._fleet_files
        token = self.work / "supervisor.token"
        token.write_text(self._supervisor_token)
        token.chmod(0o600)
        cmd = [
            sys.executable, "-m", "gcs.cli", "--timeout", "15",
            "replan", "--mission", str(fleet.mission_id), "--fleet", str(fleet_file), "--altitude",
            f"{spec.altitude_m:g}", "--overlap", f"{spec.overlap:g}", "--companion-config", str(config),
            "--backend", str(self._backend.url), "--supervisor-token-file", str(token),
        ]  # fmt: skip
        out_path = self.work / "replan.out"
        with open(out_path, "wb") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=dict(os.environ))
        self._replan = (proc, out_path, time.monotonic())
        self._fleet["replan"] = {
            "command": "cloudtrack-gcs " + " ".join(cmd[3:]),
            "started_s": round(self.now(), 2),
        }

    def _supervisor_get(self, path: str) -> dict[str, Any] | None:
        import requests

        try:
            r = requests.get(
                f"{self._backend.url}{path}",
                headers={"Authorization": f"Bearer {self._supervisor_token}"},
                timeout=1.0,
            )
        except requests.RequestException:
            return None
        return r.json() if r.status_code == 200 else None

    def _fleet_finished(self) -> bool:
        """The area covered (merged), the described person found and the re-plan over (or failed)."""
        f = self._fleet
        covered: float | None = f.get("time_to_cover_s")
        found = [t for v in self.vehicles for t, pid in v.confirmations if pid == self.world.target_id]
        replanned = (f.get("replan") or {}).get("exit_code") is not None
        if covered is None or not found or not replanned:
            return False
        return self.now() >= max(covered, min(found)) + self.scenario.follow_s

    def _fleet_results(self, outcomes: list[VehicleOutcome]) -> dict[str, Any]:
        """The fleet's figures for the JSON and the checks: the survey's parts and times, the drop-out and the
        re-plan, the merged coverage, the mission's finds on the back-end (one per person), the rejections."""
        fleet = self.scenario.fleet
        assert fleet is not None
        out = dict(self._fleet)
        if self._replan is not None:  # still running at the end
            out["replan"] = {**(out.get("replan") or {}), "exit_code": None, "output": ["(still running)"]}
        sessions = self._app.state.sessions if self._app is not None else None
        finds = [] if sessions is None else sessions.mission_finds(str(fleet.mission_id))
        person = self.world.person(self.world.target_id)
        out["finds"] = []
        for find in finds:
            north, east = _world(*find.position)
            t = (find.seen_at or find.time) - (time.time() - time.monotonic()) - (self.epoch or 0.0)
            tn, te, _ = person.state_at(max(0.0, t))
            out["finds"].append(
                {"vehicle_id": find.vehicle_id, "candidate_id": find.candidate_id,
                 "position": list(find.position), "error_m": round(math.hypot(north - tn, east - te), 2),
                 **self._heading_at_find(find.vehicle_id, max(0.0, t), (tn, te))}
            )  # fmt: skip
        out["sightings"] = (
            []
            if sessions is None
            else [
                {"vehicle_id": s.vehicle_id, "same_as": s.same_as}
                for v in self.vehicles
                for s in sessions.sightings(v.vehicle_id, str(fleet.mission_id))
            ]
        )
        out["rejections"] = [
            {"vehicle_id": v.vehicle_id, "t": round(t, 2), "person": pid}
            for v, o in zip(self.vehicles, outcomes, strict=True)
            for t, pid in o.rejected_ids
        ]
        taken = [t for v in self.vehicles for t in v.rejections_taken]
        out["first_rejection_taken_s"] = round(min(taken), 2) if taken else None
        merged = self._supervisor_get(f"/v1/missions/{fleet.mission_id}/map")
        if merged is not None:
            out["uncovered_m2"] = _uncovered_m2(merged)
            (self.work / "mission-map.json").write_text(json.dumps(merged))
        out["confirmations"] = [
            {"vehicle_id": v.vehicle_id, "t": round(t, 2), "person": pid}
            for v in self.vehicles
            for t, pid in v.confirmations
        ]
        out["time_to_cover_whole_area_s"] = out.get("time_to_cover_s")
        return out

    def _mode_number(self, v: _Vehicle, name: str) -> int:
        """HEARTBEAT.custom_mode of a mode, as the GCS sees it."""
        return int(v.autopilot.custom_mode(name)) if v.real else _custom_mode(v.personality, name)

    def _ground_url(self, v: _Vehicle) -> str:
        """Where a second ground station (the operator's laptop) connects to the vehicle's autopilot."""
        if v.real:
            return str(v.autopilot.ground_url())
        return f"udpout:127.0.0.1:{v.autopilot.link_port('ground')}"

    def _poll_statuses(self) -> None:
        """The back-end's status of each vehicle, twice a second, as the supervisor page sees it (search
        scenarios: coverage and the find come from there)."""
        if self.scenario.survey is None or self._backend is None or self.now() - self._last_poll < 0.5:
            return
        import requests

        self._last_poll = self.now()
        for v in self.vehicles:
            try:
                r = requests.get(
                    f"{self._backend.url}/v1/vehicles/{v.vehicle_id}/status",
                    headers={"Authorization": f"Bearer {self._supervisor_token}"},
                    timeout=1.0,
                )
            except requests.RequestException:
                continue
            if r.status_code == 200:
                v.statuses.append((self.now(), r.json()))

    def _mission_breaks(self, v: _Vehicle) -> list[dict[str, Any]]:
        """Every time the autopilot left its mission after the start, and where it resumed: from its own
        HEARTBEAT and MISSION_CURRENT on the GCS link (the autopilot's account, not the companion's)."""
        epoch = self.epoch or 0.0
        auto = self._mode_number(v, MISSION_MODE[v.personality])
        currents = list(v.gcs.mission_currents)
        breaks: list[dict[str, Any]] = []
        in_mission: bool | None = None
        for t, mode, _ in list(v.gcs.modes):
            now_in = mode == auto
            if in_mission is True and not now_in and t >= epoch:
                before = [seq for tc, seq in currents if tc <= t]
                breaks.append(
                    {
                        "left_t": round(t - epoch, 2),
                        "left_at": before[-1] if before else None,
                        "resumed_at": None,
                    }
                )
            elif in_mission is False and now_in and breaks and breaks[-1]["resumed_at"] is None:
                after = [seq for tc, seq in currents if tc > t + 0.1]
                breaks[-1]["resumed_t"] = round(t - epoch, 2)
                breaks[-1]["resumed_at"] = after[0] if after else None
            in_mission = now_in
        return breaks

    def _search_metrics(self, v: _Vehicle, confirm_t: float | None) -> dict[str, Any]:
        """Time to find, coverage and the find's position error at the find, the mission's break-offs and
        resumes, and what the companion sent the autopilot during the search."""
        out: dict[str, Any] = {"survey": v.survey, "mission_breaks": self._mission_breaks(v)}
        out["found"] = confirm_t is not None
        out["time_to_find_s"] = None if confirm_t is None else round(confirm_t, 2)
        sighted = [t for t, pid in v.proposals if pid == self.world.target_id]
        out["time_to_first_sighting_s"] = round(sighted[0], 2) if sighted else None
        after = [st for t, st in v.statuses if confirm_t is not None and t >= confirm_t and st.get("find")]
        coverage = [
            (st.get("search") or {}).get("coverage")
            for t, st in v.statuses
            if confirm_t is not None and t >= confirm_t
        ]
        out["coverage_at_find"] = next((c for c in coverage if c is not None), None)
        last = v.statuses[-1][1] if v.statuses else {}
        out["coverage_at_end"] = (last.get("search") or {}).get("coverage")
        out["geolocation_error_m"] = None
        if after and confirm_t is not None:
            find = after[0]["find"]
            lat, lon = find["position"]
            north = math.radians(lat - _home((0.0, 0.0))[0]) * EARTH_RADIUS
            east = (
                math.radians(lon - _home((0.0, 0.0))[1])
                * EARTH_RADIUS
                * math.cos(math.radians(_home((0.0, 0.0))[0]))
            )
            person = self.world.person(self.world.target_id)
            tn, te, _ = person.state_at(confirm_t)
            out["find"] = {k: find.get(k) for k in ("candidate_id", "position", "sigma_m", "confirmed_by")}
            stored = self._stored_candidates(v)
            if find.get("candidate_id") in stored:  # found from a keyframe kept through an outage
                out["find"].update(stored=True, seen_s=stored[find["candidate_id"]])
            out["geolocation_error_m"] = round(math.hypot(north - tn, east - te), 2)
            if find.get("seen_at") is not None:
                # How old the find's position is, and its error against where the person was then: the
                # estimate's own error, apart from how far the person has walked since.
                age = float(find["time"]) - float(find["seen_at"])
                sn, se, _ = person.state_at(max(0.0, confirm_t - age))
                out["find"]["seen_before_confirm_s"] = round(age, 2)
                out["geolocation_error_at_seen_m"] = round(math.hypot(north - sn, east - se), 2)
        out["survey_completed_s"] = self._survey_completed(v)
        out["keyframes"] = next(
            (st["keyframes"] for _, st in reversed(v.statuses) if st.get("keyframes")), None
        )
        out.update(self._pod_metrics(v))
        down, up = self.fault_times.get("backend_down"), self.fault_times.get("backend_up")
        if down is not None:
            # The POD at the person through the outage (the statuses the back-end held then) and after it.
            history = out["pod_at_target_history"]
            before = [value for t, value in history if up is None or t <= up]
            rise = next((t for t, value in history if value > 0.0), None)
            out["outage"] = {
                "down_s": round(down, 2),
                "up_s": None if up is None else round(up, 2),
                "pod_at_target_to_up": max(before) if before else None,
                "pod_at_target_rose_s": rise,
                "pod_at_target_end": out["pod_at_target"],
            }
        # The mock records the companion's commands itself; a real autopilot's bridge records them on the way.
        commands = v.autopilot.bridge.commands if v.real else getattr(v.autopilot, "commands", None)
        if commands is not None:
            epoch = self.epoch or 0.0
            setpoints = [
                sp for sp in list(v.autopilot.setpoints) if sp.link == "companion" and sp.time >= epoch
            ]
            modes = [c for c in list(commands) if c[1] == "companion" and c[2] == 176 and c[0] >= epoch]
            out["companion_commands"] = {"setpoints": len(setpoints), "mode_commands": len(modes)}
        return out

    def _stored_candidates(self, v: _Vehicle) -> dict[str, float | None]:
        """Candidates the companion reported from keyframes stored through an outage: id -> when seen
        (scenario seconds)."""
        out: dict[str, float | None] = {}
        for e in v.events:
            if e.get("kind") == "candidate_report" and e.get("stored"):
                seen = float(e.get("seen_s", math.nan))
                out[str(e.get("candidate_id"))] = (
                    round(self._world_t(seen), 2) if math.isfinite(seen) else None
                )
        return out

    def _pod_metrics(self, v: _Vehicle) -> dict[str, Any]:
        """The POD map the companion reported (`search.pod` of the statuses the back-end held): its mean, the
        share of the area at POD >= 0.8 and the POD where the described person was, at the end and whenever
        it changed; with the curve-driven detector, its own passes over the person (the model's POD there)."""
        import numpy as np

        from cloudtrack.pod_map import decode_grid, grid_value

        person = self.world.person(self.world.target_id)
        out: dict[str, Any] = {"pod_mean": None, "pod_share_at_0_8": None, "pod_at_target": None}
        out["target"] = {"place": self.scenario.place, "posture": person.pose}
        history: list[list[float]] = []
        last: tuple[float, dict[str, Any]] | None = None
        for t, status in v.statuses:
            report = (status.get("search") or {}).get("pod")
            if not report:
                continue
            n, e, _ = person.state_at(t)
            value = grid_value(report, *_home((n, e)))
            if value is not None and (not history or history[-1][1] != round(value, 4)):
                history.append([round(t, 2), round(value, 4)])
            last = (t, report)
        out["pod_at_target_history"] = history
        if last is not None:
            t, report = last
            grid = decode_grid(report)
            inside = grid[~np.isnan(grid)]
            n, e, _ = person.state_at(t)
            at = grid_value(report, *_home((n, e)))
            out["pod_mean"] = round(float(inside.mean()), 4)
            out["pod_share_at_0_8"] = round(float(np.mean(inside >= 0.8 - 1e-9)), 4)
            out["pod_at_target"] = None if at is None else round(at, 4)
            out["pod_looks"] = report.get("looks")
            out["pod_posture"] = report.get("posture")
            out["target"].update(north=round(n, 2), east=round(e, 2))
        if self.detector is not None and self.detector.noise.curve is not None:
            passes = self.detector.passes(self.world.target_id)
            out["detector_passes"] = [
                {
                    "from_s": round(x.first_s, 2),
                    "to_s": round(x.last_s, 2),
                    "looks": x.looks,
                    "best_p": round(x.best, 4),
                    "best_size_px": round(x.best_size_px, 1),
                    "latent": round(x.latent, 4),
                    "reported": x.reported,
                }
                for x in passes
            ]
            out["detector_pod_at_target"] = round(1.0 - math.prod(1.0 - x.best for x in passes), 4)
        return out

    def _log_tail(self, v: _Vehicle, lines: int = 25) -> str:
        try:
            text = v.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return f"{v.vehicle_id}: no log"
        return f"--- {v.vehicle_id} companion log ({v.log_path}) ---\n" + "\n".join(text[-lines:])

    def _stop_companions(self) -> None:
        for v in self.vehicles:
            if v.process is not None and v.process.poll() is None:
                if "stall" in self.fault_times and v.stall_resumed is None:
                    v.process.send_signal(signal.SIGCONT)
                v.process.send_signal(signal.SIGTERM)
        for v in self.vehicles:
            if v.process is None:
                continue
            started = time.monotonic()
            try:
                v.process.wait(timeout=5.0)
                v.stop_s = time.monotonic() - started
                self.say(
                    f"{v.vehicle_id}: companion exited {v.process.returncode} {v.stop_s:.2f} s after SIGTERM"
                )
            except subprocess.TimeoutExpired:
                v.process.kill()
                v.process.wait()
                self.say(f"{v.vehicle_id}: companion did not stop within 5 s of SIGTERM: killed")

    def _teardown(self) -> None:
        self._stopping = True
        for v in self.vehicles:
            if v.process is not None and v.process.poll() is None:
                v.process.kill()
                v.process.wait()
        for v in self.vehicles:
            v.camera.stop()  # no frame hook runs while the video is flushed
        if self.video is not None:
            for v in self.vehicles[:1]:
                while v.video_queue:
                    self._write_video_frame(v)
            self.video.close()
        for v in self.vehicles:
            parts = (v.gcs.stop, v.follower.stop, v.proxy.stop, v.autopilot.close)
            for stop in parts if self.shared is None else (v.proxy.stop,):
                try:
                    stop()
                except Exception as exc:  # tear everything down even if one part is already broken
                    self.progress(f"teardown: {exc}")
        if self._backend is not None:
            self._backend.stop()
        if self._vlm is not None:
            self._vlm.stop()
        if self._own_work:
            shutil.rmtree(self.work, ignore_errors=True)

    # ------------------------------------------------------------------------------------------ scoring
    def _outcome(self, v: _Vehicle, end_t: float) -> VehicleOutcome:
        target = self.world.target_id
        samples: list[FrameSample] = []
        hidden: list[tuple[float, bool]] = []
        for f in v.frames:
            tb = next((x for x in f.truth if x.person_id == target), None)
            tn, te, _ = self.world.person(target).state_at(f.time_s)
            samples.append(
                FrameSample(
                    f.time_s,
                    f.pose.north,
                    f.pose.east,
                    tn,
                    te,
                    tb.box if tb else None,
                    tb.visible if tb else 0.0,
                )
            )
            hidden.append((f.time_s, tb is None or tb.visible < 0.2))
        epoch = self.epoch or 0.0
        setpoints = [
            SetpointSample(sp.time - epoch, sp.vx, sp.vy, sp.vz, sp.yaw_rate)
            for sp in list(v.autopilot.setpoints)
            if sp.link == "companion"
        ]
        events: list[TimedEvent] = []
        for e in v.events:
            t = self._world_t(float(e.get("t", 0.0)))
            kind = e.get("kind")
            if kind == "state":
                events.append(TimedEvent(t, "state", {"state": e.get("state")}))
                if e.get("state") == "confirmed":
                    events.append(TimedEvent(t, "confirmed"))
            elif kind == "answer" and any(c.get("verdict") == "yes" for c in e.get("candidates", [])):
                if not any(x.kind == "candidate" for x in events):
                    # the first "yes", early (a cascade's local answer) or final
                    events.append(TimedEvent(t, "candidate", {"early": not e.get("final", True)}))
                if e.get("final", True) and not any(x.kind == "verified" for x in events):
                    events.append(TimedEvent(t, "verified"))  # the final verifier's first "yes"
            elif kind == "reinit":
                events.append(TimedEvent(t, "reinit"))
            elif kind in ("hold", "release"):  # a release (stop, hold mode, silence) stops the vehicle too
                events.append(TimedEvent(t, "hold", {"reason": e.get("reason", ""), "action": kind}))
            elif kind == "safety":
                events.append(
                    TimedEvent(
                        t,
                        "watchdog",
                        {"reason": e.get("reason"), "action": e.get("action"), "detail": e.get("detail", "")},
                    )
                )
        for name, t in self.fault_times.items():
            events.append(
                TimedEvent(
                    t,
                    {"takeover": "mode_change", "backend_down": "backend_lost", "link_down": "link_lost"}.get(
                        name, "fault"
                    ),
                    {"fault": name},
                )
            )
        follow = following_intervals([e for e in events if e.kind == "state"], end_t)

        def following_after(t0: float) -> float:
            n = 0
            for s in samples:
                if (
                    s.t > t0
                    and any(a <= s.t <= b for a, b in follow)
                    and s.target_box is not None
                    and s.target_visible >= 0.3
                ):
                    n += 1
            return n / 30.0

        occlusion = None
        t_confirm = v.confirmations[0][0] if v.confirmations else math.inf
        run_start = None
        for t, is_hidden in hidden:
            if t < t_confirm:
                continue
            if is_hidden and run_start is None:
                run_start = t
            elif not is_hidden and run_start is not None:
                if occlusion is None or t - run_start > occlusion[1] - occlusion[0]:
                    occlusion = (run_start, t)
                run_start = None
        takeover_t = self.fault_times.get("takeover")
        late = None
        mode_seen_after: float | None = None
        if takeover_t is not None:
            mode_times = [
                t - epoch for t, _, source in v.autopilot.mode_history if source.startswith("pilot")
            ]
            takeover_t = mode_times[0] if mode_times else takeover_t
            if v.real:
                # The real autopilot changes mode some time after the pilot's action (the RC switch is
                # debounced for 200 ms); the stop latency counts from the HEARTBEAT that reported the change.
                wanted = v.autopilot.custom_mode(v.autopilot.takeover_mode)
                seen = [
                    t - epoch
                    for t, mode, _ in list(v.gcs.modes)
                    if t - epoch >= takeover_t and mode == wanted
                ]
                if seen:
                    mode_seen_after = seen[0] - takeover_t
                    takeover_t = seen[0]
            after = [sp.t for sp in setpoints if sp.t > takeover_t]
            late = (max(after) - takeover_t) if after else 0.0
        holds = tuple(
            e.t
            for e in events
            if e.kind == "hold" or (e.kind == "watchdog" and e.detail.get("action") == "stop")
        )
        metrics = summarise(
            samples,
            setpoints,
            events,
            STANDOFF_M,
            (self.camera.width, self.camera.height),
            end_t,
            outcome="pending",
            frozen=self._frozen(v, end_t),
            unflown=self._unflown(v, end_t),
        )
        metrics["last_setpoint_after_takeover_s"] = None if late is None else round(late, 3)
        if mode_seen_after is not None:
            metrics["takeover_mode_reported_after_action_s"] = round(mode_seen_after, 3)
        metrics["occlusion_s"] = (
            None if occlusion is None else [round(occlusion[0], 2), round(occlusion[1], 2)]
        )
        metrics["frames_rendered"] = len(v.frames)
        # Whether the search moved on a cascade's early (local) answer rather than waiting for its final one.
        metrics["first_candidate_early"] = next(
            (x.detail["early"] for x in events if x.kind == "candidate"), None
        )
        # ArduCopter flies a setpoint only in GUIDED, PX4 only in OFFBOARD: those are the accepted ones.
        active = self._flying_mode(v)
        metrics["setpoints_accepted"] = sum(
            1 for sp in list(v.autopilot.setpoints) if sp.link == "companion" and sp.mode == active
        )
        # Each time the vehicle leaves that mode (the companion's own hold or hand-back, a pilot's takeover)
        # one setpoint can already be on its way: the companion learns the new mode from the next HEARTBEAT.
        number = self._mode_number(v, active)
        modes = [mode for _, mode, _ in list(v.gcs.modes)]
        metrics["left_active_mode"] = sum(1 for a, b in pairwise(modes) if a == number != b)
        track = [(f.time_s, f.pose.north, f.pose.east) for f in v.frames]
        metrics["coasted_m"] = {
            kind: round(distance_coasted(track, t), 2)
            for kind, t in self.fault_times.items()
            if kind in COASTING_FAULTS
        }
        metrics.update(self._fault_metrics(v, setpoints))
        metrics.update(self._position_metrics(v, end_t))
        if self.scenario.survey is not None:
            found = [t for t, pid in v.confirmations if pid == target]
            metrics.update(self._search_metrics(v, found[0] if found else None))
        return VehicleOutcome(
            metrics=metrics,
            confirmations=tuple(t for t, _ in v.confirmations),
            confirmed_ids=tuple(pid for _, pid in v.confirmations),
            proposals=tuple(v.proposals),
            rejected_ids=tuple(v.rejections),
            lost_intervals=(),
            occlusion=occlusion,
            last_setpoint_after_takeover_s=late,
            takeover_t=takeover_t,
            hold_times=holds,
            following_after=following_after,
        )

    def _fault_metrics(self, v: _Vehicle, setpoints: list[SetpointSample]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if v.fly_to is not None:
            t0, here, there = v.fly_to
            start = math.dist(here, there)
            closest = min(
                (
                    math.dist((f.pose.north, f.pose.east), there)
                    for f in v.frames
                    if t0 <= f.time_s <= t0 + 8.0
                ),
                default=start,
            )
            out["fly_to_progress_m"] = round(
                start - closest, 2
            )  # how far it got toward the GCS target in 8 s
            # The companion must have let go: no setpoint of its own while the GCS flies the vehicle.
            out["setpoints_during_fly_to"] = sum(1 for sp in setpoints if sp.t >= t0)
        if "abort" in self.fault_times:
            t_abort = self.fault_times["abort"]
            # The explicit zero-velocity stop (and one more in flight at most), then silence.
            out["setpoints_after_abort"] = sum(1 for sp in setpoints if sp.t >= t_abort + 0.05)
        if v.stall_resumed is not None:
            resumed = v.stall_resumed - (self.epoch or 0.0)
            texts = [(t - (self.epoch or 0.0), text) for t, text in v.gcs.statustexts]
            cause = [(t, text) for t, text in texts if t >= resumed - 0.5 and "stall" in text.lower()]
            out["stall_reported"] = (
                None if not cause else {"after_s": round(cause[0][0] - resumed, 3), "text": cause[0][1]}
            )
            out["statustexts_after_resume"] = [
                text for t, text in texts if resumed - 0.5 <= t <= resumed + 3.0
            ][:10]
            after = [sp for sp in setpoints if sp.t >= resumed]
            out["first_setpoint_after_resume"] = (
                None
                if not after
                else {
                    "after_s": round(after[0].t - resumed, 3),
                    "speed_m_s": round(after[0].horizontal_speed, 3),
                }
            )
        if v.real and "stall" in self.fault_times:
            out["autopilot_during_stall"] = self._autopilot_during_stall(v)
        if v.flood:
            out["flood"] = dict(v.flood)
        return out

    def _position_metrics(self, v: _Vehicle, end_t: float) -> dict[str, Any]:
        """The find's geolocation error: the FOUND position the GCS heard against where the target truly was
        then. Where the camera renders the truth rather than the autopilot's estimate (PX4's SIH), also how
        far the estimate the companion flies on was from the truth during the mission."""
        out: dict[str, Any] = {}
        epoch = self.epoch or 0.0
        found = next(
            ((t, m) for t, text in list(v.gcs.statustexts) if (m := FOUND_TEXT.search(text)) is not None),
            None,
        )
        if found is not None:
            t, match = found
            north, east = _world(float(match[1]), float(match[2]))
            tn, te, _ = self.world.person(self.world.target_id).state_at(t - epoch)
            out["geolocation_error_m"] = round(math.hypot(north - tn, east - te), 2)
            out["find_sigma_m"] = float(match[3])
        samples = self._pose_samples(v, end_t)
        if samples is not None:
            out["estimate_error"] = estimate_error(*samples)
        return out

    def _heading_at_find(self, vehicle_id: str, t: float, person: tuple[float, float]) -> dict[str, float]:
        """The finder's autopilot heading error when the find was seen, and its range to the person then: the
        companion places a find from the heading it is told, so an error of e degrees at range r moves the
        find r sin(e) metres across the line of sight (PX4's SIH estimate has been seen 13 degrees off its
        ground truth mid-lane). Empty where the vehicle has no ground truth apart from its estimate."""
        v = next((v for v in self.vehicles if v.vehicle_id == vehicle_id), None)
        samples = None if v is None else self._pose_samples(v, math.inf)
        if v is None or samples is None:
            return {}
        error = heading_error_at(*samples, t)
        at = min(samples[1], key=lambda p: abs(p.t - t), default=None)
        if error is None or at is None:
            return {}
        range_m = math.hypot(person[0] - at.north, person[1] - at.east)
        return {"heading_error_deg": round(error, 1), "range_m": round(range_m, 1)}

    def _pose_samples(self, v: _Vehicle, end_t: float) -> tuple[list[PoseSample], list[PoseSample]] | None:
        """What the autopilot told (its estimate) and the real vehicle (the SITL's ground truth), in scenario
        time up to `end_t`; None where the vehicle has no ground truth apart from its estimate (the mock)."""
        epoch = self.epoch or 0.0
        history = getattr(v.follower, "history", None)
        if not history or not v.gcs.estimates:
            return None
        estimates = [
            PoseSample(t - epoch, *_world(lat, lon), HOME_ALT_M - alt, heading)
            for t, lat, lon, alt, heading in list(v.gcs.estimates)
            if 0.0 <= t - epoch <= end_t
        ]
        truth = [
            PoseSample(t - epoch, p.north, p.east, p.down, math.degrees(p.yaw))
            for t, p in list(history)
            if -1.0 <= t - epoch <= end_t + 1.0
        ]
        return estimates, truth

    def _frozen(self, v: _Vehicle, end_t: float) -> list[tuple[float, float]]:
        """When `v`'s companion process was stopped (the `stall` fault until its `resume`)."""
        stalled = (
            any(f.kind == "stall" and self.vehicles[f.vehicle] is v for f in self.scenario.faults)
            and "stall" in self.fault_times
        )
        if not stalled:
            return []
        return [(self.fault_times["stall"], self.fault_times.get("resume", end_t))]

    def _flying_mode(self, v: _Vehicle) -> str:
        """The mode in which `v`'s autopilot flies the companion's setpoints: GUIDED, or OFFBOARD on PX4."""
        return str(
            v.autopilot.offboard_mode if v.real else "OFFBOARD" if v.personality == "px4" else "GUIDED"
        )

    def _unflown(self, v: _Vehicle, end_t: float) -> list[tuple[float, float]]:
        """When `v`'s autopilot was not in the mode that flies the companion's setpoints (GUIDED, OFFBOARD), as
        its HEARTBEATs on the GCS link show."""
        epoch = self.epoch or 0.0
        active = self._mode_number(v, self._flying_mode(v))
        intervals: list[tuple[float, float]] = []
        since: float | None = None  # start of the current interval outside the active mode
        for t, mode, _ in list(v.gcs.modes):
            if mode != active and since is None:
                since = t - epoch
            elif mode == active and since is not None:
                intervals.append((since, t - epoch))
                since = None
        if since is not None:
            intervals.append((since, end_t))
        return intervals

    def _autopilot_during_stall(self, v: _Vehicle) -> dict[str, Any]:
        """What the real autopilot did while the companion was frozen: its first mode change (PX4 leaves
        OFFBOARD after COM_OF_LOSS_T; ArduCopter stays in GUIDED and stops after GUID_TIMEOUT) and what it
        told the GCS."""
        epoch = self.epoch or 0.0
        t_stall = self.fault_times["stall"]
        t_resume = self.fault_times.get("resume", math.inf)
        modes = [(t - epoch, m) for t, m, _ in list(v.gcs.modes)]
        before = [m for t, m in modes if t < t_stall]
        change = next(((t, m) for t, m in modes if t >= t_stall and before and m != before[-1]), None)
        # PX4 times its offboard loss from the last setpoint it had, which is up to a setpoint period before
        # the freeze.
        last_setpoint = max(
            (
                sp.time - epoch
                for sp in list(v.autopilot.setpoints)
                if sp.link == "companion" and sp.time - epoch <= t_stall
            ),
            default=None,
        )
        return {
            "mode_before": v.autopilot.mode_of(before[-1]) if before else None,
            "mode_change": None
            if change is None
            else {
                "mode": v.autopilot.mode_of(change[1]),
                "after_s": round(change[0] - t_stall, 3),
                "after_last_setpoint_s": None
                if last_setpoint is None
                else round(change[0] - last_setpoint, 3),
            },
            "texts": [text for t, text in v.gcs.statustexts if t_stall <= t - epoch <= t_resume][:10],
        }

    def _results(self, end_t: float) -> dict[str, Any]:
        s = self.scenario
        outcomes = [self._outcome(v, end_t) for v in self.vehicles]
        for v, o in zip(self.vehicles, outcomes, strict=True):
            o.metrics["companion_stop_s"] = None if v.stop_s is None else round(v.stop_s, 3)
            o.metrics["companion_exit_code"] = v.process.returncode if v.process is not None else None
        fleet = self._fleet_results(outcomes) if s.fleet is not None else None
        failures = assess(s, outcomes, self.fault_times, [v.personality for v in self.vehicles], fleet)
        pauses = [(p.began - (self.epoch or 0.0), p.length_s) for p in self._pauses.pauses()]
        if failures:
            failures += [
                f"the runner itself paused {length:.2f} s at {at:.1f} s (its camera, autopilot bridge and "
                f"pilot with it): what failed may be the harness's pause, not the companion"
                for at, length in pauses
            ]
        outcome = "pass" if not failures else "fail"
        results: dict[str, Any] = {
            "scenario": s.name,
            "summary": s.summary,
            "autopilot": self.personality,
            "seed": self.options.seed,
            "place": s.place,
            "tracker": self.tracker,
            "verifier": self.verifier,
            "prompt": s.prompt,
            "outcome": outcome,
            "failures": failures,
            "duration_s": round(end_t, 2),
            "faults": {k: round(t, 2) for k, t in self.fault_times.items()},
            "runner_pauses": [{"at_s": round(at, 2), "length_s": length} for at, length in pauses],
            "vehicles": {},
            "work_dir": None if self._own_work else str(self.work),
        }
        if fleet is not None:
            results["fleet"] = fleet
        for v, o in zip(self.vehicles, outcomes, strict=True):
            o.metrics["outcome"] = outcome
            o.metrics["confirmed"] = list(o.confirmed_ids)
            o.metrics["rejected"] = [pid for _, pid in o.rejected_ids]
            o.metrics["proposed"] = [pid for _, pid in o.proposals]
            o.metrics["autopilot"] = v.personality
            results["vehicles"][v.vehicle_id] = o.metrics
        if self.options.json_out is not None:
            self.options.json_out.parent.mkdir(parents=True, exist_ok=True)
            self.options.json_out.write_text(json.dumps(results, indent=2))
        if self.options.plot_out is not None:
            from sitl.trajectory_plot import plot_trajectories

            tracks = {v.vehicle_id: [self._sample(f) for f in v.frames] for v in self.vehicles}
            events = {
                v.vehicle_id: [TimedEvent(t, "confirmed") for t in o.confirmations]
                + [TimedEvent(t, "hold") for t in o.hold_times[:3]]
                for v, o in zip(self.vehicles, outcomes, strict=True)
            }
            others = {
                p.person_id + f" ({p.shirt})": [p.state_at(0.0)[:2]]
                for p in self.world.people
                if p.person_id != self.world.target_id
            }
            plot_trajectories(self.options.plot_out, tracks, events, f"{s.name}: {outcome}", others)
        return results

    def _sample(self, f: _Seen) -> FrameSample:
        tn, te, _ = self.world.person(self.world.target_id).state_at(f.time_s)
        return FrameSample(f.time_s, f.pose.north, f.pose.east, tn, te, None)


def _world(lat: float, lon: float) -> tuple[float, float]:
    """World north/east (metres) of a latitude/longitude: the inverse of `_home`."""
    north = math.radians(lat - HOME_LAT) * EARTH_RADIUS
    east = math.radians(lon - HOME_LON) * EARTH_RADIUS * math.cos(math.radians(HOME_LAT))
    return north, east


def _uncovered_m2(merged: dict[str, Any]) -> float | None:
    """The merged map's area left uncovered (m2)."""
    import shapely

    from backend.mission_merge import _metres
    from cloudtrack.coverage import LocalFrame, geometry_from_rings

    area, covered = merged.get("area") or [], merged.get("covered") or []
    if not area or not area[0]:
        return None
    frame = LocalFrame(float(area[0][0][0]), float(area[0][0][1]))

    def metres(rings: list[Any]) -> Any:
        return shapely.make_valid(_metres(geometry_from_rings(rings), frame))

    left = metres(area).difference(metres(covered)) if covered else metres(area)
    return round(float(left.area), 1)


def _custom_mode(personality: str, name: str) -> int:
    """HEARTBEAT.custom_mode of a mode, as the GCS sees it (ArduCopter's number; PX4 main << 16 | sub << 24)."""
    from sitl.autopilot import ARDUCOPTER_MODES, PX4_MODES

    if personality == "px4":
        main, sub = PX4_MODES[name]
        return (main << 16) | (sub << 24)
    return ARDUCOPTER_MODES[name]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_scenario(scenario: Scenario, options: RunOptions, progress: Progress = print) -> dict[str, Any]:
    return ScenarioRun(scenario, options, progress).run()
