"""`cloudtrack-companion bench --recording`: the onboard loop with the flight record's H.264 video on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from companion.cli import main


def test_bench_recording_encodes_the_loops_frames_and_reports_the_goal_ratio(
    models_dir: Path, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench.json"
    code = main(
        [
            "bench",
            "--tracker",
            "nano",
            "--sequence",
            str(sequences_dir / "uav123_person12_1"),
            "--frames",
            "20",
            "--passes",
            "2",
            "--model-dir",
            str(models_dir),
            "--recording",
            "--json",
            str(out),
        ]
    )
    assert code == 0
    data = json.loads(out.read_text())
    assert data["recording"] is True
    # Every loop frame went to the encoder: encoded, or dropped by its full queue (never waited for).
    total = data["video_frames_encoded"] + data["video_frames_dropped"] + data["video_frames_skipped"]
    assert total == 2 * 19
    assert data["video_frames_encoded"] > 0
    assert 0 < data["recording_ms"] < data["overhead_ms"] and data["encode_cpu_ms"] > 0
    assert data["setpoints_received"] == 2 * 19
    printed = capsys.readouterr().out
    assert "everything else with recording" in printed and "GOAL ratio (in-loop)" in printed
    assert "video frames encoded" in printed
