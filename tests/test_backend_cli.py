"""`cloudtrack-backend` subcommands end to end: help, detect, eval, bench, and their error paths."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from backend.cli import main
from tests.test_backend_eval import _coco_set

CROSSING = "otb_Crossing/frames/000001.jpg"


@pytest.mark.parametrize("command", [[], ["serve"], ["detect"], ["eval"], ["bench"], ["service", "install"]])
def test_every_command_has_help_with_examples(command: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([*command, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out and "cloudtrack-backend" in out


def test_detect_one_image(
    models_dir: Path, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_json, out_jpg = tmp_path / "c.json", tmp_path / "c.jpg"
    code = main(
        [
            "detect",
            str(sequences_dir / CROSSING),
            "--prompt",
            "the person in dark clothes",
            "--model-dir",
            str(models_dir),
            "--json",
            str(out_json),
            "--draw",
            str(out_jpg),
        ]
    )
    assert code == 0
    result = json.loads(out_json.read_text())
    assert result["superset"] == "person" and result["models"]["verifier"] == "local:person"
    best = max(result["candidates"], key=lambda c: c["score"])
    assert (
        best["verdict"] == "yes" and 190 < (best["box"][0] + best["box"][2]) / 2 < 230
    )  # truth: x 205, w 17
    assert out_jpg.stat().st_size > 1000
    assert "YES" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--prompt", "a red kayak", "--superset", "unicorn"], "no COCO mapping"),
        (["--prompt", "something shiny"], "--superset"),
        (["--prompt", "a man", "--set", "verifier.kind=magic"], "verifier.kind"),
    ],
)
def test_detect_errors_exit_2_with_the_reason(
    models_dir: Path, sequences_dir: Path, extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["detect", str(sequences_dir / CROSSING), "--model-dir", str(models_dir), *extra]) == 2
    assert message in capsys.readouterr().err


def test_detect_refuses_a_corrupt_image(
    models_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8\xff" + bytes(100))
    assert main(["detect", str(bad), "--prompt", "a man", "--model-dir", str(models_dir)]) == 2
    assert "could not be decoded" in capsys.readouterr().err


def test_missing_weights_name_the_fix(
    tmp_path: Path, sequences_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(["detect", str(sequences_dir / CROSSING), "--prompt", "a man", "--model-dir", str(tmp_path)])
        == 2
    )
    assert "models download yolox" in capsys.readouterr().err


def test_eval_prints_the_table_and_writes_json(
    models_dir: Path, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    coco = _coco_set(sequences_dir, tmp_path / "set.json", step=40)
    code = main(
        [
            "eval",
            "--coco",
            str(coco),
            "--images",
            str(sequences_dir),
            "--verifier",
            "local",
            "--verifier",
            "none",
            "--model-dir",
            str(models_dir),
            "--json",
            str(tmp_path / "e.json"),
            "--markdown",
            str(tmp_path / "e.md"),
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert "| local:person |" in captured.out and "| none |" in captured.out
    assert "eval" in captured.err  # the progress bar
    scores = json.loads((tmp_path / "e.json").read_text())
    prompts = {a["referring"] for a in json.loads(coco.read_text())["annotations"]}
    assert [r["verifier"] for r in scores["results"]] == ["local:person", "none"]
    assert {t["prompt"] for t in scores["tasks"]} == prompts
    assert (tmp_path / "e.md").read_text().startswith("| Verifier |")


@pytest.mark.slow
def test_eval_on_tracking_sequences(
    models_dir: Path, sequences_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(
            [
                "eval",
                "--sequences",
                str(sequences_dir),
                "--step",
                "50",
                "--verifier",
                "none",
                "--model-dir",
                str(models_dir),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    # Each sequence's description is a task named after its sequence, whatever the other sequences are.
    assert re.search(r"T\d+ \(bag\): the white plastic bag on the ground", out) and "| none |" in out


def test_eval_input_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--coco", str(tmp_path / "missing.json"), "--images", str(tmp_path)]) == 2
    assert "missing.json" in capsys.readouterr().err
    assert main(["eval", "--voc", str(tmp_path)]) == 2
    assert "--attributes" in capsys.readouterr().err


def test_serve_refuses_a_bad_configuration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["serve", "--set", "server.port=99999"]) == 2
    assert "server.port" in capsys.readouterr().err
    assert main(["serve", "--set", 'detector.kind="simulated"']) == 2
    assert "cloudtrack-sim" in capsys.readouterr().err


def test_service_install_writes_the_backends_unit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    unit_dir, config_dir = tmp_path / "units", tmp_path / "etc"
    assert main(["service", "install", "--unit-dir", str(unit_dir), "--config-dir", str(config_dir)]) == 0
    unit = (unit_dir / "cloudtrack-backend.service").read_text()
    exec_start = next(line for line in unit.splitlines() if line.startswith("ExecStart=")).split()
    assert Path(exec_start[0].removeprefix("ExecStart=")).name == "cloudtrack-backend"
    assert exec_start[1:] == ["serve", "--config", str(config_dir / "backend.toml")]
    assert "[sessions]" in (config_dir / "backend.toml").read_text()
    assert not (unit_dir / "cloudtrack-companion.service").exists()
