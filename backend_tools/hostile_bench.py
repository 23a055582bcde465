"""`cloudtrack-backend bench --hostile`: one token's hostile requests beside another vehicle's search.

A real `cloudtrack-backend serve` (default configuration, SQLite store on disk). Vehicle A sends real
keyframes the companion's way (one every 0.5 s, waiting for each answer) and a status every 0.5 s, in three
phases: alone; while vehicle B's token (from its own process) sends `count` hostile requests of every kind
issues 31 and 44 found and `slow_clients` connections trickle header lines; and while B runs issue 44's
duplicate-header attack from `DUPLICATE_ATTACK_CONNECTIONS` connections without a pause (a status of 60,000
keys with two Content-Type headers, the limits reading one and the route the other). Printed: A's detect
and status p95 alone and in each phase (and their ratios, goal <= 1.5), /health's p95, every status code
B got (no 5xx), and the server's RSS before and after (goal +50 MB). B's token gets a rate quota high
enough that every hostile request reaches the check meant for it (the default quota would refuse most with
429 before their bodies are read, which is the cheap case).
"""

from __future__ import annotations

import base64
import contextlib
import json
import multiprocessing
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from http.client import HTTPConnection, HTTPException
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import requests

from backend_tools.capacity_bench import PROMPT, keyframes
from backend_tools.fleet_services import BackendProcess

TOKENS = {"vehicle-a": "hostile-bench-vehicle-a-token", "vehicle-b": "hostile-bench-vehicle-b-token"}
DUPLICATE_ATTACK_CONNECTIONS = 3  # the worst case: detect p95 6.1 s from three connections
ATTACKER_NICE = 10  # the attack process's priority below the server's and the good vehicle's
STATUS_B = "/v1/vehicles/vehicle-b/status"
SIXTY_THOUSAND_KEYS = json.dumps({"state": "SEARCH", **{f"k{i}": 0 for i in range(60_000)}}).encode()
DUPLICATE_CONTENT_TYPE = (("Content-Type", "application/json"), ("Content-Type", "text/plain"))


def _header_bomb(width: int, height: int) -> bytes:
    """A small real JPEG whose frame header claims width x height."""
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 7] = height.to_bytes(2, "big")
    data[sof + 7 : sof + 9] = width.to_bytes(2, "big")
    return bytes(data)


@dataclass(frozen=True)
class Hostile:
    """One kind of hostile request: what issue 31 (and issue 14 before it) found."""

    kind: str
    method: str
    path: str
    body: bytes = b""
    content_type: str = "application/json"
    files: dict[str, Any] | None = None
    data: dict[str, str] | None = None
    raw_headers: tuple[tuple[str, str], ...] = ()  # sent as they are, repeats kept (over http.client)


def hostile_kinds() -> list[Hostile]:
    """Every kind, each built once (the sender's own CPU stays small beside the server's)."""
    status = "/v1/vehicles/vehicle-b/status"
    meta = json.dumps({"vehicle_id": "vehicle-b", "mission_id": "bombs", "prompt": PROMPT})
    crop_bomb = base64.b64encode(_header_bomb(8700, 8700)).decode()
    deep: Any = 1
    for _ in range(30):
        deep = [deep]
    return [
        Hostile("150000 unknown keys (1.7 MB)", "POST", status, json.dumps({f"k{i}": 0 for i in range(150_000)}).encode()),
        Hostile("5000 unknown keys", "POST", status, json.dumps({"state": "S", **{f"k{i}": 0 for i in range(5000)}}).encode()),
        Hostile("nested 30 deep", "POST", status, json.dumps({"state": "S", "search": deep}).encode()),
        Hostile("invalid fields", "POST", status, json.dumps({"state": [1], "altitude_m": "x", **{f"x{i}": i for i in range(50)}}).encode()),
        Hostile("position off the globe", "POST", "/v1/missions/geo/rejections",
                json.dumps({"vehicle_id": "vehicle-b", "candidate_id": "c1", "position": [135, 0]}).encode()),
        Hostile("position 1e308", "POST", status, json.dumps({"state": "S", "position": [1e308, -1e308]}).encode()),
        Hostile("after = 2^63", "GET", "/v1/vehicles/vehicle-b/decisions?after=9223372036854775808"),
        Hostile("keyframe header 16000x16000", "POST", "/v1/detect", content_type="",
                files={"image": ("b.jpg", _header_bomb(16000, 16000), "image/jpeg")}, data={"meta": meta}),
        Hostile("crop header 8700x8700", "POST", "/v1/missions/bombs/rejections",
                json.dumps({"vehicle_id": "vehicle-b", "crop_jpeg_b64": crop_bomb}).encode()),
        Hostile("a new mission each time", "POST", status, b""),  # body made per request below
        Hostile("duplicate Content-Type, 60000 keys", "POST", status, SIXTY_THOUSAND_KEYS,
                raw_headers=(*DUPLICATE_CONTENT_TYPE, ("Authorization", f"Bearer {TOKENS['vehicle-b']}"))),
        # The route would act as B while the quota counts A.
        Hostile("duplicate Authorization", "POST", status, json.dumps({"state": "SEARCH"}).encode(),
                raw_headers=(("Content-Type", "application/json"),
                             ("Authorization", f"Bearer {TOKENS['vehicle-b']}"),
                             ("Authorization", f"Bearer {TOKENS['vehicle-a']}"))),
    ]  # fmt: skip


def raw_post(url: str, path: str, headers: tuple[tuple[str, str], ...], body: bytes) -> str:
    """One POST with exactly these header lines (repeats kept): the status code, or "no answer"."""
    host, port = url.removeprefix("http://").rsplit(":", 1)
    conn = HTTPConnection(host, int(port), timeout=60)
    try:
        conn.putrequest("POST", path)
        for name, value in (*headers, ("Content-Length", str(len(body)))):
            conn.putheader(name, value)
        conn.endheaders()
        with contextlib.suppress(OSError):  # refused from its headers: the server closes on the body
            conn.send(body)
        return str(conn.getresponse().status)
    except (OSError, HTTPException):
        return "no answer"
    finally:
        conn.close()


@dataclass
class Phase:
    latencies: list[float] = field(default_factory=list)
    statuses: list[float] = field(default_factory=list)
    health: list[float] = field(default_factory=list)
    codes: dict[str, int] = field(default_factory=dict)

    def p95(self, values: list[float]) -> float:
        return float(np.percentile(values, 95)) if values else float("nan")

    def figures(self) -> dict[str, Any]:
        return {
            "keyframes": len(self.latencies),
            "p50_s": float(np.median(self.latencies)) if self.latencies else float("nan"),
            "p95_s": self.p95(self.latencies),
            "statuses": len(self.statuses),
            "status_p50_s": float(np.median(self.statuses)) if self.statuses else float("nan"),
            "status_p95_s": self.p95(self.statuses),
        }


def _vehicle_a_status(url: str, stop: threading.Event, phase: Phase) -> None:
    """Vehicle A's status every 0.5 s, as the companion reports (its position moving along)."""
    with requests.Session() as http:
        http.headers["Authorization"] = f"Bearer {TOKENS['vehicle-a']}"
        step = 0
        while not stop.is_set():
            body = {"mission_id": "search", "state": "SEARCH", "prompt": PROMPT,
                    "position": [47.0 + step * 1e-5, 8.0], "altitude_m": 40.0}  # fmt: skip
            started = time.monotonic()
            answer = http.post(f"{url}/v1/vehicles/vehicle-a/status", json=body, timeout=60)
            code = f"A status {answer.status_code}"
            phase.codes[code] = phase.codes.get(code, 0) + 1
            if answer.status_code == 200:
                phase.statuses.append(time.monotonic() - started)
            step += 1
            stop.wait(max(0.0, 0.5 - (time.monotonic() - started)))


def _duplicate_attack(url: str, seconds: float, connections: int) -> dict[str, int]:
    """Issue 44's attack, in its own process: `connections` threads each sending the duplicate-Content-Type
    status of 60,000 keys back to back for `seconds`; the status codes. Refused from its headers, each
    request costs the server about 1 ms (uvicorn's connection and h11), and the attacker can send as fast as
    its own CPU allows: on the bench's shared cores it runs at a lower priority (`ATTACKER_NICE`), as an
    attacker's CPU is its own machine's; what the server spends on it is what the good vehicle feels."""
    os.nice(ATTACKER_NICE)
    codes: dict[str, int] = {}
    lock = threading.Lock()
    deadline = time.monotonic() + seconds
    head = (*DUPLICATE_CONTENT_TYPE, ("Authorization", f"Bearer {TOKENS['vehicle-b']}"))

    def attack() -> None:
        while time.monotonic() < deadline:
            code = raw_post(url, STATUS_B, head, SIXTY_THOUSAND_KEYS)
            with lock:
                codes[code] = codes.get(code, 0) + 1

    threads = [threading.Thread(target=attack) for _ in range(connections)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return codes


def _vehicle_a(url: str, jpegs: list[bytes], stop: threading.Event, phase: Phase) -> None:
    """Vehicle A: a keyframe every 0.5 s, waiting for each answer (one out at a time: its own latency)."""
    period = 0.5
    frame = 0
    with requests.Session() as http:
        http.headers["Authorization"] = f"Bearer {TOKENS['vehicle-a']}"
        due = time.monotonic()
        while not stop.is_set():
            meta = {"vehicle_id": "vehicle-a", "mission_id": "search", "prompt": PROMPT, "frame_id": frame}
            started = time.monotonic()
            answer = http.post(
                f"{url}/v1/detect",
                files={"image": ("k.jpg", jpegs[frame % len(jpegs)], "image/jpeg")},
                data={"meta": json.dumps(meta)},
                timeout=60,
            )
            code = str(answer.status_code)
            phase.codes[f"A {code}"] = phase.codes.get(f"A {code}", 0) + 1
            if answer.status_code == 200:
                phase.latencies.append(time.monotonic() - started)
            frame += 1
            due += period
            time.sleep(max(0.0, due - time.monotonic()))


def _health(url: str, stop: threading.Event, phase: Phase) -> None:
    """/health every 0.1 s: how long the event loop takes to answer anything."""
    with requests.Session() as http:
        while not stop.is_set():
            started = time.monotonic()
            http.get(f"{url}/health", timeout=60)
            phase.health.append(time.monotonic() - started)
            time.sleep(0.1)


def _trickle(port: int, stop: threading.Event, closed: list[float]) -> None:
    """Header lines a second apart, never the blank line; `closed` gets the seconds until the server cut it."""
    started = time.monotonic()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=60) as conn:
            conn.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
            conn.settimeout(1.0)
            while not stop.is_set():
                conn.sendall(b"X-Trickle: 1\r\n")  # a header line a second, never the blank line
                try:
                    conn.recv(4096)  # an answer (408) or the close: the server cut it
                except TimeoutError:
                    continue
                closed.append(time.monotonic() - started)
                return
    except OSError:
        closed.append(time.monotonic() - started)


def _send_hostile(url: str, count: int) -> tuple[dict[str, dict[str, int]], float]:
    """Vehicle B's hostile requests, in their own process (the measuring client's GIL stays A's):
    the status codes by kind and the seconds they took."""
    kinds = hostile_kinds()
    by_kind: dict[str, dict[str, int]] = {}
    started = time.monotonic()
    with requests.Session() as http:
        http.headers["Authorization"] = f"Bearer {TOKENS['vehicle-b']}"
        for i in range(count):
            kind = kinds[i % len(kinds)]
            headers = {"Content-Type": kind.content_type} if kind.content_type else {}
            body = kind.body or (json.dumps({"mission_id": f"flood-{i}", "state": "SEARCH"}).encode()
                                 if kind.kind.startswith("a new mission") else b"")  # fmt: skip
            if kind.raw_headers:
                code = raw_post(url, kind.path, kind.raw_headers, body)
            else:
                try:
                    answer = http.request(
                        kind.method, url + kind.path, data=kind.data if kind.files else body,
                        files=kind.files, headers=headers, timeout=60,
                    )  # fmt: skip
                    code = str(answer.status_code)
                except requests.RequestException:
                    code = "no answer"
            counts = by_kind.setdefault(kind.kind, {})
            counts[code] = counts.get(code, 0) + 1
    return by_kind, time.monotonic() - started


def hostile_run(
    model_dir: Path,
    sequences: Path,
    count: int,
    slow_clients: int,
    solo_s: float,
    say: Callable[[str], None],
    extra_settings: tuple[str, ...] = (),
    source_tree: Path | None = None,
) -> dict[str, Any]:
    """The three phases against a server run from this code, or from `source_tree` (a "before")."""
    jpegs = keyframes(sequences)
    with tempfile.TemporaryDirectory(prefix="cloudtrack-hostile-") as folder:
        settings = [
            f"detector.model_dir={json.dumps(str(model_dir))}",
            f"sessions.sqlite_path={json.dumps(str(Path(folder) / 'sessions.sqlite3'))}",
            "sessions.rate_limit_requests=100000",  # every hostile request reaches its own check
            *extra_settings,
        ]
        with BackendProcess(settings, TOKENS, source_tree=source_tree) as server:
            port = int(server.url.rsplit(":", 1)[1])
            for _ in range(3):  # warm up: models loaded, first allocations made
                requests.post(
                    f"{server.url}/v1/detect",
                    files={"image": ("k.jpg", jpegs[0], "image/jpeg")},
                    data={"meta": json.dumps({"vehicle_id": "vehicle-a", "mission_id": "warm", "prompt": PROMPT})},
                    headers={"Authorization": f"Bearer {TOKENS['vehicle-a']}"},
                    timeout=60,
                )  # fmt: skip
            say(f"  vehicle A alone for {solo_s:g} s ...")
            solo = Phase()
            with _vehicle_a_running(server.url, jpegs, solo):
                time.sleep(solo_s)
            rss_before = server.rss_bytes()
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as sender:
                sender.submit(_send_hostile, server.url, 0).result()  # started and imported before A's phase
                say(f"  vehicle A beside {count} hostile requests and {slow_clients} slow clients ...")
                beside = Phase()
                stop = threading.Event()
                closed: list[float] = []
                trickling = [
                    threading.Thread(target=_trickle, args=(port, stop, closed)) for _ in range(slow_clients)
                ]
                with _vehicle_a_running(server.url, jpegs, beside):
                    for t in trickling:
                        t.start()
                    by_kind, hostile_s = sender.submit(_send_hostile, server.url, count).result()
                    time.sleep(max(0.0, solo_s - hostile_s))  # A's phase at least as long as its solo one
                    stop.set()
                    for t in trickling:
                        t.join()
                say(
                    f"  vehicle A beside the duplicate-header attack from {DUPLICATE_ATTACK_CONNECTIONS} "
                    f"connections for {solo_s:g} s ..."
                )
                attacked = Phase()
                with _vehicle_a_running(server.url, jpegs, attacked):
                    attack_codes = sender.submit(
                        _duplicate_attack, server.url, solo_s, DUPLICATE_ATTACK_CONNECTIONS
                    ).result()
            rss_after = server.rss_bytes()
    server_errors = sum(
        n for counts in by_kind.values() for code, n in counts.items() if code.startswith("5")
    )
    server_errors += sum(n for code, n in attack_codes.items() if code.startswith("5"))
    server_errors += sum(
        n
        for phase in (beside, attacked)
        for code, n in phase.codes.items()
        if code.split()[-1].startswith("5")
    )
    solo_figures = solo.figures()

    def ratios(phase: Phase) -> dict[str, float]:
        figures = phase.figures()
        return {
            "detect_p95_ratio": figures["p95_s"] / solo_figures["p95_s"],
            "status_p95_ratio": figures["status_p95_s"] / solo_figures["status_p95_s"],
        }

    return {
        "hostile_requests": count,
        "hostile_s": hostile_s,
        "slow_clients": slow_clients,
        "slow_clients_closed": len(closed),
        "slow_client_max_s": max(closed) if closed else float("nan"),
        "by_kind": by_kind,
        "vehicle_a": {
            "solo": solo_figures,
            "beside": beside.figures(),
            "codes": beside.codes,
            "p95_ratio": ratios(beside)["detect_p95_ratio"],
            "status_p95_ratio": ratios(beside)["status_p95_ratio"],
        },
        "duplicate_header_attack": {
            "connections": DUPLICATE_ATTACK_CONNECTIONS,
            "seconds": solo_s,
            "answers": attack_codes,
            "vehicle_a": attacked.figures(),
            "codes": attacked.codes,
            **ratios(attacked),
            "health_p95_s": attacked.p95(attacked.health),
        },
        "health_p95_s": {"solo": solo.p95(solo.health), "beside": beside.p95(beside.health),
                         "max_beside": max(beside.health) if beside.health else float("nan")},
        "server_errors": server_errors,
        "rss_mb": {"before": rss_before / 1e6, "after": rss_after / 1e6, "grown": (rss_after - rss_before) / 1e6},
    }  # fmt: skip


@contextlib.contextmanager
def _vehicle_a_running(url: str, jpegs: list[bytes], phase: Phase) -> Iterator[None]:
    """Vehicle A's keyframes and statuses and the /health probe, for as long as the block runs."""
    stop = threading.Event()
    workers = [
        threading.Thread(target=_vehicle_a, args=(url, jpegs, stop, phase)),
        threading.Thread(target=_vehicle_a_status, args=(url, stop, phase)),
        threading.Thread(target=_health, args=(url, stop, phase)),
    ]
    for w in workers:
        w.start()
    try:
        yield
    finally:
        stop.set()
        for w in workers:
            w.join()


def print_hostile(report: dict[str, Any]) -> None:
    a, h, r = report["vehicle_a"], report["health_p95_s"], report["rss_mb"]
    d = report["duplicate_header_attack"]
    print(
        f"Hostile load: {report['hostile_requests']} requests from one token in {report['hostile_s']:.1f} s, "
        f"{report['slow_clients']} clients trickling header lines ({report['slow_clients_closed']} cut off by the "
        f"server, the last after {report['slow_client_max_s']:.1f} s)"
    )
    print("| kind | answers |\n|---|---|")
    for kind, codes in report["by_kind"].items():
        print(f"| {kind} | {', '.join(f'{n} x {code}' for code, n in sorted(codes.items()))} |")
    print(
        f"Vehicle A (a keyframe and a status every 0.5 s): detect p95 {a['solo']['p95_s']:.3f} s alone, "
        f"{a['beside']['p95_s']:.3f} s beside the hostile token: ratio {a['p95_ratio']:.2f}; status p95 "
        f"{a['solo']['status_p95_s']:.3f} s alone, {a['beside']['status_p95_s']:.3f} s beside: ratio "
        f"{a['status_p95_ratio']:.2f} (goal <= 1.5); answers {a['codes']}"
    )
    attack = ", ".join(f"{n} x {code}" for code, n in sorted(d["answers"].items()))
    print(
        f"Duplicate-header attack ({d['connections']} connections, {d['seconds']:g} s: {attack}): vehicle A's "
        f"detect p95 {d['vehicle_a']['p95_s']:.3f} s (ratio {d['detect_p95_ratio']:.2f}), status p95 "
        f"{d['vehicle_a']['status_p95_s']:.3f} s (ratio {d['status_p95_ratio']:.2f}) (goal <= 1.5); "
        f"/health p95 {1000 * d['health_p95_s']:.1f} ms; answers {d['codes']}"
    )
    print(
        f"/health p95 {1000 * h['solo']:.1f} ms alone, {1000 * h['beside']:.1f} ms beside (max "
        f"{1000 * h['max_beside']:.1f} ms); 5xx answers: {report['server_errors']}; RSS {r['before']:.1f} -> "
        f"{r['after']:.1f} MB ({r['grown']:+.1f} MB, goal < +50 MB)"
    )
