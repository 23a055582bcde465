"""The README's code blocks marked `<!-- readme-test: offline -->` run as written after the set-up commands.

The block marked `<!-- readme-test: setup -->` (activate .venv, point CLOUDTRACK_MODEL_DIR at the shared
weights) runs first in the same shell, as a user would type it. A fast check parses every command of the
marked blocks with the real argument parsers (a renamed flag fails here, in `make check`); the slow test
runs them (minutes: eval, benches and closed-loop scenarios). What a command writes that is also a test's
evidence (the eval on every shared sequence, `OUTPUT_CHECKS`) is checked from its output, not run twice.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"<!-- readme-test: (setup|offline) -->\s*\n```sh\n(.*?)\n```", re.S)
SCRIPTS = {
    "cloudtrack-companion": "companion.cli",
    "cloudtrack-backend": "backend.cli",
    "cloudtrack-sim": "sitl.cli",
    "cloudtrack-gcs": "gcs.cli",
}


def _blocks(kind: str) -> list[str]:
    return [text for mark, text in BLOCK.findall((REPO / "README.md").read_text()) if mark == kind]


def _commands(block: str) -> list[list[str]]:
    """Each console-script invocation in a block (continuation lines joined, comments dropped)."""
    commands: list[list[str]] = []
    for line in block.replace("\\\n", " ").splitlines():
        words: list[str] = []
        for word in [*shlex.split(line, comments=True), "&&"]:
            if word in ("&&", "||", ";", "|"):
                if words and words[0] in SCRIPTS:
                    commands.append(words)
                words = []
            else:
                words.append(word)
    return commands


def _setup_script() -> str:
    [setup] = _blocks("setup")
    if not (REPO / ".venv" / "bin" / "activate").is_file():
        # A checkout whose tests run from another virtual environment: activate that one instead.
        setup = setup.replace("source .venv/bin/activate", f"source {shlex.quote(sys.prefix)}/bin/activate")
    return setup


def test_readme_marks_the_setup_and_offline_blocks() -> None:
    [setup] = _blocks("setup")
    assert "source .venv/bin/activate" in setup and "CLOUDTRACK_MODEL_DIR" in setup
    offline = _blocks("offline")
    assert len(offline) >= 2
    scripts = {words[0] for block in offline for words in _commands(block)}
    assert {"cloudtrack-companion", "cloudtrack-backend", "cloudtrack-sim"} <= scripts


@pytest.mark.parametrize("index", range(len(_blocks("offline"))))
def test_readme_offline_commands_parse(index: int) -> None:
    for words in _commands(_blocks("offline")[index]):
        parser = importlib.import_module(SCRIPTS[words[0]]).build_parser()
        argv = ["x" if "$(" in w else w for w in words[1:]]  # a command substitution stands for a path
        parser.parse_args(argv)  # exits (SystemExit) on an unknown flag or a missing argument


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("index", range(len(_blocks("offline"))))
def test_readme_offline_block_runs_as_written(index: int) -> None:
    assert (REPO.parent / "shared" / "models").is_dir(), (
        "the README's examples use ../shared beside the repository"
    )
    block = _blocks("offline")[index]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CLOUDTRACK_") or k == "CLOUDTRACK_SHARED"}
    # xtrace puts each command of the block on stderr before its own output (PS4 marks those lines), and the
    # ERR trap names the one that failed with its exit status, so a failure says which command and why.
    script = f"set -euo pipefail\n{_setup_script()}\n{_TRACE}\n{block}\n"
    result = subprocess.run(
        ["bash", "-c", script], cwd=REPO, env=env, capture_output=True, text=True, timeout=1700
    )
    if result.returncode != 0:
        last = result.stderr.rfind("\n" + _PS4)  # the failing command, then everything it wrote to stderr
        pytest.fail(
            f"README block {index} failed with exit status {result.returncode}:\n{block}\n"
            f"--- stdout (end)\n{result.stdout[-3000:]}\n"
            f"--- the failing command and its stderr\n{result.stderr[last + 1 :][-6000:]}",
            pytrace=False,
        )
    for output, check in OUTPUT_CHECKS.items():
        if output in block:
            check(json.loads((REPO / output).read_text()))


def _eval_keeps_the_bare_tracker(report: dict[str, Any]) -> None:
    """The eval on every shared sequence (defaults, bare tracker beside them in the same run): no
    re-initialisation takes the box off the target, and the product is not below the bare tracker."""
    run = report["runs"][0]
    assert run["policy"] == "verified"
    assert all(s["reinit_outcomes"].get("target->other", 0) == 0 for s in run["sequences"]), [
        (s["name"], s["reinit_outcomes"]) for s in run["sequences"]
    ]
    assert run["overall"]["miou"] >= run["bare"]["overall"]["miou"]
    assert run["overall"]["frames"] == run["bare"]["overall"]["frames"]
    assert len(run["sequences"]) == len([p for p in SEQUENCES.iterdir() if (p / "groundtruth.txt").is_file()])


def _sitl_mission_replays_identically(report: dict[str, Any]) -> None:
    """The closed-loop `reject` flight (real companion process, mock autopilot, rendered camera, real
    back-end, scripted supervisor) recorded itself; replayed, every decision is made the same way."""
    assert report["steps"] > 100 and report["differences"] == [], report["differences"][:5]
    from companion.flight_record import read_events

    kinds = {e.get("kind") for e in read_events(REPO / report["folder"])}  # the folder as the README named it
    assert {"supervisor_decision", "backend_answer"} <= kinds, kinds


def _fleet_bench_ran_every_part(report: dict[str, Any]) -> None:
    """The back-end bench as the README runs it (real servers, the VLM emulator at 1.0 s): k crops checked
    concurrently take about one answer's time, one after another at least k answers; every fleet request
    answered; two replicas lose no rejection and no decision when one is killed."""
    t_f = report["t_f"]
    k, latency = t_f["k"], t_f["latency_s"]
    assert t_f["concurrent"]["candidates"] == t_f["sequential"]["candidates"] == [k] * 3
    assert t_f["sequential"]["t_f_s"] > k * latency > t_f["concurrent"]["t_f_s"]
    assert [row["vehicles"] for row in report["fleet"]] == [1, 4]
    assert all(row["errors"] == 0 and row["requests"] >= row["vehicles"] for row in report["fleet"])
    assert all(row["bytes_per_request"] < 100_000 for row in report["fleet"])
    replicas = report["replicas"]
    assert replicas["replicas_1"]["errors"] == 0 and replicas["replicas_2"]["errors"] == 0
    failover = replicas["failover"]
    assert failover["acknowledged_rejections"] >= 2 and failover["acknowledged_decisions"] >= 2
    assert failover["lost_rejections"] == 0 and failover["lost_decisions"] == 0


# What a README command writes that is also a test's evidence: run once, as the user would, and checked here.
SEQUENCES = REPO.parent / "shared" / "data" / "sequences"
OUTPUT_CHECKS: dict[str, Callable[[dict[str, Any]], None]] = {
    "out/eval.json": _eval_keeps_the_bare_tracker,
    "out/replay.json": _sitl_mission_replays_identically,
    "out/bench.json": _fleet_bench_ran_every_part,
}


_PS4 = "+README: "
_TRACE = f"""trap 'status=$?; echo "README command failed, exit status $status: $BASH_COMMAND" >&2' ERR
PS4={shlex.quote(_PS4)}
set -x"""
