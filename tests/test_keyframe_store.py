"""The outage store's bounds, order and counts (`companion.cloud.keyframe_store`), on real JPEG keyframes.
Select: -k keyframe_store."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from behaviors.telemetry import Telemetry
from cloudtrack.api_client import BackendClient, EncodedKeyframe
from companion.cloud.keyframe_store import KeyframeStore, StoreCounts, StoredKeyframe
from tests.backend_fixtures import frame


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _keyframe(frame_id: int, capture_time: float, size: int = 1000) -> StoredKeyframe:
    pose = Telemetry(capture_time, 47.0, 8.0, 30.0)
    return StoredKeyframe(frame_id, capture_time, EncodedKeyframe(b"x" * size, 1.0, (640, 360)), pose)


def _taken(store: KeyframeStore) -> list[int]:
    out = []
    while (kept := store.take_newest()) is not None:
        out.append(kept.frame_id)
    return out


def test_keyframe_store_sends_the_newest_first_whatever_order_they_came_in() -> None:
    store = KeyframeStore(10_000, 900.0, Clock())
    for frame_id, t in ((1, 91.0), (3, 93.0), (2, 92.0)):  # threads may put them out of order
        store.put(_keyframe(frame_id, t))
    assert store.counts() == StoreCounts(stored=3, waiting=3, bytes=3000)
    assert _taken(store) == [3, 2, 1]
    assert store.counts() == StoreCounts(stored=3)  # taken: out on a request, neither waiting nor sent


def test_keyframe_store_drops_the_oldest_past_the_byte_bound_and_counts_them() -> None:
    store = KeyframeStore(3500, 900.0, Clock())
    for frame_id in range(1, 6):
        store.put(_keyframe(frame_id, 90.0 + frame_id))
    assert store.counts() == StoreCounts(stored=5, waiting=3, dropped=2, bytes=3000)
    assert _taken(store) == [5, 4, 3]
    store.put(_keyframe(9, 99.0, size=4000))  # larger than the whole store: kept by nothing
    assert store.counts() == StoreCounts(stored=6, waiting=0, dropped=3, bytes=0)


def test_keyframe_store_drops_keyframes_older_than_the_age_bound_from_capture() -> None:
    clock = Clock()
    store = KeyframeStore(10**6, 60.0, clock)
    store.put(_keyframe(1, 30.0))  # captured 70 s ago: already too old
    store.put(_keyframe(2, 50.0))
    store.put(_keyframe(3, 80.0))
    assert store.counts() == StoreCounts(stored=3, waiting=2, dropped=1, bytes=2000)
    clock.now = 111.0  # frame 2 is 61 s old now
    assert len(store) == 1 and store.counts().dropped == 2
    assert _taken(store) == [3]


def test_keyframe_store_a_keyframe_put_back_waits_again_in_its_place_and_counts_once() -> None:
    store = KeyframeStore(10_000, 900.0, Clock())
    for frame_id in (1, 2, 3):
        store.put(_keyframe(frame_id, 90.0 + frame_id))
    newest = store.take_newest()
    assert newest is not None and newest.frame_id == 3
    store.put(_keyframe(4, 95.0))
    store.put_back(newest)  # its request failed again: the back-end went away once more
    taken = store.take_newest()
    assert taken is not None and taken.frame_id == 4
    store.sent()
    second = store.take_newest()
    assert second is not None and second.frame_id == 3
    store.refused()  # a 4xx: given up, counted with the dropped
    assert store.counts() == StoreCounts(stored=4, waiting=2, sent=1, dropped=1, bytes=2000)


def test_keyframe_store_bounds_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_bytes"):
        KeyframeStore(0, 900.0)
    with pytest.raises(ValueError, match="max_age_s"):
        KeyframeStore(1000, 0.0)


def test_keyframe_store_holds_the_keyframe_as_the_client_sends_it(sequences_dir: Path) -> None:
    """The bytes bound counts the JPEG the client would send: downscaled to max_keyframe_width, quality as
    configured, never over max_keyframe_bytes."""
    image = frame(sequences_dir, size=(1280, 720))
    client = BackendClient("http://127.0.0.1:9", "t", max_width=640, max_keyframe_bytes=90_000)
    encoded = client.encode(image)
    assert encoded.size == (1280, 720) and encoded.scale == pytest.approx(0.5)
    assert 0 < len(encoded.jpeg) <= 90_000
    store = KeyframeStore(64 * 2**20, 900.0, Clock())
    store.put(StoredKeyframe(1, 99.0, encoded, Telemetry(99.0)))
    assert store.counts().bytes == len(encoded.jpeg)
    assert np.frombuffer(encoded.jpeg[:2], np.uint8).tolist() == [0xFF, 0xD8]  # a JPEG
