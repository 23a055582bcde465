"""Secrets in configuration (issue 31): `config check` refuses a MAVLink signing key that is not 64 hex
digits, and a password or token inside a URL never reaches `config show`, an error or a log line."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cloudtrack.config_files import HIDDEN
from cloudtrack.logging_setup import JsonLinesFormatter, ReadableFormatter

ROOT = Path(__file__).resolve().parents[1]


def _companion(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "companion.cli", *args],
        capture_output=True,
        text=True,
        env={"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "PYTHONPATH": str(ROOT), **(env or {})},
        timeout=60,
    )


@pytest.mark.parametrize(
    ("key", "ok"),
    [
        ("", True),
        ("5e" * 32, True),
        ("5E" * 32, True),
        ("abc123", False),
        ("zz" * 32, False),
        ("5e" * 33, False),
    ],
)
def test_config_check_checks_the_signing_key(tmp_path: Path, key: str, ok: bool) -> None:
    config = tmp_path / "companion.toml"
    config.write_text(f'[mavlink]\nsigning_key = "{key}"\n')
    checked = _companion("config", "check", str(config))
    assert (checked.returncode == 0) is ok, checked.stderr
    if not ok:
        assert "64 hexadecimal" in checked.stderr and (len(key) < 3 or key not in checked.stderr)


def test_config_show_hides_a_password_in_a_url() -> None:
    url = "https://pilot:hunter2-secret@backend.example.org:8443/?token=abc123def"
    shown = _companion("config", "show", "--set", f'backend.url="{url}"')
    assert shown.returncode == 0, shown.stderr
    assert "hunter2-secret" not in shown.stdout and "abc123def" not in shown.stdout
    assert f'url = "https://pilot:{HIDDEN}@backend.example.org:8443/?token={HIDDEN}"' in shown.stdout


@pytest.mark.parametrize(
    ("text", "hidden"),
    [
        ("https://pilot:s3cret@host/v1", "https://pilot:<hidden>@host/v1"),
        ("redis://:s3cret@127.0.0.1:6379/0", "redis://:<hidden>@127.0.0.1:6379/0"),
        ("https://s3cret@host/", "https://<hidden>@host/"),
        ("http://h/p?api_key=s3cret&x=1#f", "http://h/p?api_key=<hidden>&x=1#f"),
        ("back-end http://127.0.0.1:8080 unreachable", "back-end http://127.0.0.1:8080 unreachable"),
        ("no url = here", "no url = here"),
    ],
)
def test_url_secrets_table(text: str, hidden: str) -> None:
    from cloudtrack.config_files import hide_url_secrets

    assert hide_url_secrets(text) == hidden


@pytest.mark.parametrize("formatter", [ReadableFormatter(), JsonLinesFormatter()])
def test_log_lines_hide_url_secrets(formatter: logging.Formatter) -> None:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter)
    log = logging.getLogger("test.secrets")
    log.addHandler(handler)
    try:
        log.warning("back-end %s unreachable", "https://pilot:s3cret@host/")
    finally:
        log.removeHandler(handler)
    assert "s3cret" not in stream.getvalue() and "pilot:<hidden>@host" in stream.getvalue()
