"""`cloudtrack-backend bench --fleet-map` at a tiny scale (1 and 2 vehicles, 2 s each, real `serve` processes on
loopback): it produces every figure, sane, and every vehicle is on the merged map and the page. Timings are
printed by the bench, never asserted here. Select: -k fleet_map.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from backend.cli import main
from backend_tools.mission_fleet_bench import FleetMapSettings, part_flight, status_bodies
from cloudtrack.api_models import VehicleStatusIn


def test_fleet_map_reports_are_valid_status_reports_growing_per_strip() -> None:
    flight = part_flight(FleetMapSettings(warm_s=20.0), 3)
    bodies = status_bodies(flight, 3, 100.0)
    reports = [[VehicleStatusIn.model_validate_json(b) for b in mine] for mine in bodies]
    for mine in reports:
        assert all(r.mission_id == "fleet-map" and r.search is not None for r in mine)
        first, last = mine[0].search, mine[-1].search
        assert first is not None and last is not None and last.pod is not None and first.pod is not None
        assert last.coverage >= first.coverage > 0 and last.pod.looks > first.pod.looks
    # Each vehicle its own strip: the same shape, side by side from west to east.
    west = [min(p[1] for p in mine[0].search.area) for mine in reports if mine[0].search is not None]
    assert west == sorted(west) and len(set(west)) == 3


def test_fleet_map_bench_prints_every_figure(models_dir: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "fleet-map.json"
    argv = ["bench", "--fleet-map", "2", "--fleet-s", "2", "--fleet-warm-s", "20"]
    assert main([*argv, "--model-dir", str(models_dir), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| vehicles | status p50/p95 [ms]" in printed and "2 vs 1: map p95 x" in printed
    report = json.loads(out.read_text())
    assert [r["vehicles"] for r in report["runs"]] == [1, 2]
    for run in report["runs"]:
        n = run["vehicles"]
        assert run["errors"] == 0, run["error_examples"]
        assert run["status_reports"] == 2 * n  # every report answered 200
        for part in ("status", "decisions_poll", "state", "map"):
            assert run[part]["count"] >= 1 and 0 <= run[part]["p50_ms"] <= run[part]["p95_ms"], part
        assert run["map"]["bytes"] > 0 and run["state"]["bytes"] > 0 and run["status_bytes"] > 0
        assert 0 < run["rss_mb"]["start"] <= run["rss_mb"]["max"]
        assert run["server_cpu"]["seconds"] > 0 and run["merge_cpu_ms"] >= 0
        assert run["page_stream"]["events"] >= 1 and run["page_stream"]["bytes_per_s"] > 0
        final = run["final"]
        assert final["map_vehicles"] == [f"bench-{i}" for i in range(n)]  # every vehicle on the merged map
        assert final["page_vehicles"] == n and 0 < final["map_coverage"] <= 1 and final["map_pod_cells"] > 0
    ratios = report["ratios"]
    assert ratios["vehicles"] == "2 vs 1"
    assert all(math.isfinite(v) and v > 0 for k, v in ratios.items() if k != "vehicles")
