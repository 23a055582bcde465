"""The H.264 writer: files browsers play, a caller that is never made to wait, failures kept off the caller."""

from __future__ import annotations

import threading
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


def test_h264_writer_writes_every_frame_when_waiting_is_allowed(tmp_path: Path) -> None:
    writer = H264Writer(tmp_path / "v.mp4", 25.0)
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


def test_h264_writer_drops_instead_of_blocking_a_slow_encoder(tmp_path: Path) -> None:
    release = threading.Event()

    def slow_draw(image: np.ndarray) -> np.ndarray:
        release.wait(5.0)  # an encoder that cannot keep up
        return image

    writer = H264Writer(tmp_path / "v.mp4", 30.0, queue_frames=4)
    started = time.perf_counter()
    accepted = [writer.write(image, slow_draw) for image in _frames(40)]
    elapsed = time.perf_counter() - started
    release.set()
    writer.close()
    assert elapsed < 1.0, "write() waited for the encoder"
    assert sum(accepted) <= 5 and writer.frames_dropped == 40 - sum(accepted)
    assert writer.frames_written == sum(accepted)


def test_h264_writer_odd_sizes_and_failures_stay_off_the_caller(tmp_path: Path) -> None:
    odd = H264Writer(tmp_path / "odd.mp4", 10.0)
    for image in _frames(5, (161, 121)):
        odd.write(image, wait=True)
    odd.close()
    with av.open(str(tmp_path / "odd.mp4")) as container:
        assert (
            container.streams.video[0].codec_context.width,
            container.streams.video[0].codec_context.height,
        ) == (160, 120)

    broken = H264Writer(tmp_path / "broken.mp4", 10.0)
    broken.write(_frames(1, (160, 120))[0], wait=True)
    broken.write(_frames(1, (320, 240))[0], wait=True)  # a second size: the encoder thread fails
    broken.close()
    assert broken.error is not None and "differs" in broken.error
    assert broken.write(_frames(1)[0]) is False  # later frames are refused, nothing raised

    unwritable = H264Writer(Path("/proc/cloudtrack-video/v.mp4"), 10.0)  # nothing can be created in /proc
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
