"""`cloudtrack-gcs mode MODE`: the mode the autopilot's HEARTBEAT shows afterwards, the COMMAND_ACK printed,
and one line with its exit code for a refusal, a mode the autopilot does not list, or no answer; against
the mock (both personalities), the real ArduCopter SITL and the real PX4 SITL."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from gcs import cli as gcs_cli
from sitl.autopilot import SimulatedAutopilot
from tests.mavlink_harness import autopilot

GCS = str(Path(sys.executable).with_name("cloudtrack-gcs"))


def _mode(capsys: pytest.CaptureFixture[str], sim: SimulatedAutopilot, name: str) -> tuple[int, str, str]:
    code = gcs_cli.main(
        ["--connect", f"udpout:127.0.0.1:{sim.link_port('gcs')}", "--timeout", "3", "mode", name]
    )
    out, err = capsys.readouterr()
    return code, out, "".join(line for line in err.splitlines(keepends=True) if line.startswith("error: "))


def test_arducopter_modes_on_the_mock(capsys: pytest.CaptureFixture[str]) -> None:
    with autopilot("ardupilot", start_height_m=10.0) as sim:
        assert _mode(capsys, sim, "loiter") == (
            0, "mode LOITER: ACCEPTED; the autopilot's HEARTBEAT shows LOITER (was GUIDED)\n", ""
        )  # fmt: skip
        assert sim.mode == "LOITER"
        code, out, err = _mode(capsys, sim, "AUTO")  # no mission: ArduCopter refuses
        assert (code, out) == (1, "")
        assert err == (
            'error: mode AUTO refused by the autopilot: FAILED ("Mode change to AUTO failed: init failed"); '
            "it stays in LOITER\n"
        )
        code, out, err = _mode(capsys, sim, "MISSION")
        assert (code, out) == (2, "")
        assert err.startswith(
            "error: ArduPilot (vehicle type 2) has no mode 'MISSION' (its mission mode is AUTO); "
        )
        assert (
            "its modes: STABILIZE, ACRO, ALT_HOLD, AUTO, GUIDED, LOITER, RTL" in err and err.count("\n") == 1
        )
        assert _mode(capsys, sim, "GUIDED")[0] == 0 and sim.mode == "GUIDED"


def test_px4_modes_on_the_mock(capsys: pytest.CaptureFixture[str]) -> None:
    with autopilot("px4", start_height_m=10.0) as sim:
        assert _mode(capsys, sim, "HOLD") == (
            0, "mode HOLD: ACCEPTED; the autopilot's HEARTBEAT shows HOLD (was POSCTL)\n", ""
        )  # fmt: skip
        code, out, err = _mode(capsys, sim, "MISSION")  # PX4 acknowledges at once, then refuses
        assert (code, out) == (1, "")
        assert err == (
            'error: mode MISSION refused by the autopilot: TEMPORARILY_REJECTED ("No valid mission"); '
            "it stays in HOLD\n"
        )
        code, _, err = _mode(capsys, sim, "AUTO")
        assert code == 2 and "PX4 (vehicle type 2) has no mode 'AUTO' (its mission mode is MISSION)" in err
        # PX4 accepts a mode it does not fly and changes nothing: the HEARTBEAT says so.
        code, out, err = _mode(capsys, sim, "ACRO")
        assert (code, out) == (1, "")
        assert (
            err == "error: mode ACRO was accepted, but the autopilot's HEARTBEAT still shows HOLD after 3 s\n"
        )


def test_a_signed_link_takes_the_autopilots_unsigned_answer(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    key = tmp_path / "signing.key"
    key.write_text("ab" * 32)
    with autopilot("ardupilot", start_height_m=10.0) as sim:
        link = ["--connect", f"udpout:127.0.0.1:{sim.link_port('gcs')}", "--timeout", "3"]
        assert gcs_cli.main([*link, "--signing-key-file", str(key), "mode", "LOITER"]) == 0
        assert "HEARTBEAT shows LOITER" in capsys.readouterr().out and sim.mode == "LOITER"


def test_no_autopilot_is_a_one_line_timeout() -> None:
    done = subprocess.run(
        [GCS, "--connect", "udpout:127.0.0.1:9", "--timeout", "1", "mode", "AUTO"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert done.returncode == 3 and done.stdout == ""
    assert done.stderr.startswith("error: no HEARTBEAT from system 1 on udpout:127.0.0.1:9 within 1 s")
    assert done.stderr.count("\n") == 1


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([GCS, *args], capture_output=True, text=True, timeout=60)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_arducopter_sitl_modes(tmp_path: Path) -> None:
    from sitl.arducopter_sitl import ArduCopterSitl, RealAutopilot, find_binary
    from sitl.scenarios import ScriptedGcs

    sitl = ArduCopterSitl(find_binary(), tmp_path, (47.397742, 8.545594, 488.0, 0.0), speedup=10.0).start()
    gcs = ScriptedGcs(f"tcp:127.0.0.1:{sitl.ports.gcs}").start()
    real = RealAutopilot(sitl, gcs)
    try:
        real.fly_up(10.0, progress=print)
        # SERIAL5: a laptop's GCS
        link = ["--connect", f"tcp:127.0.0.1:{sitl.ports.ground}", "--timeout", "5"]
        done = _run(*link, "mode", "LOITER")
        assert (done.returncode, done.stdout, done.stderr) == (
            0, "mode LOITER: ACCEPTED; the autopilot's HEARTBEAT shows LOITER (was GUIDED)\n", ""
        ), done  # fmt: skip
        assert real.mode_name() == "LOITER"
        done = _run(*link, "mode", "AUTO")  # airborne without a mission
        assert (done.returncode, done.stdout) == (1, ""), done
        assert done.stderr.startswith("error: mode AUTO refused by the autopilot: FAILED"), done.stderr
        assert done.stderr.endswith("; it stays in LOITER\n") and done.stderr.count("\n") == 1, done.stderr
        done = _run(*link, "mode", "HOLD")
        assert done.returncode == 2 and "has no mode 'HOLD' (its loiter mode is LOITER)" in done.stderr
        done = _run(*link, "mode", "rtl")
        assert (done.returncode, done.stdout) == (
            0, "mode RTL: ACCEPTED; the autopilot's HEARTBEAT shows RTL (was LOITER)\n"
        ), done  # fmt: skip
    finally:
        gcs.stop()
        real.close()


@pytest.mark.slow
@pytest.mark.shares_px4
@pytest.mark.timeout(300)
def test_px4_sitl_modes(shared_px4: Any) -> None:
    px4 = shared_px4.get()
    link = ["--connect", px4.ground_url(), "--system", str(px4.system_id), "--timeout", "8"]
    done = _run(*link, "mode", "MISSION")  # no mission uploaded
    assert (done.returncode, done.stdout) == (1, ""), done
    assert done.stderr.startswith("error: mode MISSION ") and done.stderr.count("\n") == 1, done.stderr
    done = _run(*link, "mode", "AUTO")
    assert done.returncode == 2 and "has no mode 'AUTO' (its mission mode is MISSION)" in done.stderr
    done = _run(*link, "mode", "POSCTL")
    assert (done.returncode, done.stdout) == (
        0, "mode POSCTL: ACCEPTED; the autopilot's HEARTBEAT shows POSCTL (was HOLD)\n"
    ), done  # fmt: skip
    done = _run(*link, "mode", "hold")
    assert (done.returncode, done.stdout) == (
        0, "mode HOLD: ACCEPTED; the autopilot's HEARTBEAT shows HOLD (was POSCTL)\n"
    ), done  # fmt: skip
