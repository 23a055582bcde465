"""Where configuration files and flight records live when no path is given (XDG and systemd conventions)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from backend.config import load_backend_config
from cloudtrack import config_files
from companion.config import load_companion_config
from companion.flight_record import records_dir


@pytest.fixture
def system_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """/etc/cloudtrack stood in by a temporary folder (the real one is not ours to write in a test)."""
    folder = tmp_path / "etc-cloudtrack"
    folder.mkdir()
    monkeypatch.setattr(config_files, "SYSTEM_CONFIG_DIR", folder)
    return folder


def test_config_lookup_reads_system_then_user_file(tmp_path: Path, system_dir: Path) -> None:
    xdg = tmp_path / "xdg"
    (xdg / "cloudtrack").mkdir(parents=True)
    (system_dir / "companion.toml").write_text('[vehicle]\nid = "from-etc"\n[safety]\nmax_speed_m_s = 2.0\n')
    env = {"XDG_CONFIG_HOME": str(xdg)}
    system_only = load_companion_config(None, environ=env)
    assert system_only.vehicle.id == "from-etc" and system_only.safety.max_speed_m_s == 2.0

    (xdg / "cloudtrack" / "companion.toml").write_text('[vehicle]\nid = "from-user"\n')
    both = load_companion_config(None, environ=env)
    assert (
        both.vehicle.id == "from-user" and both.safety.max_speed_m_s == 2.0
    )  # the user's file over the system's
    # The environment and --set still win over both files.
    over = load_companion_config(
        None, ["vehicle.id=from-flag"], environ={**env, "CLOUDTRACK_SAFETY__MAX_SPEED_M_S": "1"}
    )
    assert over.vehicle.id == "from-flag" and over.safety.max_speed_m_s == 1.0


def test_config_lookup_explicit_file_replaces_the_search(tmp_path: Path, system_dir: Path) -> None:
    (system_dir / "companion.toml").write_text('[vehicle]\nid = "from-etc"\n')
    explicit = tmp_path / "mine.toml"
    explicit.write_text("[safety]\nmax_speed_m_s = 2.5\n")
    config = load_companion_config(explicit, environ={"XDG_CONFIG_HOME": str(tmp_path / "none")})
    assert config.vehicle.id == "drone-1" and config.safety.max_speed_m_s == 2.5


def test_config_lookup_errors_name_the_found_file(tmp_path: Path, system_dir: Path) -> None:
    (system_dir / "backend.toml").write_text("[server]\nport = 0\n")
    with pytest.raises(config_files.ConfigError, match=str(system_dir / "backend.toml")):
        load_backend_config(None, environ={"XDG_CONFIG_HOME": str(tmp_path / "none")})


def test_config_lookup_user_file_reaches_the_command_line(tmp_path: Path) -> None:
    (tmp_path / "cloudtrack").mkdir()
    (tmp_path / "cloudtrack" / "companion.toml").write_text('[vehicle]\nid = "xdg-drone"\n')
    result = subprocess.run(
        [sys.executable, "-m", "companion.cli", "config", "show"],
        capture_output=True,
        text=True,
        env={**_environ(), "XDG_CONFIG_HOME": str(tmp_path)},
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert 'id = "xdg-drone"' in result.stdout


def test_records_dir_follows_config_then_systemd_then_xdg(tmp_path: Path) -> None:
    assert records_dir("~/flights", {}) == Path.home() / "flights"
    assert records_dir("", {"STATE_DIRECTORY": "/var/lib/cloudtrack:/var/lib/other"}) == Path(
        "/var/lib/cloudtrack/records"
    )
    assert records_dir("", {"XDG_DATA_HOME": str(tmp_path)}) == tmp_path / "cloudtrack" / "records"
    assert records_dir("", {}) == Path.home() / ".local" / "share" / "cloudtrack" / "records"


def _environ() -> dict[str, str]:
    return {
        k: v for k, v in os.environ.items() if not k.startswith("CLOUDTRACK_") or k == "CLOUDTRACK_SHARED"
    }
