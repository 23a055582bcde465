"""`cloudtrack-backend bench --capacity`: how many searching vehicles one back-end serves, beside what its
detector alone could do on the same cores.

- The limit of this hardware: the configured detector (YOLOX-nano, `[detector] tiles` as configured)
  run back to back on real keyframes in as many threads as the machine has cores, one onnxruntime thread
  each: keyframes per second, nothing else (no HTTP, no verifier, no store); measured before and after
  the fleets, the faster taken (on a shared machine one 10 s measurement can be halved by other work).
- Capacity: a real `cloudtrack-backend serve` with its default configuration (the `local` verifier, no
  emulated delay; the SQLite store on disk) and N simulated vehicles, each sending a keyframe every
  1 / `rate_hz` seconds the companion's way (JPEG at 640 px, quality 80; at most `in_flight` requests
  out, a keyframe due while they are all out is skipped as the companion replaces it). N is served when
  the answers' p95 is within `p95_bound_s` and at most 1 % of the keyframes due were refused or
  skipped. N doubles until it is not served, then the last gap is bisected.
The ratio of keyframes per second served at capacity to the detector's raw rate says how close the whole
service comes to its detector; per keyframe the CPU goes to the detector, the verifier and everything
else (HTTP, decoding, the store): the server's CPU per keyframe, event loop and worker threads, is
printed beside it.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import requests

from backend.config import BackendConfig, load_backend_config
from backend.detectors.factory import build_detector
from backend_tools.fleet_bench import fleet_tokens
from backend_tools.fleet_services import BackendProcess
from cloudtrack.api_client import encode_keyframe

PROMPT = "a man in a gray shirt"
# Real keyframes: the dev sequences' people as a searching drone sees them (640 px wide, as sent).
KEYFRAME_SOURCES = (
    "uav123_person12_1",
    "dtb70_Surfing06",
    "uav123_wakeboard7",
    "uav123_group1_1",
    "otb_Crossing",
)
KEYFRAME_INDICES = (1, 21, 41, 61)
# The companion's defaults ([backend] max_keyframe_width, jpeg_quality, max_requests_in_flight).
KEYFRAME_WIDTH, KEYFRAME_QUALITY, IN_FLIGHT = 640, 80, 4


@dataclass(frozen=True)
class CapacitySettings:
    rate_hz: float = 2.0  # a searching vehicle's keyframes ([backend] search_interval_s = 0.5 s)
    p95_bound_s: float = 1.0  # two search intervals: an answer later than that is about an old view
    trial_s: float = 20.0
    warmup_s: float = 3.0
    max_vehicles: int = 64
    max_refused: float = 0.01  # share of due keyframes refused (non-200) or skipped (all in flight)


@dataclass
class Trial:
    vehicles: int
    due: int = 0
    answered: int = 0
    refused: int = 0
    skipped: int = 0
    p50_s: float = float("nan")
    p95_s: float = float("nan")
    keyframes_per_s: float = 0.0
    codes: dict[str, int] = field(default_factory=dict)
    # The server's own timings of the answered keyframes (median, p95), and its CPU seconds per keyframe
    # on its event loop and in its worker threads (decode, detect, verify, store).
    timings: dict[str, list[float]] = field(default_factory=dict)
    cpu_per_keyframe_ms: dict[str, float] = field(default_factory=dict)

    def served(self, settings: CapacitySettings) -> bool:
        lost = self.refused + self.skipped
        return (
            self.answered > 0
            and self.p95_s <= settings.p95_bound_s
            and lost <= settings.max_refused * max(1, self.due)
        )


def keyframes(sequences: Path) -> list[bytes]:
    """JPEG keyframes as the companion sends them, from real frames of the dev sequences."""
    found = []
    for name in KEYFRAME_SOURCES:
        for index in KEYFRAME_INDICES:
            image = cv2.imread(str(sequences / name / "frames" / f"{index:06d}.jpg"))
            if image is None:
                raise FileNotFoundError(f"{sequences / name} frame {index} (set --data or CLOUDTRACK_SHARED)")
            found.append(encode_keyframe(image, KEYFRAME_WIDTH, KEYFRAME_QUALITY)[0])
    return found


def decoded(jpegs: Sequence[bytes]) -> list[np.ndarray]:
    return [np.asarray(cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR)) for j in jpegs]


def raw_detector_rate(
    config: BackendConfig, frames: Sequence[np.ndarray], seconds: float = 10.0
) -> dict[str, Any]:
    """Keyframes per second of the configured detector alone: one thread per core, one onnxruntime thread each."""
    cores = os.cpu_count() or 1
    detectors = [
        build_detector(config.detector.model_copy(update={"threads": 1, "parallel_tiles": False}))
        for _ in range(cores)
    ]
    for detector in detectors:  # warm up: first runs allocate
        detector.detect(frames[0], ["person"])
    counts = [0] * cores
    stop = time.monotonic() + seconds

    def run(k: int) -> None:
        i = k
        while time.monotonic() < stop:
            detectors[k].detect(frames[i % len(frames)], ["person"])
            counts[k] += 1
            i += cores

    threads = [threading.Thread(target=run, args=(k,)) for k in range(cores)]
    started = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - started
    return {"cores": cores, "keyframes": sum(counts), "keyframes_per_s": sum(counts) / wall}


def hardware_limit(first: dict[str, Any], last: dict[str, Any]) -> dict[str, Any]:
    """The detector's raw rate measured before and after the fleets: the faster is the hardware's limit (other
    work on a shared machine only ever slows a measurement down); both are kept."""
    best = max(first, last, key=lambda r: float(r["keyframes_per_s"]))
    return {**best, "measured_keyframes_per_s": [first["keyframes_per_s"], last["keyframes_per_s"]]}


def _cpu_s(stat_file: Path) -> float:
    fields = stat_file.read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of the server's event loop (its main thread) and of all its other threads together
    (decode, detect, verify, store). The process's own count keeps what threads that ended used; Python
    3.11 gives its threads no OS names, so they are not told apart further."""
    total = _cpu_s(Path(f"/proc/{pid}/stat"))
    loop = _cpu_s(Path(f"/proc/{pid}/task/{pid}/stat"))
    return {"event loop": loop, "worker threads": total - loop}


def vehicle_trial(
    url: str,
    tokens: dict[str, str],
    n: int,
    jpegs: Sequence[bytes],
    settings: CapacitySettings,
    server_pid: int | None = None,
) -> Trial:
    """N vehicles, each due a keyframe every 1 / rate_hz s (staggered), at most IN_FLIGHT out at once."""
    vehicles = list(tokens)[:n]
    trial = Trial(vehicles=n)
    latencies: list[float] = []
    lock = threading.Lock()
    local = threading.local()
    period = 1.0 / settings.rate_hz
    start = time.monotonic() + 0.5
    measure_from = start + settings.warmup_s
    end = measure_from + settings.trial_s
    outstanding = dict.fromkeys(vehicles, 0)
    timings: dict[str, list[float]] = {}
    cpu_from: dict[str, float] = {}

    def send(vehicle: str, frame_id: int, due: float) -> None:
        session = getattr(local, "session", None)
        if session is None:
            session = local.session = requests.Session()
        meta = {
            "vehicle_id": vehicle,
            "mission_id": f"capacity-{vehicle}",
            "prompt": PROMPT,
            "frame_id": frame_id,
        }
        code = "error"
        try:
            answer = session.post(
                f"{url}/v1/detect",
                files={"image": ("k.jpg", jpegs[frame_id % len(jpegs)], "image/jpeg")},
                data={"meta": json.dumps(meta)},
                headers={"Authorization": f"Bearer {tokens[vehicle]}"},
                timeout=30,
            )
            code = str(answer.status_code)
            server_timings = answer.json()["timings"] if code == "200" else {}
        except (requests.RequestException, ValueError, KeyError):
            server_timings = {}
        took = time.monotonic() - due
        with lock:
            outstanding[vehicle] -= 1
            if due >= measure_from:
                trial.codes[code] = trial.codes.get(code, 0) + 1
                if code == "200":
                    trial.answered += 1
                    latencies.append(took)
                    for key, value in server_timings.items():
                        timings.setdefault(key, []).append(value)
                else:
                    trial.refused += 1

    with ThreadPoolExecutor(max_workers=n * IN_FLIGHT) as pool:
        schedule = sorted(
            (start + k * period / n + i * period, k, i)
            for k in range(n)
            for i in range(int((end - start) / period) + 1)
        )
        for due, k, i in schedule:
            if due >= end:
                continue
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if server_pid is not None and not cpu_from and due >= measure_from:
                cpu_from = thread_cpu(server_pid)
            vehicle = vehicles[k]
            with lock:
                counted = due >= measure_from
                trial.due += counted
                if outstanding[vehicle] >= IN_FLIGHT:  # the companion replaces a keyframe it cannot send
                    trial.skipped += counted
                    continue
                outstanding[vehicle] += 1
            pool.submit(send, vehicle, k * 100_000 + i, due)
        cpu_to = thread_cpu(server_pid) if server_pid is not None and cpu_from else {}
    if latencies:
        trial.p50_s = float(np.percentile(latencies, 50))
        trial.p95_s = float(np.percentile(latencies, 95))
    trial.keyframes_per_s = trial.answered / settings.trial_s
    trial.timings = {k: [float(np.median(v)), float(np.percentile(v, 95))] for k, v in timings.items()}
    if trial.answered and cpu_to:
        trial.cpu_per_keyframe_ms = {
            k: 1000 * (cpu_to[k] - cpu_from.get(k, 0.0)) / trial.answered for k in sorted(cpu_to)
        }
    return trial


def find_capacity(
    trial: Callable[[int], Trial], settings: CapacitySettings, say: Callable[[str], None]
) -> tuple[int, list[Trial]]:
    """The most vehicles served: doubling from 1 until a trial fails, then bisecting the last gap."""
    tried: dict[int, Trial] = {}

    def served(n: int) -> bool:
        if n not in tried:
            tried[n] = trial(n)
            t = tried[n]
            say(
                f"    {n} vehicles: p95 {t.p95_s:.2f} s, {t.keyframes_per_s:.1f} keyframes/s, "
                f"refused {t.refused}, skipped {t.skipped} of {t.due}: "
                f"{'served' if t.served(settings) else 'NOT served'}"
            )
        return tried[n].served(settings)

    good, bad = 0, 0
    n = 1
    while n <= settings.max_vehicles:
        if not served(n):
            bad = n
            break
        good, n = n, n * 2
    if bad:
        while bad - good > 1:
            middle = (good + bad) // 2
            good, bad = (middle, bad) if served(middle) else (good, middle)
    return good, [tried[k] for k in sorted(tried)]


@dataclass(frozen=True)
class Configuration:
    """What one capacity run serves: settings over the defaults, and the source tree (None: this one)."""

    label: str
    settings: tuple[str, ...] = ()
    tree: Path | None = None


def capacity(
    configuration: Configuration,
    model_setting: str,
    jpegs: Sequence[bytes],
    settings: CapacitySettings,
    say: Callable[[str], None],
) -> dict[str, Any]:
    """One configuration's capacity: a `serve` process with these settings, vehicles added until not served."""
    tokens = fleet_tokens(settings.max_vehicles)
    label, server_settings = configuration.label, [model_setting, *configuration.settings]
    with tempfile.TemporaryDirectory(prefix="cloudtrack-capacity-") as folder:
        store = json.dumps(str(Path(folder) / "sessions.sqlite3"))
        server = BackendProcess(
            [f"sessions.sqlite_path={store}", *server_settings], tokens, source_tree=configuration.tree
        )
        try:
            server.wait_ready()
            tree = f" (the code of {configuration.tree})" if configuration.tree else ""
            say(f"  {label}: {' '.join(configuration.settings) or 'defaults'}{tree}")
            best, trials = find_capacity(
                lambda n: vehicle_trial(server.url, tokens, n, jpegs, settings, server.pid), settings, say
            )
        finally:
            server.stop()
    at = next((t for t in trials if t.vehicles == best), None)
    return {
        "label": label,
        "settings": list(configuration.settings),
        "tree": str(configuration.tree) if configuration.tree else None,
        "vehicles": best,
        "keyframes_per_s": at.keyframes_per_s if at else 0.0,
        "p95_s": at.p95_s if at else float("nan"),
        "timings": at.timings if at else {},
        "cpu_per_keyframe_ms": at.cpu_per_keyframe_ms if at else {},
        "trials": [asdict(t) for t in trials],
    }


def capacity_report(
    model_dir: Path,
    sequences: Path,
    settings: CapacitySettings,
    configurations: Sequence[Configuration],
    say: Callable[[str], None],
) -> dict[str, Any]:
    """The raw detector rate and each configuration's capacity, measured in one run."""
    model = f"detector.model_dir={json.dumps(str(model_dir))}"
    jpegs = keyframes(sequences)
    config = load_backend_config(None, [model], environ={})
    say("  the detector alone, one thread per core ...")
    first = raw_detector_rate(config, decoded(jpegs))
    say(f"    {first['keyframes_per_s']:.1f} keyframes/s on {first['cores']} cores")
    runs = [capacity(configuration, model, jpegs, settings, say) for configuration in configurations]
    say("  the detector alone again ...")
    last = raw_detector_rate(config, decoded(jpegs))
    say(f"    {last['keyframes_per_s']:.1f} keyframes/s")
    raw = hardware_limit(first, last)
    for run in runs:
        run["ratio"] = run["keyframes_per_s"] / raw["keyframes_per_s"]
    return {
        "settings": asdict(settings),
        "prompt": PROMPT,
        "load_average_1min": os.getloadavg()[0],
        "raw_detector": raw,
        "runs": runs,
    }


def print_capacity(report: dict[str, Any]) -> None:
    s, raw = report["settings"], report["raw_detector"]
    print(
        f"Capacity: vehicles served at {s['rate_hz']:g} keyframes/s each with p95 <= {s['p95_bound_s']:g} s "
        f"(<= {100 * s['max_refused']:g} % refused or skipped), local verifier, {raw['cores']} cores; raw detector "
        f"{' and '.join(f'{v:.1f}' for v in raw.get('measured_keyframes_per_s', []))} keyframes/s before and "
        "after the fleets, the faster taken:"
    )
    print("| configuration | vehicles | keyframes/s | p95 [s] | raw detector [keyframes/s] | ratio |")
    print("|---|---|---|---|---|---|")
    for run in report["runs"]:
        print(
            f"| {run['label']} | {run['vehicles']} | {run['keyframes_per_s']:.1f} | {run['p95_s']:.2f} | "
            f"{raw['keyframes_per_s']:.1f} | {run['ratio']:.2f} |"
        )
    for run in report["runs"]:
        timings = ", ".join(f"{k} {1000 * v[0]:.0f}/{1000 * v[1]:.0f}" for k, v in run["timings"].items())
        cpu = ", ".join(f"{k} {v:.0f}" for k, v in run["cpu_per_keyframe_ms"].items())
        print(f"{run['label']} at capacity: server timings median/p95 ms: {timings}")
        print(f"{run['label']} at capacity: server CPU per keyframe, ms: {cpu}")
