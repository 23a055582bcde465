"""`cloudtrack-gcs status --all` (issue 43 item 4): one line per vehicle, from a real back-end on loopback
(uvicorn, `tests.live_backend`) holding two vehicles' statuses; the supervisor token from a file or the
environment, never on the command line or in what it prints; a refusal or an unreachable back-end is one
line and a non-zero exit."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import requests

from cloudtrack.api_models import VehicleStatus
from gcs import cli as gcs_cli
from gcs import fleet_status
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, LiveBackend, free_port, live_backend

GCS = [str(Path(sys.executable).with_name("cloudtrack-gcs"))]
AREA_1 = [[47.3970, 8.5450], [47.3985, 8.5450], [47.3985, 8.5460], [47.3970, 8.5460]]
AREA_2 = [[47.3970, 8.5460], [47.3985, 8.5460], [47.3985, 8.5470], [47.3970, 8.5470]]
POD = {  # one cell at POD 0.8 (round(0.8 * 250) = 200: base64 "yA==")
    "target": "person", "posture": "standing", "target_pod": 0.8, "origin": [47.3970, 8.5460], "cell_m": 50.0,
    "rows": 1, "cols": 1, "values": "yA==", "mean": 0.8, "at_target": 1.0, "looks": 3,
}  # fmt: skip
STATUSES = {
    "drone-1": {
        "mission_id": "m-43", "state": "SEARCHING", "position": [47.39712, 8.54551], "altitude_m": 30.0,
        "search": {"area": AREA_1, "coverage": 0.42, "mode": "AUTO"},
    },
    "drone-2": {
        "mission_id": "m-43", "state": "AWAITING_SUPERVISOR", "position": [47.39801, 8.54655],
        "search": {"area": AREA_2, "coverage": 0.25, "mode": "GUIDED", "pod": POD},
    },
}  # fmt: skip


@pytest.fixture(scope="module")
def backend(models_dir: Path) -> Iterator[LiveBackend]:
    # Reported once for the module: silence must not make the vehicles drop-outs however long it runs.
    with live_backend(models_dir, dropout_s=3600) as running:
        for vehicle, status in STATUSES.items():
            answer = requests.post(
                f"{running.url}/v1/vehicles/{vehicle}/status",
                json=status,
                headers={"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"},
                timeout=10,
            )
            assert answer.status_code == 200, answer.text[:300]
        yield running


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    path = tmp_path / "supervisor-token"
    path.write_text(SUPERVISOR_TOKEN + "\n")
    path.chmod(0o600)
    return path


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, list[str], str]:
    code = gcs_cli.main(["status", "--all", *args])
    out, err = capsys.readouterr()
    assert SUPERVISOR_TOKEN not in out + err
    return code, out.splitlines(), err


def test_status_all_prints_a_line_per_vehicle(
    backend: LiveBackend, token_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, lines, err = _run(capsys, "--backend", backend.url, "--supervisor-token-file", str(token_file))
    assert code == 0, err
    assert len(lines) == 2, lines
    one, two = lines
    assert one.startswith("drone-1  mission m-43  SEARCHING  mode AUTO  at 47.397120,8.545510 30 m")
    assert "coverage 42 %" in one and "POD" not in one
    assert two.startswith("drone-2  mission m-43  AWAITING_SUPERVISOR  mode GUIDED  at 47.398010,8.546550")
    assert "coverage 25 %, POD >= 0.80 on 100 % (mean 0.80)" in two
    for line in lines:
        age = re.search(r"last report (\d+) s ago$", line)
        assert age is not None and int(age.group(1)) <= 60, line


def test_status_all_takes_the_token_from_the_environment_and_filters_a_mission(
    backend: LiveBackend, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(fleet_status.TOKEN_ENV, SUPERVISOR_TOKEN)
    monkeypatch.setenv(fleet_status.BACKEND_ENV, backend.url)
    code, lines, _ = _run(capsys, "--mission", "m-43")
    assert code == 0 and [line.split()[0] for line in lines] == ["drone-1", "drone-2"]
    code, lines, _ = _run(capsys, "--mission", "m-99")
    assert code == 0 and lines == [f"no vehicle in mission m-99 has reported to {backend.url}"]


def test_status_all_as_the_console_script(backend: LiveBackend, token_file: Path) -> None:
    result = subprocess.run(
        [*GCS, "status", "--all", "--backend", backend.url, "--supervisor-token-file", str(token_file)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert [line.split()[0] for line in result.stdout.splitlines()] == ["drone-1", "drone-2"]


def test_status_all_refused_or_unreachable_is_one_line(
    backend: LiveBackend, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wrong = tmp_path / "wrong-token"
    wrong.write_text(VEHICLE_TOKENS["drone-1"])  # a vehicle's token is not the supervisor's
    code, lines, err = _run(capsys, "--backend", backend.url, "--supervisor-token-file", str(wrong))
    assert code == fleet_status.EXIT_REFUSED and lines == []
    assert len(err.splitlines()) == 1 and "refused the supervisor token (HTTP 403)" in err, err
    assert VEHICLE_TOKENS["drone-1"] not in err
    gone = f"http://pilot:secret@127.0.0.1:{free_port()}"
    code, lines, err = _run(capsys, "--backend", gone, "--supervisor-token-file", str(wrong))
    assert code == fleet_status.EXIT_UNREACHABLE and lines == []
    assert (
        err.strip()
        == f"error: back-end http://pilot:<hidden>@127.0.0.1:{gone.rsplit(':', 1)[1]} unreachable: connection refused"
    )


def test_status_all_never_takes_a_token_on_the_command_line(
    backend: LiveBackend, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(fleet_status.TOKEN_ENV, raising=False)
    code, _, err = _run(capsys, "--backend", backend.url, "--supervisor-token", SUPERVISOR_TOKEN)
    assert code == 2 and "visible to every user" in err
    code, _, err = _run(capsys, "--backend", backend.url)
    assert code == 2 and "--supervisor-token-file" in err
    assert gcs_cli.main(["status", "--backend", backend.url]) == 2  # --backend is for --all
    assert "go with status --all" in capsys.readouterr().err


def test_a_line_marks_a_silent_vehicle_and_keeps_hostile_text_on_one_line() -> None:
    status = VehicleStatus.model_validate(
        {
            "vehicle_id": "drone-3",
            "updated_at": 1000.0,
            "state": "SEARCHING\n\x1b[2Jfake line",
            "search": None,
        }
    )
    assert fleet_status.status_line(status, now=1003.0) == (
        "drone-3  mission -  SEARCHING [2Jfake line  mode -  position unknown  no search area  last report 3 s ago"
    )
    line = fleet_status.status_line(status, now=1045.0)
    assert line.endswith("last report 45 s ago, SILENT") and "\n" not in line and "\x1b" not in line
    assert fleet_status.status_line(status, now=1000.0 + 7200).endswith("last report 2.0 h ago, SILENT")


def test_status_all_offers_the_replan_for_a_vehicle_that_went_home(
    models_dir: Path, token_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """drone-2 reports RTL with its part unflown: below the vehicles' lines, the re-plan onto drone-1."""
    part = [[47.3980, 8.5450], [47.3980, 8.5470], [47.3990, 8.5470], [47.3990, 8.5450]]
    with live_backend(models_dir, dropout_s=3600) as running:
        for vehicle, search in (
            ("drone-1", {"area": AREA_1, "coverage": 0.3, "mode": "AUTO"}),
            ("drone-2", {"area": part, "coverage": 0.0, "mode": "RTL"}),
        ):
            answer = requests.post(
                f"{running.url}/v1/vehicles/{vehicle}/status",
                json={"mission_id": "m-50", "state": "SEARCHING", "search": search},
                headers={"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"},
                timeout=10,
            )
            assert answer.status_code == 200, answer.text[:300]
        code, lines, err = _run(capsys, "--backend", running.url, "--supervisor-token-file", str(token_file))
    assert code == 0, err
    assert [line.split()[0] for line in lines[:2]] == ["drone-1", "drone-2"]
    (offer,) = lines[2:]
    assert (
        offer.startswith("REPLAN OFFERED: drone-2 left the search (mode RTL), ")
        and "ha unflown; onto drone-1:" in offer
    )
    assert offer.endswith(
        "cloudtrack-gcs replan --mission m-50 --fleet FLEET_FILE --altitude SURVEY_ALTITUDE"
    )
