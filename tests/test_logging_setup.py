from __future__ import annotations

import io
import json
import logging
import sys

import pytest

from cloudtrack.logging_setup import setup_logging


def test_json_lines_carry_message_and_extras(capsys: pytest.CaptureFixture[str]) -> None:
    setup_logging("INFO", json_lines=True)
    logging.getLogger("cloudtrack.test").warning("backend lost after %d s", 10, extra={"vehicle": "drone-1"})
    line = capsys.readouterr().err.strip().splitlines()[-1]
    entry = json.loads(line)
    assert entry["message"] == "backend lost after 10 s"
    assert (
        entry["level"] == "warning" and entry["vehicle"] == "drone-1" and entry["logger"] == "cloudtrack.test"
    )


def test_readable_by_default_and_level_filter(capsys: pytest.CaptureFixture[str]) -> None:
    setup_logging("WARNING")
    log = logging.getLogger("cloudtrack.test")
    log.info("hidden")
    log.error("shown")
    err = capsys.readouterr().err
    assert "hidden" not in err and "ERROR" in err and "cloudtrack.test: shown" in err
    setup_logging("INFO")


def test_lines_go_to_the_stderr_of_the_moment_not_a_closed_one(monkeypatch: pytest.MonkeyPatch) -> None:
    # A stderr swapped and closed after set-up (a test's capture) once made every later line a "Logging
    # error" traceback that stalled the logging thread for 600 ms (a mock autopilot's mode change).
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    setup_logging("INFO")
    first.close()
    second = io.StringIO()
    monkeypatch.setattr(sys, "stderr", second)
    logging.getLogger("cloudtrack.test").warning("after the swap")
    assert "cloudtrack.test: after the swap" in second.getvalue()
    monkeypatch.undo()
    setup_logging("INFO")
