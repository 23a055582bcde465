"""Every console script and every subcommand answers --help with real examples."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = {
    "cloudtrack-companion": "companion.cli",
    "cloudtrack-backend": "backend.cli",
    "cloudtrack-sim": "sitl.cli",
    "cloudtrack-gcs": "gcs.cli",
}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_console_script_help_shows_examples(script: str) -> None:
    exe = Path(sys.executable).with_name(script)
    assert exe.is_file(), f"{script} is not installed next to {sys.executable}"
    result = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "example" in result.stdout.lower()
    assert f"{script} " in result.stdout.split("xample", 1)[1], "examples must show real invocations"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_every_subcommand_help_renders_with_an_example(script: str) -> None:
    parser = importlib.import_module(SCRIPTS[script]).build_parser()
    commands = _subparsers(parser)
    assert commands
    for name, sub in commands.items():
        text = sub.format_help()
        assert "usage:" in text, name
        assert f"{script} {name}" in text.split("xample", 1)[-1], (
            f"{script} {name} --help shows no example of itself"
        )


WEIGHT_COMMANDS = [
    ("cloudtrack-companion", "run"),
    ("cloudtrack-companion", "eval"),
    ("cloudtrack-companion", "bench"),
    ("cloudtrack-backend", "serve"),
    ("cloudtrack-backend", "detect"),
    ("cloudtrack-backend", "eval"),
    ("cloudtrack-backend", "bench"),
    ("cloudtrack-sim", "run"),
]


@pytest.mark.parametrize(("script", "command"), WEIGHT_COMMANDS)
def test_every_command_that_loads_weights_takes_model_dir(script: str, command: str) -> None:
    sub = _subparsers(importlib.import_module(SCRIPTS[script]).build_parser())[command]
    options = {o for action in sub._actions for o in action.option_strings}
    assert "--model-dir" in options, f"{script} {command} has no --model-dir"
    assert "CLOUDTRACK_MODEL_DIR" in sub.format_help()  # and says what the default is


def test_serve_applies_model_dir_to_the_detector(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from backend.cli import main

    # An empty folder: serve must look for YOLOX there (and say so), not in the cache or the environment.
    assert main(["serve", "--model-dir", str(tmp_path)]) == 2
    assert str(tmp_path / "yolox_nano" / "yolox_nano.onnx") in capsys.readouterr().err


@pytest.mark.parametrize(
    ("script", "command", "name"),
    [("cloudtrack-backend", "serve", "backend.toml"), ("cloudtrack-companion", "run", "companion.toml")],
)
def test_config_help_names_the_files_read_without_it(script: str, command: str, name: str) -> None:
    from cloudtrack.config_files import config_search_path

    sub = _subparsers(importlib.import_module(SCRIPTS[script]).build_parser())[command]
    text = " ".join(sub.format_help().split())
    system, user = config_search_path(name, {"XDG_CONFIG_HOME": "$XDG_CONFIG_HOME"})
    assert f"default: {system}, then {user}, where they exist" in text
    assert "config/" not in text  # the repository's example file is never read by default


def test_camera_with_a_short_token_says_so_in_one_line() -> None:
    exe = Path(sys.executable).with_name("cloudtrack-sim")
    result = subprocess.run(
        [
            str(exe),
            "camera",
            "--autopilot-url",
            "udpin:127.0.0.1:0",
            "--backend-port",
            "0",
            "--token",
            "short",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--token must be at least 16 characters" in lines[0], result.stderr
    assert "Traceback" not in result.stdout + result.stderr and "short" not in lines[0]  # never echo a secret


def test_the_backend_starts_without_a_colour_science_warning() -> None:
    """The back-end installs no SciPy; colour-science must not warn about it at every start."""
    code = (
        "import sys, warnings; sys.modules['scipy'] = None; warnings.simplefilter('error');"
        "import backend.verifiers.colour_names"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "Warning" not in result.stderr, result.stderr
