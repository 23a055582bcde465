"""docs/quickstart.md as written: its `up` block starts everything (`cloudtrack-sim up`), its `gcs` blocks
run in order in a second shell, and a candidate is confirmed. What the start prints is the page's own
`output` block, line for line; the confirm shows in the companion's status, on the supervisor's snapshot
and in the GeoJSON download; Ctrl-C stops everything. The area-search rehearsal likewise: `search-up`
starts the search world (printing the page's `search-printed` lines), `search-watch` runs in a third
shell throughout, the `search-gcs` blocks upload the survey, switch to AUTO, start, reject the look-alike,
confirm the person described and download the finds. A fast check parses every command with the real
argument parsers. Select: -k quickstart.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "quickstart.md"
BLOCK = re.compile(r"<!-- quickstart: ([a-z-]+) -->\s*\n```(?:sh|text)\n(.*?)\n```", re.S)
SCRIPTS = {"cloudtrack-sim": "sitl.cli", "cloudtrack-gcs": "gcs.cli"}


def _blocks(kind: str) -> list[str]:
    return [text for mark, text in BLOCK.findall(PAGE.read_text()) if mark == kind]


def test_quickstart_commands_parse() -> None:
    [up] = _blocks("up")
    gcs = _blocks("gcs")
    assert len(gcs) >= 4 and len(_blocks("output")) == 1
    search = [*_blocks("search-up"), *_blocks("search-watch"), *_blocks("search-gcs")]
    assert len(search) == 7 and len(_blocks("search-printed")) == 1
    commands = [shlex.split(line) for block in (up, *gcs, *search) for line in block.splitlines()]
    runs = [words for words in commands if words and words[0] in SCRIPTS]
    assert {words[0] for words in runs} == set(SCRIPTS)
    for words in runs:
        importlib.import_module(SCRIPTS[words[0]]).build_parser().parse_args(words[1:])


def _shell(script: str, **popen: object) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(  # type: ignore[call-overload, no-any-return]
        ["bash", "-c", script],
        cwd=REPO,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        **popen,
    )


def _port_free(port: int) -> bool:
    """Nothing listens on the port (connections of a stopped server waiting out TIME_WAIT do not count)."""
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_quickstart_as_written_confirms_a_candidate() -> None:
    assert (REPO.parent / "shared" / "models").is_dir(), "the quickstart uses ../shared beside the repository"
    [up] = _blocks("up")
    gcs = _blocks("gcs")
    setup = "source .venv/bin/activate\n" if (REPO / ".venv").is_dir() else ""
    work = REPO / "out" / "quickstart"
    if work.exists():
        import shutil

        shutil.rmtree(work)
    assert _port_free(8080), "port 8080 is taken: the quickstart's back-end needs it"
    stack = _shell(up, start_new_session=True)
    assert stack.stdout is not None
    printed: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while not any("In another shell" in line for line in printed):
            line = stack.stdout.readline()
            assert line or stack.poll() is None, "cloudtrack-sim up ended:\n" + "".join(printed)
            printed.append(line)
            assert time.monotonic() < deadline, "cloudtrack-sim up did not come up:\n" + "".join(printed)
        text = "".join(printed)
        assert "supervisor page  http://127.0.0.1:8080/supervisor" in text
        token = (work / "supervisor-token").read_text().strip()
        assert token not in text  # the token is in its file, never printed

        outputs = []
        for block in gcs:
            # A block's own set-up line (source) stays; a later block runs in the same second shell.
            script = block if block.startswith("source") else setup + block
            done = _shell(script)
            out, _ = done.communicate(timeout=120)
            outputs.append(out)
            assert done.returncode == 0, f"{block}\n{out}\ncompanion log:\n{_tail(work / 'companion.log')}"

        start, watch, decide, download = outputs[:4]
        [expected] = _blocks("output")
        assert start.strip().splitlines() == expected.splitlines(), start
        assert re.search(r"CANDIDATE (AWAITING|REVERIFIED) ", watch), watch + _tail(work / "companion.log")
        assert "[summary]" in watch and len(watch.splitlines()) < 60
        assert "FOUND" in decide or "CONFIRMED" in decide, decide
        headers = {"Authorization": f"Bearer {token}"}
        snapshot = httpx.get("http://127.0.0.1:8080/supervisor/api/state", headers=headers, timeout=10).json()
        (vehicle,) = snapshot["vehicles"]
        assert vehicle["state"] == "CONFIRMED" and vehicle["finds"], vehicle
        document = json.loads((work / "finds.geojson").read_text())
        assert [f for f in document["features"] if f["properties"]["kind"] == "find"], download
    finally:
        stack.send_signal(signal.SIGINT)  # Ctrl-C
        try:
            rest, _ = stack.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(stack.pid, signal.SIGKILL)
            rest, _ = stack.communicate()
    assert stack.returncode == 0, rest
    assert rest.strip().endswith("stopped"), rest
    assert _port_free(8080)  # everything it started has stopped


# The search world's people (sitl/world.py, fixed_search_world), metres north of home: the candidates'
# latitudes tell them apart.
LOOKALIKE_NORTH_M, TARGET_NORTH_M = 60.0, 90.0
HOME_LAT = 47.397742
CANDIDATE = re.compile(r"CANDIDATE (?:AWAITING|REVERIFIED) (\w+) at (-?\d+\.\d+),(-?\d+\.\d+)")


def _north_m(lat: float) -> float:
    return (lat - HOME_LAT) * 111_195.0


def _candidate(watch: str, log: Path) -> tuple[str, float]:
    found = CANDIDATE.findall(watch)
    assert found, watch + _tail(log)
    cid, lat, _ = found[-1]
    return cid, _north_m(float(lat))


def _start_stack(script: str, work: Path, ready: str) -> tuple[subprocess.Popen[str], str]:
    """`sim up` as its block says, once it printed `ready`; what it printed."""
    if work.exists():
        import shutil

        shutil.rmtree(work)
    assert _port_free(8080), "port 8080 is taken: the quickstart's back-end needs it"
    stack = _shell(script, start_new_session=True)
    assert stack.stdout is not None
    printed: list[str] = []
    deadline = time.monotonic() + 120
    while not any(ready in line for line in printed):
        line = stack.stdout.readline()
        if not line and stack.poll() is not None:
            _stop(stack)
            raise AssertionError("cloudtrack-sim up ended:\n" + "".join(printed))
        printed.append(line)
        if time.monotonic() > deadline:
            _stop(stack)
            raise AssertionError("cloudtrack-sim up did not come up:\n" + "".join(printed))
    return stack, "".join(printed)


def _stop(stack: subprocess.Popen[str]) -> str:
    stack.send_signal(signal.SIGINT)  # Ctrl-C
    try:
        rest, _ = stack.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(stack.pid, signal.SIGKILL)
        rest, _ = stack.communicate()
    return str(rest)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_quickstart_area_search_rehearsal_as_written() -> None:
    assert (REPO.parent / "shared" / "models").is_dir(), "the quickstart uses ../shared beside the repository"
    [up] = _blocks("search-up")
    [watch_block] = _blocks("search-watch")
    [printed_block] = _blocks("search-printed")
    survey, start, reject, confirm, download = _blocks("search-gcs")
    setup = "source .venv/bin/activate\n" if (REPO / ".venv").is_dir() else ""
    work = REPO / "out" / "search"
    log = work / "companion.log"
    stack, printed = _start_stack(up, work, "or decide on the supervisor page")
    watch: subprocess.Popen[str] | None = None
    try:
        for line in printed_block.splitlines():  # the world, the area and the survey that suits the camera
            assert line in printed, printed
        assert "survey --centre 47.398281,8.545621 --size 60x100 --altitude 10" in printed, printed
        watch = _shell(watch_block)  # the third shell, throughout

        def run(block: str) -> str:
            script = block if block.startswith("source") else setup + block
            done = _shell(script)
            out, _ = done.communicate(timeout=180)
            assert done.returncode == 0, f"{block}\n{out}\ncompanion log:\n{_tail(log)}"
            return str(out)

        out = run(survey)
        assert "uploaded 7 items, read back and checked" in out, out
        assert "mode AUTO: ACCEPTED; the autopilot's HEARTBEAT shows AUTO (was GUIDED)" in out, out
        out = run(start)
        assert "MISSION 43 STARTED: a person in a green shirt (person)" in out and "WARNING" not in out, out
        lookalike, north = _candidate(out, log)
        assert abs(north - LOOKALIKE_NORTH_M) < 5.0, out  # the look-alike, met first on the first lane
        out = run(reject)
        assert "REJECTED: supervisor rejected" in out, out
        person, north = _candidate(out, log)
        assert person != lookalike and abs(north - TARGET_NORTH_M) < 5.0, out
        out = run(confirm)
        assert re.search(r"FOUND -?\d+\.\d+,-?\d+\.\d+ \+-", out), out
        assert "CONFIRMED: supervisor confirmed" in out, out
        run(download)
        token = (work / "supervisor-token").read_text().strip()
        assert token not in printed
        headers = {"Authorization": f"Bearer {token}"}
        snapshot = httpx.get("http://127.0.0.1:8080/supervisor/api/state", headers=headers, timeout=10).json()
        (vehicle,) = snapshot["vehicles"]
        assert vehicle["state"] == "CONFIRMED" and vehicle["search"]["coverage"] > 0, vehicle
        assert [f["candidate_id"] for f in vehicle["finds"]] == [person], vehicle["finds"]
        document = json.loads((work / "finds.geojson").read_text())
        finds = [f for f in document["features"] if f["properties"]["kind"] == "find"]
        assert (
            len(finds) == 1 and abs(_north_m(finds[0]["geometry"]["coordinates"][1]) - TARGET_NORTH_M) < 3.0
        )
        kml = (work / "finds.kml").read_text()
        assert kml.startswith("<?xml") and "<Placemark" in kml, kml[:500]
    finally:
        if watch is not None:
            watch.terminate()
            seen, _ = watch.communicate(timeout=30)
        rest = _stop(stack)
    # The third shell saw the break-off, the survey handed back where it broke off, and the find.
    # Only the event lines: the periodic [summary] line repeats the last message ("last: LEFT MISSION ...").
    left = re.findall(r"^\[\d+/\d+\] LEFT MISSION at item (\d+)", seen, re.MULTILINE)
    assert len(left) == 2 and f"MISSION RESUMED at item {left[0]} (left at {left[0]})" in seen, seen
    assert "[autopilot] mode AUTO" in seen and "FOUND" in seen, seen
    assert stack.returncode == 0 and rest.strip().endswith("stopped"), rest
    assert _port_free(8080)


def _tail(path: Path, lines: int = 40) -> str:
    return "\n".join(path.read_text().splitlines()[-lines:]) if path.is_file() else "(no log)"
