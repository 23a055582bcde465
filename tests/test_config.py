from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from cloudtrack.config_files import ConfigError, load_config
from companion.config import CompanionConfig, load_companion_config

REPO = Path(__file__).resolve().parents[1]


def test_default_file_matches_schema_defaults() -> None:
    assert load_config(CompanionConfig, REPO / "config" / "companion.toml", environ={}) == CompanionConfig()


def test_unknown_key_names_file_key_and_allowed(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[mavlink]\nconection = "udpin:0.0.0.0:14540"\n')
    with pytest.raises(ConfigError) as info:
        load_config(CompanionConfig, path, environ={})
    message = str(info.value)
    assert str(path) in message and "mavlink.conection" in message and "connection" in message


def test_wrong_type_and_range_are_named(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[safety]\nmax_speed_m_s = 99\n[camera]\nwidth = "wide"\n')
    with pytest.raises(ConfigError) as info:
        load_config(CompanionConfig, path, environ={})
    message = str(info.value)
    assert "safety.max_speed_m_s" in message and "less than or equal to 15" in message
    assert "camera.width" in message


def test_altitude_band_must_be_ordered() -> None:
    with pytest.raises(ConfigError, match="min_altitude_m"):
        load_config(
            CompanionConfig,
            None,
            environ={},
            assignments=["safety.min_altitude_m=50", "safety.max_altitude_m=40"],
        )


def test_precedence_file_then_environment_then_flags(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[safety]\nmax_speed_m_s = 2.0\nmax_yaw_rate_deg_s = 30\n[vehicle]\nid = "file"\n')
    env = {"CLOUDTRACK_SAFETY__MAX_SPEED_M_S": "2.5", "CLOUDTRACK_VEHICLE__ID": "env"}
    config = load_config(CompanionConfig, path, environ=env, assignments=["vehicle.id=flag"])
    assert config.safety.max_speed_m_s == 2.5
    assert config.safety.max_yaw_rate_deg_s == 30
    assert config.vehicle.id == "flag"


def test_environment_error_names_environment() -> None:
    with pytest.raises(ConfigError, match="environment: key 'mavlink.setpoint_rate_hz'"):
        load_config(CompanionConfig, None, environ={"CLOUDTRACK_MAVLINK__SETPOINT_RATE_HZ": "100"})


def test_malformed_toml_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[mavlink\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(CompanionConfig, bad, environ={})
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(CompanionConfig, tmp_path / "absent.toml", environ={})


def test_config_check_cli_exits_nonzero_naming_key(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[behavior]\nstandof_m = 10\n")
    result = subprocess.run(
        [sys.executable, "-m", "companion.cli", "config", "check", str(path)], capture_output=True, text=True
    )
    assert result.returncode == 2
    assert "behavior.standof_m" in result.stderr
    good = subprocess.run(
        [sys.executable, "-m", "companion.cli", "config", "check", str(REPO / "config" / "companion.toml")],
        capture_output=True,
        text=True,
    )
    assert good.returncode == 0, good.stderr


def test_config_show_prints_effective_values() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "companion.cli", "config", "show", "--set", "safety.max_speed_m_s=2.25"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    assert "max_speed_m_s = 2.25" in result.stdout


def test_backend_service_variables_do_not_break_the_companion() -> None:
    env = {
        "CLOUDTRACK_BACKEND_AUTH__TOKENS": '{"drone-1": "s3cret"}',  # the back-end's, same host
        "CLOUDTRACK_BACKEND__TOKEN": "s3cret",  # the companion's own [backend] token
        "CLOUDTRACK_MAVLINK__CONNECTION": "serial:/dev/ttyAMA0:921600",
    }
    config = load_companion_config(None, environ=env)
    assert config.backend.token == "s3cret"
    assert config.mavlink.connection == "serial:/dev/ttyAMA0:921600"
    with pytest.raises(ConfigError, match="mavlnk"):
        load_companion_config(None, environ={"CLOUDTRACK_MAVLNK__CONNECTION": "x"})
