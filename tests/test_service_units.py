"""The systemd units and `cloudtrack-companion service install`."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cloudtrack.config_files import load_config
from companion.config import CompanionConfig
from companion.flight_record import records_dir

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "companion.cli"]


def parse_unit(text: str) -> dict[str, list[tuple[str, str]]]:
    """Sections of (key, value) in order; systemd allows a key to repeat (DeviceAllow=...)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], [])
            continue
        assert current is not None and "=" in line, f"not a unit line: {raw!r}"
        key, value = line.split("=", 1)
        current.append((key.strip(), value.strip()))
    return sections


def value(section: list[tuple[str, str]], key: str) -> str:
    found = [v for k, v in section if k == key]
    assert len(found) == 1, f"{key}: {found}"
    return found[0]


@pytest.mark.parametrize("name", ["companion", "backend"])
def test_unit_is_notify_watchdog_restart_dedicated_user_hardened(name: str) -> None:
    unit = parse_unit((REPO / "config" / f"cloudtrack-{name}.service").read_text())
    service = unit["Service"]
    assert value(service, "Type") == "notify"
    assert value(service, "NotifyAccess") == "main"
    assert float(value(service, "WatchdogSec")) > 0
    assert value(service, "Restart") == "on-failure"
    assert value(service, "User") == "cloudtrack" and value(service, "Group") == "cloudtrack"
    # The process promises to exit within 2 s of SIGTERM; systemd must wait at least that long.
    assert float(value(service, "TimeoutStopSec")) >= 2
    for key, expected in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "CapabilityBoundingSet": "",
        "SystemCallFilter": "@system-service",
        "RestrictSUIDSGID": "yes",
    }.items():
        assert value(service, key) == expected, key
    assert value(unit["Install"], "WantedBy") == "multi-user.target"


def test_companion_unit_watchdog_outlasts_the_loop_stall_watchdog() -> None:
    """systemd restarts only what the companion's own stall watchdog (which stops motion) did not cure."""
    service = parse_unit((REPO / "config" / "cloudtrack-companion.service").read_text())["Service"]
    assert float(value(service, "WatchdogSec")) > 4 * CompanionConfig().safety.loop_stall_s
    devices = [v for k, v in service if k == "DeviceAllow"]
    assert value(service, "DevicePolicy") == "closed"
    assert "char-ttyAMA rw" in devices and "char-video4linux rw" in devices
    assert "dialout" in value(service, "SupplementaryGroups").split()


def test_install_print_writes_nothing_and_names_installed_program(tmp_path: Path) -> None:
    result = subprocess.run(
        [
            *CLI,
            "service",
            "install",
            "--print",
            "--unit-dir",
            str(tmp_path / "u"),
            "--config-dir",
            str(tmp_path / "c"),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert not (tmp_path / "u").exists() and not (tmp_path / "c").exists()
    program = Path(sys.executable).parent / "cloudtrack-companion"
    assert f"ExecStart={program} run --config {tmp_path / 'c' / 'companion.toml'}" in result.stdout
    assert 'connection = "/dev/ttyAMA0,921600"' in result.stdout


def test_install_writes_unit_systemd_accepts_and_config_that_validates(tmp_path: Path) -> None:
    unit_dir, config_dir = tmp_path / "units", tmp_path / "etc"
    args = [*CLI, "service", "install", "--unit-dir", str(unit_dir), "--config-dir", str(config_dir)]
    result = subprocess.run(args, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    unit_path = unit_dir / "cloudtrack-companion.service"
    config_path = config_dir / "companion.toml"
    config = load_config(CompanionConfig, config_path, environ={})
    assert config.mavlink.connection == "/dev/ttyAMA0,921600"
    # Records go to the unit's StateDirectory through $STATE_DIRECTORY, not a path written into the file.
    assert config.recording.dir == ""
    state_directory = value(parse_unit(unit_path.read_text())["Service"], "StateDirectory")
    assert records_dir(config.recording.dir, {"STATE_DIRECTORY": f"/var/lib/{state_directory}"}) == Path(
        "/var/lib/cloudtrack/records"
    )

    # The ExecStart line parses with the real command-line parser.
    exec_start = value(parse_unit(unit_path.read_text())["Service"], "ExecStart").split()
    assert Path(exec_start[0]).is_file()
    from companion.cli import build_parser

    parsed = build_parser().parse_args(exec_start[1:])
    assert parsed.command == "run" and Path(parsed.config) == config_path

    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is part of the test environment (Debian's systemd package)"
    verify = subprocess.run([analyze, "verify", "--man=no", str(unit_path)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    assert "Unknown" not in verify.stderr and "ignoring" not in verify.stderr, verify.stderr

    # A second install keeps the operator's configuration unless --force.
    config_path.write_text("# edited by the operator\n")
    again = subprocess.run(args, capture_output=True, text=True, check=True)
    assert "kept" in again.stdout and config_path.read_text() == "# edited by the operator\n"
    subprocess.run([*args, "--force"], capture_output=True, text=True, check=True)
    assert "/dev/ttyAMA0,921600" in config_path.read_text()


def test_install_into_unwritable_place_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    result = subprocess.run(
        [*CLI, "service", "install", "--unit-dir", str(blocker / "units"), "--config-dir", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 1
    assert "error:" in result.stderr and "Traceback" not in result.stderr


def test_backend_install_names_the_backend_program_and_its_config(tmp_path: Path) -> None:
    unit_dir, config_dir = tmp_path / "units", tmp_path / "etc"
    result = subprocess.run(
        [
            *CLI,
            "service",
            "install",
            "--backend",
            "--unit-dir",
            str(unit_dir),
            "--config-dir",
            str(config_dir),
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    from backend.cli import build_parser as backend_parser
    from backend.config import BackendConfig

    exec_start = value(
        parse_unit((unit_dir / "cloudtrack-backend.service").read_text())["Service"], "ExecStart"
    ).split()
    assert Path(exec_start[0]).name == "cloudtrack-backend" and Path(exec_start[0]).is_file()
    parsed = backend_parser().parse_args(exec_start[1:])
    assert parsed.command == "serve" and Path(parsed.config) == config_dir / "backend.toml"
    assert (
        load_config(BackendConfig, config_dir / "backend.toml", env_prefix="CLOUDTRACK_BACKEND_", environ={})
        == BackendConfig()
    )
    verify = subprocess.run(
        [
            shutil.which("systemd-analyze") or "systemd-analyze",
            "verify",
            "--man=no",
            str(unit_dir / "cloudtrack-backend.service"),
        ],
        capture_output=True,
        text=True,
    )
    assert verify.returncode == 0 and "Unknown" not in verify.stderr, verify.stderr


def test_the_package_ships_the_units_and_configs_of_the_source_tree() -> None:
    """`cloudtrack/systemd/` links to config/ (wheels copy the content), so an installed package has them."""
    shipped = REPO / "cloudtrack" / "systemd"
    for name in (
        "cloudtrack-companion.service",
        "cloudtrack-backend.service",
        "companion.toml",
        "backend.toml",
    ):
        assert (shipped / name).read_text() == (REPO / "config" / name).read_text(), name
