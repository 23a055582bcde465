"""Every autopilot parameter docs/operations.md names exists on the real autopilot (the shared SITL builds).

Starts `../shared/sitl/arducopter` (V4.7.0-dev) and `../shared/sitl/px4` (v1.16.0, SIH), reads each whole
parameter list with PARAM_REQUEST_LIST and checks the names in the doc's ArduPilot and PX4 tables; names
marked "board-only" are not in SITL, names given for older releases ("4.5/4.6: ...") are not checked
against this one.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil

from cloudtrack.mavlink_connection import open_connection

ROOT = Path(__file__).resolve().parent.parent


def _doc_names(section: str = "### ArduPilot", end: str = "### PX4") -> set[str]:
    text = (ROOT / "docs" / "operations.md").read_text()
    table = text[text.index(section) : text.index(end, text.index(section))]
    names: set[str] = set()
    for line in table.splitlines():
        if not line.startswith("| `"):
            continue
        first = line.split("|")[1]
        first = re.sub(r"\((4\.5/4\.6|older)[^)]*\)", "", first)  # older releases' names
        if "board-only" in first:
            continue
        names.update(re.findall(r"`([A-Z][A-Z0-9_]+)`", first))
    return names


def _arducopter_parameters(shared: Path, workdir: Path) -> dict[str, float]:
    binary = shared / "sitl" / "arducopter"
    assert binary.exists(), f"{binary} missing (the shared ArduCopter SITL build, see its SOURCE.md)"
    instance = 20 + os.getpid() % 40  # SITL's ports are 5760 + 10 * instance: keep clear of parallel runs
    port = 5760 + 10 * instance
    proc = subprocess.Popen(
        [str(binary), "--model", "+", "--speedup", "1", "--slave", "0", "--sim-address=127.0.0.1",
         "--defaults", str(shared / "sitl" / "copter.parm"), f"-I{instance}", "--home", "-35.363261,149.165230,584,90",
         "--wipe"],
        cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        conn = None
        deadline = time.monotonic() + 30
        while conn is None and time.monotonic() < deadline:
            try:
                conn = open_connection(f"tcp:127.0.0.1:{port}", 255, 190)
            except OSError:
                time.sleep(0.5)
        assert conn is not None, "ArduCopter SITL did not open its TCP port"
        params = _parameter_list(conn, 1)
        conn.close()
        return params
    finally:
        proc.kill()
        proc.wait(timeout=5)


def _parameter_list(
    conn: Any, system: int, value: Callable[[Any], float] = lambda msg: float(msg.param_value)
) -> dict[str, float]:
    """PARAM_REQUEST_LIST: every PARAM_VALUE until param_count names have arrived (asked again on a gap)."""
    params: dict[str, float] = {}
    total = None
    conn.mav.param_request_list_send(system, 1)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and (total is None or len(params) < total):
        msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        if msg is None:
            conn.mav.param_request_list_send(system, 1)
            continue
        params[msg.param_id] = value(msg)
        total = msg.param_count
    return params


def _px4_value(msg: Any) -> float:
    """PX4 sends an integer parameter's bytes in param_value (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE);
    ArduPilot casts it to a float."""
    if msg.param_type in (mavutil.mavlink.MAV_PARAM_TYPE_INT32, mavutil.mavlink.MAV_PARAM_TYPE_UINT32):
        return float(struct.unpack("<i", struct.pack("<f", msg.param_value))[0])
    return float(msg.param_value)


def _read_by_name(conn: Any, system: int, names: list[str]) -> dict[str, float]:
    """PARAM_REQUEST_READ by name: PX4 answers for every parameter it has, also one no module uses yet."""
    found: dict[str, float] = {}
    for name in names:
        for _ in range(3):
            conn.mav.param_request_read_send(system, 1, name.encode(), -1)
            msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
            if msg is not None and msg.param_id == name:
                found[name] = _px4_value(msg)
                break
    return found


def _px4_parameters(workdir: Path, names: set[str]) -> dict[str, float]:
    """The real PX4's list, as a GCS reads it on its GCS link. PX4 lists the parameters its modules use so far
    (MAV_1_* were missing from a list read 2 s after start), so the doc's names missing from it are read by
    name."""
    from sitl.px4_sitl import Px4Sitl, find_package

    sitl = Px4Sitl(find_package(), workdir, (47.397742, 8.545594, 488.0))
    sitl.params = {"SDLOG_MODE": -1}  # the binary's own defaults, not the scenarios' settings
    conn = open_connection(f"udpout:127.0.0.1:{sitl.ports.gcs}", 255, 190)
    try:
        sitl.start()
        deadline = time.monotonic() + 30
        while conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.1) is None:
            sitl.check_running()
            assert time.monotonic() < deadline, "PX4 never answered on its GCS link\n" + sitl.log_tail()
            conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # the first local sender becomes PX4's GCS partner
        params = _parameter_list(conn, sitl.system_id, _px4_value)
        return params | _read_by_name(conn, sitl.system_id, sorted(names - params.keys()))
    finally:
        conn.close()
        sitl.stop()


@pytest.mark.slow
def test_operations_doc_parameters_exist_on_arducopter(shared_dir: Path, tmp_path: Path) -> None:
    names = _doc_names()
    assert {"GUID_TIMEOUT", "MAV3_POSITION", "MAV_GCS_SYSID", "FS_OPTIONS"} <= names
    params = _arducopter_parameters(shared_dir, tmp_path)
    assert len(params) > 1000
    missing = sorted(n for n in names if n not in params)
    assert not missing, f"docs/operations.md names parameters ArduCopter 4.7 does not have: {missing}"
    for gone in ("SR2_POSITION", "SYSID_MYGCS"):  # the old names really are gone
        assert gone not in params
    assert params["GUID_TIMEOUT"] == 3.0  # the default the doc tells you to lower to 1 s


@pytest.mark.slow
def test_operations_doc_parameters_exist_on_px4_sitl(tmp_path: Path) -> None:
    names = _doc_names("### PX4", "### Message signing")
    assert {"COM_OF_LOSS_T", "COM_OBL_RC_ACT", "COM_RC_OVERRIDE", "MAV_1_MODE", "NAV_DLL_ACT"} <= names
    params = _px4_parameters(tmp_path, names | {"COM_OBL_ACT"})
    print(f"px4: {len(params)} parameters")
    assert len(params) > 500
    missing = sorted(n for n in names if n not in params)
    assert not missing, f"docs/operations.md names parameters PX4 1.16 does not have: {missing}"
    assert "COM_OBL_ACT" not in params  # gone since 1.14: COM_OBL_RC_ACT is the offboard-loss action
    # The defaults the doc tells you to change.
    assert params["COM_OF_LOSS_T"] == 1.0 and params["COM_OBL_RC_ACT"] == 0 and params["COM_RC_OVERRIDE"] == 1
