"""The H.264 writer: files browsers play, a caller that is never made to wait, failures kept off the caller."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from cloudtrack.h264_video import H264Writer


def _frames(n: int, size: tuple[int, int] = (160, 120)) -> list[np.ndarray]:
    w, h = size
    return [np.full((h, w, 3), (i * 20) % 255, np.uint8) for i in range(n)]


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_h264_writer_writes_every_frame_when_waiting_is_allowed(tmp_path: Path, process: bool) -> None:
    writer = H264Writer(tmp_path / "v.mp4", 25.0, process=process)
    for image in _frames(50):
        assert writer.write(image, wait=True)
    writer.close()
    assert writer.error is None and writer.frames_written == 50 and writer.frames_dropped == 0
    with av.open(str(tmp_path / "v.mp4")) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert (stream.codec_context.width, stream.codec_context.height) == (160, 120)
        assert sum(1 for _ in container.decode(video=0)) == 50
        assert abs(float(stream.duration * stream.time_base) - 2.0) < 0.1  # 50 frames at 25 FPS


def _slow_draw(image: np.ndarray, seconds: float) -> np.ndarray:
    time.sleep(seconds)  # an encoder that cannot keep up
    return image


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_h264_writer_drops_instead_of_blocking_a_slow_encoder(tmp_path: Path, process: bool) -> None:
    writer = H264Writer(tmp_path / "v.mp4", 30.0, queue_frames=4, process=process)
    started = time.perf_counter()
    accepted = [writer.write(image, functools.partial(_slow_draw, seconds=0.5)) for image in _frames(40)]
    elapsed = time.perf_counter() - started
    writer.close()
    assert elapsed < 1.0, "write() waited for the encoder"
    # The queue holds 4; the thread (or the pipe to the process) may have taken one or two more.
    assert sum(accepted) <= 8 and writer.frames_dropped == 40 - sum(accepted)
    assert writer.frames_written == sum(accepted) and writer.error is None


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_h264_writer_odd_sizes_and_failures_stay_off_the_caller(tmp_path: Path, process: bool) -> None:
    odd = H264Writer(tmp_path / "odd.mp4", 10.0, process=process)
    for image in _frames(5, (161, 121)):
        odd.write(image, wait=True)
    odd.close()
    with av.open(str(tmp_path / "odd.mp4")) as container:
        assert (
            container.streams.video[0].codec_context.width,
            container.streams.video[0].codec_context.height,
        ) == (160, 120)

    broken = H264Writer(tmp_path / "broken.mp4", 10.0, process=process)
    broken.write(_frames(1, (160, 120))[0], wait=True)
    broken.write(_frames(1, (320, 240))[0], wait=True)  # a second size: the encoder thread fails
    broken.close()
    assert broken.error is not None and "differs" in broken.error
    assert broken.write(_frames(1)[0]) is False  # later frames are refused, nothing raised

    # Nothing can be created in /proc, even by root.
    unwritable = H264Writer(Path("/proc/cloudtrack-video/v.mp4"), 10.0, process=process)
    unwritable.write(_frames(1)[0])
    unwritable.close()
    assert unwritable.error is not None and "cannot open" in unwritable.error


@pytest.mark.slow
def test_h264_video_plays_in_chromium_where_mp4v_does_not(tmp_path: Path) -> None:
    from tests.browser_video import play_in_chromium

    writer = H264Writer(tmp_path / "h264.mp4", 30.0)
    for image in _frames(60, (320, 240)):
        writer.write(image, wait=True)
    writer.close()
    shown = play_in_chromium(tmp_path / "h264.mp4")
    assert shown["error"] is None and shown["readyState"] >= 2, shown
    assert abs(shown["duration"] - 2.0) < 0.1 and (shown["width"], shown["height"]) == (320, 240)

    # What the demo wrote before: OpenCV's MPEG-4 Part 2, which the browser refuses (MEDIA_ERR_SRC_NOT_SUPPORTED).
    old = cv2.VideoWriter(str(tmp_path / "mp4v.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), 30.0, (320, 240))
    for image in _frames(60, (320, 240)):
        old.write(image)
    old.release()
    assert play_in_chromium(tmp_path / "mp4v.mp4")["error"] == 4


def test_h264_encoder_process_finishes_the_file_on_sigterm(tmp_path: Path) -> None:
    """systemd stops the unit with SIGTERM to every process: the encoder still writes a playable file."""
    import multiprocessing
    import os
    import signal

    writer = H264Writer(tmp_path / "v.mp4", 10.0, process=True)
    for image in _frames(10):
        writer.write(image, wait=True)
    deadline = time.monotonic() + 20
    while writer.frames_written < 10 and time.monotonic() < deadline:
        time.sleep(0.05)
    [child] = [p for p in multiprocessing.active_children() if p.name == "h264-v.mp4"]
    assert child.pid is not None
    os.kill(child.pid, signal.SIGTERM)
    child.join(10)
    assert child.exitcode == 0
    writer.close()
    with av.open(str(tmp_path / "v.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 10
