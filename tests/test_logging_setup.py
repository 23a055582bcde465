from __future__ import annotations

import json
import logging

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
