"""docs/quickstart.md as written: its `up` block starts everything (`cloudtrack-sim up`), its `gcs` blocks
run in order in a second shell, and a candidate is confirmed. What the start prints is the page's own
`output` block, line for line; the confirm shows in the companion's status, on the supervisor's snapshot
and in the GeoJSON download; Ctrl-C stops everything. A fast check parses every command with the real
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
BLOCK = re.compile(r"<!-- quickstart: (up|gcs|output) -->\s*\n```(?:sh|text)\n(.*?)\n```", re.S)
SCRIPTS = {"cloudtrack-sim": "sitl.cli", "cloudtrack-gcs": "gcs.cli"}


def _blocks(kind: str) -> list[str]:
    return [text for mark, text in BLOCK.findall(PAGE.read_text()) if mark == kind]


def test_quickstart_commands_parse() -> None:
    [up] = _blocks("up")
    gcs = _blocks("gcs")
    assert len(gcs) >= 4 and len(_blocks("output")) == 1
    commands = [shlex.split(line) for block in (up, *gcs) for line in block.splitlines()]
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


def _tail(path: Path, lines: int = 40) -> str:
    return "\n".join(path.read_text().splitlines()[-lines:]) if path.is_file() else "(no log)"
