"""Every ArduPilot parameter docs/operations.md names exists on a real ArduCopter (the shared SITL build).

Starts `../shared/sitl/arducopter` (V4.7.0-dev), reads its whole parameter list with PARAM_REQUEST_LIST
and checks the names in the doc's ArduPilot table; names marked "board-only" are not in SITL, names given
for older releases ("4.5/4.6: ...") are not checked against this one.
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from pathlib import Path

import pytest

from cloudtrack.mavlink_connection import open_connection

ROOT = Path(__file__).resolve().parent.parent


def _doc_names() -> set[str]:
    text = (ROOT / "docs" / "operations.md").read_text()
    table = text[text.index("### ArduPilot") : text.index("### PX4")]
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
        params: dict[str, float] = {}
        total = None
        conn.mav.param_request_list_send(1, 1)
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and (total is None or len(params) < total):
            msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            if msg is None:
                conn.mav.param_request_list_send(1, 1)
                continue
            params[msg.param_id] = msg.param_value
            total = msg.param_count
        conn.close()
        return params
    finally:
        proc.kill()
        proc.wait(timeout=5)


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
