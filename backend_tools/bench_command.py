"""`cloudtrack-backend bench`: what the back-end costs a fleet, against a real server and a VLM endpoint
of fixed latency L (the OpenAI-compatible emulator in backend_tools/vlm_emulator.py, on loopback).

1. Detection time of a 640x480 frame (YOLOX-nano, onnxruntime).
2. t_f for a keyframe with k candidates, verified concurrently versus one after another (the reference
   code's way): two servers, verifier pool k and 1.
3. N simulated vehicles (threads, each its own token, sending real keyframes back to back with
   BackendClient): p50/p95 latency and throughput versus N, and bytes per request.
4. Replicas (backend_tools/fleet_bench.py): 16 vehicles through nginx over 1 and over 2 replicas sharing one
   redis-server, then a failover run that SIGKILLs one replica half-way and counts acknowledged
   rejections and decisions lost (must be 0). Needs Debian's redis-server and nginx (make install-services).
`--capacity`, `--hostile` and `--fleet-map` measure one thing each instead (their modules say what);
`--fleet-map` (backend_tools/mission_fleet_bench.py): one mission of N vehicles, its merged map and the
supervisor page's state.
Servers run as separate `cloudtrack-backend serve` processes so the bench's own threads do not share
their interpreter. Each part prints a line when it starts, so a run of a few minutes shows where it is.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from backend_tools.fleet_bench import fleet_tokens, replicated_bench
from backend_tools.fleet_services import BackendProcess
from backend_tools.vlm_emulator import MODEL_NAME, VlmEmulator
from cloudtrack.api_client import BackendClient, BackendError
from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import ModelError, require, resolve_model_dir

PROMPT = "a man in a gray shirt"
SOURCES = [("uav123_person12_1", 1), ("uav123_person12_1", 100), ("otb_Crossing", 1), ("otb_Crossing", 60),
           ("uav123_person12_1", 180), ("otb_Crossing", 110)]  # fmt: skip


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "bench",
        help="latency and throughput for many vehicles against a server and a VLM of fixed latency",
        description="Starts a VLM emulator (fixed latency L) and back-end servers on loopback, then measures "
        "detection time, t_f for k candidates concurrent vs sequential, and p50/p95 latency, throughput and "
        "bytes per request for N simulated vehicles. With --url it measures an already running server.",
        epilog="examples:\n"
        "  cloudtrack-backend bench --latency 1.0 --candidates 5 --vehicles 1 4 16\n"
        "  cloudtrack-backend bench --latency 0.2 --requests 5 --json out/bench.json\n"
        '  cloudtrack-backend bench --url https://backend.example.org --tokens \'{"drone-1": "...", "drone-2": "..."}\' '
        "--vehicles 1 2\n"
        "  cloudtrack-backend bench --capacity --json out/capacity.json\n"
        "  cloudtrack-backend bench --hostile --json out/hostile.json\n"
        "  cloudtrack-backend bench --fleet-map 50 --fleet-s 30 --json out/fleet-map.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--latency", type=float, default=1.0, help="VLM latency L in seconds (default 1.0)")
    parser.add_argument(
        "--candidates", type=int, default=5, help="k candidates in the t_f keyframe (default 5)"
    )
    parser.add_argument(
        "--vehicles", type=int, nargs="+", default=[1, 4, 16], help="fleet sizes N (default 1 4 16)"
    )
    parser.add_argument("--requests", type=int, default=6, help="keyframes per vehicle (default 6)")
    parser.add_argument(
        "--verify-concurrency", type=int, default=64, help="server verifier pool for the fleet runs"
    )
    parser.add_argument(
        "--data", type=Path, help="shared data folder (default: $CLOUDTRACK_SHARED or ../shared)"
    )
    parser.add_argument("--model-dir", help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)")
    parser.add_argument("--url", help="measure this running server instead (fleet part only)")
    parser.add_argument("--tokens", help='JSON {"vehicle id": "token"} for --url')
    parser.add_argument(
        "--replica-vehicles",
        type=int,
        default=16,
        help="vehicles for the 1-vs-2-replica and failover runs (default 16)",
    )
    parser.add_argument(
        "--no-replicas",
        action="store_true",
        help="skip the replica runs (they need redis-server and nginx: make install-services)",
    )
    capacity = parser.add_argument_group("capacity (--capacity)")
    capacity.add_argument(
        "--capacity",
        action="store_true",
        help="find the most vehicles one back-end serves (local verifier, no emulated delay) and print it "
        "beside the detector's raw keyframes/s on the same cores; nothing else is measured",
    )
    capacity.add_argument(
        "--baseline",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="also measure the server with this setting first (repeatable; e.g. verifier.kind=none: the "
        "service without its verifier), named by its settings, or 'before' with --baseline-tree",
    )
    capacity.add_argument(
        "--baseline-tree",
        type=Path,
        metavar="DIR",
        help="also measure the server run from this source tree first, as 'before' (e.g. `git worktree add "
        "DIR COMMIT`): before and after in one run (--capacity and --hostile)",
    )
    capacity.add_argument(
        "--rate", type=float, default=2.0, help="keyframes per second per vehicle (default 2: searching)"
    )
    capacity.add_argument(
        "--p95-bound", type=float, default=1.0, help="p95 latency a served fleet stays within (default 1.0 s)"
    )
    capacity.add_argument(
        "--trial-s", type=float, default=20.0, help="seconds measured per fleet size (default 20)"
    )
    hostile = parser.add_argument_group("hostile load (--hostile)")
    hostile.add_argument(
        "--hostile",
        action="store_true",
        help="one vehicle's search alone, then beside another token's hostile requests of every kind and "
        "clients trickling header lines: its p95 ratio, /health, status codes, RSS; nothing else is measured",
    )
    hostile.add_argument("--hostile-requests", type=int, default=2000, help="hostile requests (default 2000)")
    hostile.add_argument(
        "--slow-clients", type=int, default=90, help="connections trickling header lines (default 90)"
    )
    hostile.add_argument(
        "--solo-s", type=float, default=30.0, help="seconds of the vehicle's search alone (default 30)"
    )
    fleet_map = parser.add_argument_group("one mission of many vehicles (--fleet-map)")
    fleet_map.add_argument(
        "--fleet-map",
        type=int,
        nargs="+",
        metavar="N",
        help="N vehicles searching one mission id, each reporting status (area, covered area, POD grid) at the "
        "companion's default rates, while a supervisor reads the merged map and the page's state: their "
        "p50/p95 and bytes, the status report's p95, the server's RSS; one N is measured beside 1 vehicle "
        "(e.g. --fleet-map 50, or --fleet-map 1 10 50); nothing else is measured",
    )
    fleet_map.add_argument(
        "--fleet-s", type=float, default=30.0, help="seconds measured per fleet size (default 30)"
    )
    fleet_map.add_argument(
        "--fleet-warm-s",
        type=float,
        default=120.0,
        help="how far into its flight each vehicle's maps are when the measurement starts (default 120)",
    )
    fleet_map.add_argument(
        "--fleet-store",
        choices=("sqlite", "redis"),
        default="sqlite",
        help="the server's session store: SQLite on disk (default) or Debian's redis-server on loopback",
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the figures as JSON")
    parser.set_defaults(func=_bench)


def say(text: str) -> None:
    """Progress on stderr, at once: the figures go to stdout at the end."""
    print(text, file=sys.stderr, flush=True)


def _shared(args: argparse.Namespace) -> Path:
    default = Path(__file__).resolve().parents[1].parent / "shared"
    return args.data or Path(os.environ.get("CLOUDTRACK_SHARED") or default)


def _frame(sequences: Path, name: str, index: int) -> np.ndarray:
    image = cv2.imread(str(sequences / name / "frames" / f"{index:06d}.jpg"))
    if image is None:
        raise FileNotFoundError(f"{sequences / name} frame {index} (set --data or CLOUDTRACK_SHARED)")
    return image


def mosaic(sequences: Path, k: int) -> np.ndarray:
    """A 640x480 keyframe holding k real people, cut from the sequences at their ground-truth boxes."""
    canvas = np.full((480, 640, 3), (120, 125, 130), np.uint8)
    columns = max(k, 1)
    width = min(120, 600 // columns)
    for slot in range(k):
        name, index = SOURCES[slot % len(SOURCES)]
        line = (sequences / name / "groundtruth.txt").read_text().split()[index - 1]
        x, y, w, h = (float(v) for v in line.split(","))
        image = _frame(sequences, name, index)
        x1, y1 = int(max(0, x - 0.3 * w)), int(max(0, y - 0.3 * h))
        patch = image[y1 : int(y + 1.3 * h), x1 : int(x + 1.3 * w)]
        patch = cv2.resize(patch, None, fx=200 / patch.shape[0], fy=200 / patch.shape[0])[:, :width]
        left = 20 + slot * (width + 4)
        canvas[140 : 140 + patch.shape[0], left : left + patch.shape[1]] = patch
    return canvas


def detection_time(model_dir: Path, sequences: Path, runs: int = 50) -> dict[str, float]:
    """Median and p95 of YOLOX on one 640x480 frame, with one onnxruntime thread and with all cores."""
    from backend.detectors.yolox import YoloxDetector

    frame = cv2.resize(_frame(sequences, "uav123_person12_1", 1), (640, 480))
    result = {"load_average_1min": os.getloadavg()[0], "cpus": float(os.cpu_count() or 0)}
    for threads in (1, 0):
        detector = YoloxDetector(require("yolox", model_dir)["yolox_nano.onnx"], threads=threads)
        for _ in range(5):
            detector.detect(frame, ["person"])
        times = []
        for _ in range(runs):
            start = time.perf_counter()
            detector.detect(frame, ["person"])
            times.append(time.perf_counter() - start)
        label = "1thread" if threads == 1 else "allcores"
        result[f"median_ms_{label}"] = 1000 * float(np.median(times))
        result[f"min_ms_{label}"] = 1000 * float(np.min(times))
        result[f"p95_ms_{label}"] = 1000 * float(np.percentile(times, 95))
    return result


def _vlm_settings(base_url: str, model_dir: Path) -> list[str]:
    # One onnxruntime thread per detection and two detections at once: no oversubscribed cores.
    return [
        'verifier.kind="vlm"',
        f"vlm.base_url={json.dumps(base_url)}",
        f'vlm.model="{MODEL_NAME}"',
        f"detector.model_dir={json.dumps(str(model_dir))}",
        "vlm.max_retries=0",
        "detector.threads=1",
        "sessions.detector_concurrency=2",
        'sessions.sqlite_path=":memory:"',
        "sessions.rate_limit_requests=100000",
    ]


def t_f_concurrent_vs_sequential(
    emulator: VlmEmulator, model_dir: Path, sequences: Path, k: int, latency: float
) -> dict[str, Any]:
    image = mosaic(sequences, k)
    result: dict[str, Any] = {"k": k, "latency_s": latency}
    for label, pool in (("concurrent", k), ("sequential", 1)):
        settings = [
            *_vlm_settings(emulator.base_url, model_dir),
            f"verifier.concurrency={pool}",
            f"detector.max_candidates={k}",
            f"verifier.timeout_s={k * latency + 10}",
            f"verifier.request_deadline_s={k * latency + 30}",
        ]
        say(f"  t_f with a verifier pool of {pool} ...")
        server = BackendProcess(settings, {"bench-0": "bench-vehicle-token-0000"})
        try:
            server.wait_ready()
            client = BackendClient(
                server.url,
                "bench-vehicle-token-0000",
                timeout_s=k * latency + 60,
                vehicle_id="bench-0",
                mission_id="t-f",
            )
            times, counts = [], []
            for _ in range(3):
                start = time.perf_counter()
                reply = client.detect_reply(image, PROMPT)
                times.append(time.perf_counter() - start)
                counts.append(len(reply.detections))
        finally:
            server.stop()
        result[label] = {"t_f_s": float(np.median(times)), "candidates": counts}
    result["ratio"] = result["concurrent"]["t_f_s"] / result["sequential"]["t_f_s"]
    return result


def fleet(
    url: str, tokens: dict[str, str], n: int, requests_each: int, frames: list[np.ndarray]
) -> dict[str, float]:
    vehicles = list(tokens)[:n]
    latencies: list[float] = []
    sizes: list[int] = []
    errors: list[str] = []
    lock = threading.Lock()

    def vehicle(vehicle_id: str, offset: int) -> None:
        client = BackendClient(
            url, tokens[vehicle_id], timeout_s=120, vehicle_id=vehicle_id, mission_id=f"bench-{vehicle_id}"
        )
        for i in range(requests_each):
            frame = frames[(offset + i) % len(frames)]
            start = time.perf_counter()
            try:
                reply = client.detect_reply(frame, PROMPT, frame_id=i, capture_time=time.time())
            except BackendError as exc:
                with lock:
                    errors.append(str(exc))
                continue
            with lock:
                latencies.append(time.perf_counter() - start)
                sizes.append(reply.request_bytes)
                if len(latencies) % max(1, len(vehicles) * requests_each // 4) == 0:
                    say(f"    {len(latencies)}/{len(vehicles) * requests_each} keyframes answered")

    threads = [threading.Thread(target=vehicle, args=(v, i)) for i, v in enumerate(vehicles)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - start
    return {
        "vehicles": len(vehicles),
        "requests": len(latencies),
        "errors": len(errors),
        "p50_s": float(np.percentile(latencies, 50)) if latencies else float("nan"),
        "p95_s": float(np.percentile(latencies, 95)) if latencies else float("nan"),
        "throughput_rps": len(latencies) / wall,
        "bytes_per_request": float(np.mean(sizes)) if sizes else float("nan"),
    }


def _fleet_frames(sequences: Path) -> list[np.ndarray]:
    frames = []
    for name in ("uav123_person12_1", "otb_Crossing", "dtb70_Surfing06", "uav123_wakeboard7"):
        for index in (1, 21, 41, 61):
            frames.append(
                cv2.resize(_frame(sequences, name, index), (640, 480), interpolation=cv2.INTER_AREA)
            )
    return frames


def _print_report(report: dict[str, Any]) -> None:
    if "detection" in report:
        d = report["detection"]
        print(f"YOLOX-nano, 640x480 frame ({d['cpus']:.0f} CPUs, load average {d['load_average_1min']:.1f}):")
        for label, text in (("1thread", "1 thread"), ("allcores", "all cores")):
            print(
                f"  {text}: median {d['median_ms_' + label]:.1f} ms, min {d['min_ms_' + label]:.1f} ms, "
                f"p95 {d['p95_ms_' + label]:.1f} ms"
            )
        print()
    if "t_f" in report:
        t = report["t_f"]
        print(f"t_f for a keyframe with k={t['k']} candidates, VLM latency L={t['latency_s']:.2f} s:")
        print("| verification | t_f [s] | candidates |\n|---|---|---|")
        for label in ("concurrent", "sequential"):
            print(f"| {label} | {t[label]['t_f_s']:.2f} | {t[label]['candidates'][0]} |")
        print(f"concurrent / sequential = {t['ratio']:.2f}\n")
    print(
        f"Fleet: each vehicle sends keyframes back to back (640x480, JPEG 80), VLM latency L={report['latency_s']:.2f} s"
    )
    print("| vehicles | requests | errors | p50 [s] | p95 [s] | throughput [req/s] | bytes/request |")
    print("|---|---|---|---|---|---|---|")
    for row in report["fleet"]:
        print(
            f"| {row['vehicles']} | {row['requests']} | {row['errors']} | {row['p50_s']:.2f} | {row['p95_s']:.2f} | "
            f"{row['throughput_rps']:.2f} | {row['bytes_per_request']:.0f} |"
        )
    if "replicas" in report:
        r = report["replicas"]
        print(
            f"\nReplicas sharing one redis-server behind nginx, {r['vehicles']} vehicles "
            f"(2 replicas on the same {os.cpu_count()} CPUs as 1):"
        )
        print(
            "| replicas | requests | errors | p50 [s] | p95 [s] | throughput [req/s] |\n|---|---|---|---|---|---|"
        )
        for count in (1, 2):
            row = r[f"replicas_{count}"]
            print(
                f"| {count} | {row['requests']} | {row['errors']} | {row['p50_s']:.2f} | {row['p95_s']:.2f} | "
                f"{row['throughput_rps']:.2f} |"
            )
        print(f"p95 2 replicas / 1 replica = {r['replicas_2']['p95_s'] / r['replicas_1']['p95_s']:.2f}")
        f = r["failover"]
        print(
            f"Failover (one replica SIGKILLed half-way): {f['keyframes']} keyframes, {f['errors']} errors, "
            f"p95 {f['p95_s']:.2f} s; rejections acknowledged {f['acknowledged_rejections']}, lost "
            f"{f['lost_rejections']}; decisions acknowledged {f['acknowledged_decisions']}, lost {f['lost_decisions']}"
        )


def _capacity(args: argparse.Namespace, model_dir: Path, sequences: Path) -> int:
    from backend_tools.capacity_bench import CapacitySettings, Configuration, capacity_report, print_capacity

    settings = CapacitySettings(rate_hz=args.rate, p95_bound_s=args.p95_bound, trial_s=args.trial_s)
    # Another tree is "before" and this one "after"; settings alone are named (e.g. verifier.kind=none beside
    # the defaults: what the verifier costs).
    first = "before" if args.baseline_tree else " ".join(args.baseline)
    configurations = [Configuration(first, tuple(args.baseline), args.baseline_tree)] if first else []
    configurations.append(Configuration("after" if args.baseline_tree else "defaults"))
    try:
        require("yolox", model_dir)
        say(f"[capacity] {args.rate:g} keyframes/s per vehicle, p95 <= {args.p95_bound:g} s ...")
        report = capacity_report(model_dir, sequences, settings, configurations, say)
    except (ConfigError, ModelError, ValueError, OSError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_capacity(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


def _hostile(args: argparse.Namespace, model_dir: Path, sequences: Path) -> int:
    from backend_tools.hostile_bench import hostile_run, print_hostile

    try:
        require("yolox", model_dir)
        say(f"[hostile] {args.hostile_requests} hostile requests, {args.slow_clients} slow clients ...")
        before = None
        if args.baseline_tree:
            say(f"[hostile] before: the server from {args.baseline_tree}")
            before = hostile_run(
                model_dir, sequences, args.hostile_requests, args.slow_clients, args.solo_s, say,
                source_tree=args.baseline_tree,
            )  # fmt: skip
            say("[hostile] after: the server from this tree")
        report = hostile_run(model_dir, sequences, args.hostile_requests, args.slow_clients, args.solo_s, say)
    except (ConfigError, ModelError, ValueError, OSError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if before is not None:
        print("Before:")
        print_hostile(before)
        print("After:")
        report = {"before": before, **report}
    print_hostile(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


def _fleet_map(args: argparse.Namespace, model_dir: Path) -> int:
    from backend_tools.mission_fleet_bench import FleetMapSettings, fleet_map_bench, print_fleet_map

    sizes = [1, *args.fleet_map] if len(args.fleet_map) == 1 and args.fleet_map[0] != 1 else args.fleet_map
    if any(n < 1 or n > 500 for n in sizes) or args.fleet_s <= 0 or args.fleet_warm_s < 0:
        print("error: --fleet-map takes 1-500 vehicles, --fleet-s > 0, --fleet-warm-s >= 0", file=sys.stderr)
        return 2
    settings = FleetMapSettings(duration_s=args.fleet_s, warm_s=args.fleet_warm_s, store=args.fleet_store)
    try:
        report = fleet_map_bench(sizes, model_dir, settings, say)
    except (ConfigError, ModelError, ValueError, OSError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_fleet_map(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


def _bench(args: argparse.Namespace) -> int:
    sequences = _shared(args) / "data" / "sequences"
    model_dir = resolve_model_dir(args.model_dir)
    if args.fleet_map:
        return _fleet_map(args, model_dir)
    if args.capacity:
        return _capacity(args, model_dir, sequences)
    if args.hostile:
        return _hostile(args, model_dir, sequences)
    report: dict[str, Any] = {"latency_s": args.latency}
    try:
        frames = _fleet_frames(sequences)
        if args.url:
            tokens = json.loads(args.tokens or "{}")
            if not isinstance(tokens, dict) or len(tokens) < max(args.vehicles):
                raise ValueError(f"--url needs --tokens with at least {max(args.vehicles)} vehicles")
            report["fleet"] = [
                fleet(args.url.rstrip("/"), tokens, n, args.requests, frames) for n in args.vehicles
            ]
        else:
            require("yolox", model_dir)
            say("[1/4] YOLOX detection time on one frame ...")
            report["detection"] = detection_time(model_dir, sequences)
            with VlmEmulator(latency_s=args.latency) as emulator:
                say(f"[2/4] t_f for k={args.candidates} candidates, concurrent vs sequential ...")
                report["t_f"] = t_f_concurrent_vs_sequential(
                    emulator, model_dir, sequences, args.candidates, args.latency
                )
                tokens = fleet_tokens(max(args.vehicles))
                settings = [
                    *_vlm_settings(emulator.base_url, model_dir),
                    f"verifier.concurrency={args.verify_concurrency}",
                ]
                server = BackendProcess(settings, tokens)
                try:
                    server.wait_ready()
                    report["fleet"] = []
                    for n in args.vehicles:
                        say(f"[3/4] fleet of {n} vehicles, {args.requests} keyframes each ...")
                        report["fleet"].append(fleet(server.url, tokens, n, args.requests, frames))
                finally:
                    server.stop()
                if not args.no_replicas:
                    say(
                        f"[4/4] {args.replica_vehicles} vehicles over 1 and 2 replicas (redis-server, nginx) ..."
                    )
                    report["replicas"] = replicated_bench(
                        settings, args.replica_vehicles, args.requests, frames, PROMPT, fleet, say
                    )
    except (ConfigError, ModelError, ValueError, OSError, RuntimeError, BackendError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0
