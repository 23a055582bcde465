"""`cloudtrack-backend pod-curve` end to end on real frames, real weights and the back-end's real pipeline
(two sequences, every 20th frame), and the curve the product ships."""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
from pathlib import Path

import cv2
import pytest

from backend.cli import main
from backend.config import BackendConfig
from backend_tools.pod_curve import is_target, read_sequence
from behaviors.geometry import Box
from behaviors.scene_light import MIN_MEAN_LUMA
from cloudtrack.detection_curves import SHIPPED, curve_for, load_curves
from companion.config import BackendConfig as CompanionBackendConfig

SEQUENCES = ("otb_Crossing", "uav123_person12_1")
STEP = 20


@pytest.fixture(scope="module")
def measured(
    models_dir: Path, sequences_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("pod_curve") / "curve.json"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(
            ["pod-curve", *(str(sequences_dir / s) for s in SEQUENCES), "--step", str(STEP),
             "--model-dir", str(models_dir), "--json", str(out), "--min-sequences", "2"]
        )  # fmt: skip
    assert code == 0
    return out, printed.getvalue()


def test_the_curve_file_loads_and_its_counts_add_up(measured: tuple[Path, str], sequences_dir: Path) -> None:
    out, printed = measured
    curve = load_curves(out)["person"]
    # Every STEP-th frame where the ground truth shows the target, each counted once.
    expected = {
        s: sum(
            1
            for i, box in enumerate(read_sequence(sequences_dir / s).boxes)
            if box is not None and i % STEP == 0
        )
        for s in SEQUENCES
    }
    assert {name: sum(b.samples for b in bins) for name, bins in curve.sequences} == expected
    assert curve.samples == sum(expected.values())
    for b in curve.bins:
        assert b.yes + b.uncertain <= b.proposed <= b.samples
    document = json.loads(out.read_text())
    assert document["measured"]["step"] == STEP
    assert {k: v["frames"] for k, v in document["measured"]["sequences"].items()} == expected
    looks = document["looks"]["classes"]["person"]
    assert (
        0 < looks["pairs"] < curve.samples
        and looks["missed_before"] + looks["found_before"] == looks["pairs"]
    )
    config = dict(curve.configuration)
    defaults = BackendConfig()
    assert (
        config["detector"] == defaults.detector.kind and config["model_file"] == "yolox_nano/yolox_nano.onnx"
    )
    assert config["tiles"] == str(defaults.detector.tiles) and config["keyframe_width"] == "640"
    assert config["verifier"] == defaults.verifier.kind
    assert "| size px | frames | proposed | POD (yes) | 95 % interval |" in printed
    assert "not independent" in printed


def test_check_reports_per_bin_and_gates_on_the_error(
    measured: tuple[Path, str], models_dir: Path, sequences_dir: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    curve_file, _ = measured
    out = tmp_path / "check.json"
    # Every bin with a frame counts, and any error at all is too much: the exit status follows the bins.
    code = main(
        ["pod-curve", str(sequences_dir / SEQUENCES[0]), "--step", str(STEP), "--model-dir", str(models_dir),
         "--check", str(curve_file), "--json", str(out), "--max-error", "0", "--min-samples", "1"]
    )  # fmt: skip
    printed = capsys.readouterr().out
    check = json.loads(out.read_text())
    person = check["classes"]["person"]
    rows = [r for r in person["bins"] if r["samples"]]
    assert rows and sum(r["samples"] for r in rows) == person["sequences"][SEQUENCES[0]]["samples"]
    assert person["sequences"][SEQUENCES[0]]["held_out"] is True  # predicted from the other sequence alone
    for r in rows:
        assert r["error"] == pytest.approx(r["predicted"] - r["observed"], abs=2e-4)
        assert r["baseline_error"] == pytest.approx(r["baseline"] - r["observed"], abs=2e-4)
    assert person["max_abs_error"] == max(abs(r["error"]) for r in rows)
    assert code == (1 if person["max_abs_error"] > 0 else 0)
    assert "reading: 'uncertain' is a miss" in printed
    assert (
        "| size px | frames | predicted | observed | predicted - observed | size-blind - observed |"
        in printed
    )


def test_frames_too_dark_for_the_curve_are_measured_apart(
    models_dir: Path, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real sequence as at dusk (every pixel at a fifth, mean luma under two stops below mid-grey) beside
    the same frames as shot: the dark copy is in no bin and no fit, and reported on its own."""
    source = sequences_dir / SEQUENCES[0]
    dusk = tmp_path / "dusk" / SEQUENCES[0]
    (dusk / "frames").mkdir(parents=True)
    for name in ("groundtruth.txt", "referring.txt", "source.json"):
        if (source / name).exists():
            shutil.copy(source / name, dusk / name)
    for i, frame in enumerate(sorted((source / "frames").iterdir())):
        if i % STEP == 0:  # only the frames measured
            cv2.imwrite(str(dusk / "frames" / frame.name), (cv2.imread(str(frame)) * 0.2).astype("uint8"))
        else:
            shutil.copy(frame, dusk / "frames" / frame.name)
    out, check_out = tmp_path / "curve.json", tmp_path / "check.json"
    code = main(
        ["pod-curve", str(dusk), str(sequences_dir / SEQUENCES[1]), "--step", str(STEP), "--model-dir",
         str(models_dir), "--json", str(out), "--min-sequences", "1", "--self-check", str(check_out)]
    )  # fmt: skip
    printed = capsys.readouterr().out
    assert code in (0, 1)  # the self-check's gate follows the bins (no --max-error: none)
    in_view = sum(1 for i, box in enumerate(read_sequence(source).boxes) if box is not None and i % STEP == 0)
    document = json.loads(out.read_text())
    dark = document["measured"]["sequences"][SEQUENCES[0]]
    assert dark["frames"] == 0 and dark["low_light"]["frames"] == in_view
    assert dark["low_light"]["mean_luma"] < MIN_MEAN_LUMA
    curve = load_curves(out)["person"]
    assert [name for name, _ in curve.sequences] == [SEQUENCES[1]]  # fitted on the lit sequence alone
    check = json.loads(check_out.read_text())
    assert check["low_light"][SEQUENCES[0]]["frames"] == in_view
    assert list(check["classes"]["person"]["sequences"]) == [SEQUENCES[1]]
    assert (
        "Low light (keyframe mean luma < 60" in printed
        and f"| {SEQUENCES[0]} | person | {in_view} |" in printed
    )


GROUND_TRUTH = Box(100, 100, 100, 100)


@pytest.mark.parametrize(
    ("candidate", "target"),
    [
        (Box(100, 100, 100, 100), True),
        (Box(110, 110, 90, 90), True),  # IoU 0.81
        (Box(150, 150, 100, 100), False),  # IoU 0.14
        (Box(120, 100, 50, 100), True),  # the rider inside the rider-and-bicycle box (IoU 0.5, inside)
        (Box(120, 100, 40, 80), True),  # IoU 0.32, all inside, spans 0.32
        (Box(120, 120, 40, 40), False),  # inside but a small part (a head, a bag): spans 0.16
        (Box(80, 100, 40, 100), False),  # spans 0.2 of it, half outside
        (Box(100, 100, 0, 0), False),
    ],
)
def test_a_candidate_is_the_target_by_overlap_or_held_by_its_box(candidate: Box, target: bool) -> None:
    assert is_target(candidate, GROUND_TRUTH) is target


@pytest.mark.parametrize(
    "content",
    [
        "{not json",
        '{"format": "cloudtrack-detection-curve/1", "curves": {"person": {"target_class": 3}}}',
        "x" * 3_000_000,
    ],
)
def test_a_bad_curve_file_is_a_one_line_error(
    content: str, sequences_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "curve.json"
    bad.write_text(content)
    assert main(["pod-curve", str(sequences_dir / SEQUENCES[0]), "--check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and str(bad) in err[0]


def test_a_folder_that_is_no_sequence_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "frames").mkdir()
    (tmp_path / "referring.txt").write_text("the person in red")
    (tmp_path / "frames" / "000001.jpg").write_bytes(b"")
    (tmp_path / "groundtruth.txt").write_text("1,2,3\n")
    assert main(["pod-curve", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"error: {tmp_path / 'groundtruth.txt'} line 1: expected x,y,w,h (nan where the target is absent)"
    ]


def test_the_shipped_curve_is_measured_for_the_backends_defaults() -> None:
    curve = curve_for("person")
    assert curve.samples > 0 and len(curve.sequences) >= 2
    assert "provisional" not in json.loads(SHIPPED.read_text())
    config = dict(curve.configuration)
    defaults = BackendConfig()
    # Another detector, tiling, threshold, keyframe width or verifier is another curve: measure it again
    # (docs/benchmarks.md, "Detection curve") when a default changes.
    assert config["detector"] == defaults.detector.kind
    assert config["tiles"] == str(defaults.detector.tiles)
    assert config["score_threshold"] == str(defaults.detector.score_threshold)
    assert config["verifier"] == defaults.verifier.kind
    assert config["keyframe_width"] == str(CompanionBackendConfig().max_keyframe_width)
    assert not math.isnan(curve.probability(30.0))
