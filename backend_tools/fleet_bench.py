"""The replicated part of `cloudtrack-backend bench`: replicas sharing one Redis behind nginx on loopback.

1. p50/p95 latency of N vehicles through nginx in front of 1 replica, then in front of 2 (same Redis).
2. Failover: N vehicles through nginx over 2 replicas, each sending keyframes, rejections (with a crop)
   and, for each, a supervisor decision; half-way one replica is SIGKILLed. Afterwards every rejection
   and decision that was acknowledged (201) is looked up through the surviving replica: none may be lost.
All processes are real: `cloudtrack-backend serve`, Debian's redis-server and nginx, on 127.0.0.1 only.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import requests

from backend_tools.fleet_services import BackendProcess, NginxBalancer, RedisServer
from cloudtrack.api_client import BackendClient, BackendError

SUPERVISOR_TOKEN = "bench-supervisor-token-0001"


def fleet_tokens(n: int) -> dict[str, str]:
    return {f"bench-{i}": f"bench-vehicle-token-{i:04d}" for i in range(n)}


def _percentiles(latencies: list[float]) -> dict[str, float]:
    if not latencies:
        return {"p50_s": float("nan"), "p95_s": float("nan")}
    return {"p50_s": float(np.percentile(latencies, 50)), "p95_s": float(np.percentile(latencies, 95))}


def failover_run(
    url: str,
    tokens: dict[str, str],
    requests_each: int,
    frames: list[np.ndarray],
    kill: Callable[[], None],
    prompt: str,
) -> dict[str, Any]:
    """Keyframes + rejections + decisions from every vehicle; `kill()` half-way; then count what was kept."""
    acked_rejections: list[tuple[str, str, int]] = []  # vehicle, mission, rejection_id
    acked_decisions: list[tuple[str, int]] = []  # vehicle, decision_id
    latencies: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()
    total = len(tokens) * requests_each
    done = [0]
    killed = threading.Event()
    supervisor = requests.Session()
    supervisor.headers["Authorization"] = f"Bearer {SUPERVISOR_TOKEN}"

    def vehicle(vehicle_id: str, offset: int) -> None:
        mission = f"failover-{vehicle_id}"
        client = BackendClient(
            url, tokens[vehicle_id], timeout_s=120, vehicle_id=vehicle_id, mission_id=mission
        )
        for i in range(requests_each):
            frame = frames[(offset + i) % len(frames)]
            try:
                start = time.perf_counter()
                client.detect_reply(frame, prompt, frame_id=i, capture_time=time.time())
                elapsed = time.perf_counter() - start
                rejection = client.reject(None, crop_bgr=frame[100:260, 200:280], reason=f"bench {i}")
                with lock:
                    latencies.append(elapsed)
                    acked_rejections.append((vehicle_id, mission, rejection.rejection_id))
                answer = supervisor.post(
                    f"{url}/v1/vehicles/{vehicle_id}/decisions",
                    json={"candidate_id": f"c-{i}", "action": "reject"},
                    timeout=60,
                )
                if answer.status_code == 201:
                    with lock:
                        acked_decisions.append((vehicle_id, int(answer.json()["decision_id"])))
                else:
                    with lock:
                        errors.append(f"decision HTTP {answer.status_code}")
            except (BackendError, requests.RequestException) as exc:
                with lock:
                    errors.append(str(exc)[:200])
            with lock:
                done[0] += 1
                if done[0] >= total // 2 and not killed.is_set():
                    killed.set()
                    kill()

    threads = [threading.Thread(target=vehicle, args=(v, i)) for i, v in enumerate(tokens)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - start
    # What was acknowledged must be there, read through whichever replica is left.
    lost_rejections = 0
    for vehicle_id, mission in {(v, m) for v, m, _ in acked_rejections}:
        kept = supervisor.get(
            f"{url}/v1/missions/{mission}/rejections", params={"vehicle_id": vehicle_id}, timeout=30
        )
        ids = {r["rejection_id"] for r in kept.json()}
        lost_rejections += sum(
            1 for v, m, rid in acked_rejections if (v, m) == (vehicle_id, mission) and rid not in ids
        )
    lost_decisions = 0
    for vehicle_id in {v for v, _ in acked_decisions}:
        drone = {"Authorization": f"Bearer {tokens[vehicle_id]}"}
        kept = requests.get(f"{url}/v1/vehicles/{vehicle_id}/decisions", headers=drone, timeout=30).json()
        ids = {d["decision_id"] for d in kept}
        lost_decisions += sum(1 for v, did in acked_decisions if v == vehicle_id and did not in ids)
    supervisor.close()
    return {
        "vehicles": len(tokens),
        "keyframes": len(latencies),
        "errors": len(errors),
        "error_examples": errors[:3],
        **_percentiles(latencies),
        "wall_s": wall,
        "acknowledged_rejections": len(acked_rejections),
        "lost_rejections": lost_rejections,
        "acknowledged_decisions": len(acked_decisions),
        "lost_decisions": lost_decisions,
    }


def replicated_bench(
    settings: list[str],
    n: int,
    requests_each: int,
    frames: list[np.ndarray],
    prompt: str,
    fleet: Callable[[str, dict[str, str], int, int, list[np.ndarray]], dict[str, float]],
    say: Callable[[str], None],
) -> dict[str, Any]:
    """Latency over 1 and 2 replicas (same Redis, behind nginx), then the failover run."""
    tokens = fleet_tokens(n)
    result: dict[str, Any] = {"vehicles": n}
    with RedisServer() as redis_server:
        shared = [
            *settings,
            'sessions.store="redis"',
            f'sessions.redis_url="{redis_server.url}"',
            "sessions.rate_limit_requests=100000",
        ]
        replicas = [BackendProcess(shared, tokens, SUPERVISOR_TOKEN) for _ in range(2)]
        try:
            for replica in replicas:
                replica.wait_ready()
            for count in (1, 2):
                with NginxBalancer([r.url for r in replicas[:count]]) as balancer:
                    say(f"  fleet of {n} vehicles through nginx over {count} replica(s) ...")
                    result[f"replicas_{count}"] = fleet(balancer.url, tokens, n, requests_each, frames)
            with NginxBalancer([r.url for r in replicas]) as balancer:
                say(f"  failover: {n} vehicles over 2 replicas, one SIGKILLed half-way ...")
                result["failover"] = failover_run(
                    balancer.url, tokens, requests_each, frames, replicas[1].kill, prompt
                )
        finally:
            for replica in replicas:
                replica.stop()
    return result
