"""Fixtures for the shared test data (../shared beside the repo, or $CLOUDTRACK_SHARED).

Missing data fails the run loudly: a skipped test proves nothing.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _import_anyio_now() -> None:
    """anyio imports its API on first use, and as a pytest plugin its modules go through pytest's assertion
    rewriter. A first use from a server thread then compiles there while pytest compiles in the main
    thread, which CPython 3.11.7's AST validator does not survive ("SystemError: AST constructor recursion
    depth mismatch", a 500 on a static file). Resolve the lazy names once, here, in the main thread."""
    import anyio

    for name in dir(anyio):
        getattr(anyio, name)


_import_anyio_now()


@pytest.fixture(autouse=True)
def _older_objects_left_out_of_collection(request: pytest.FixtureRequest) -> Iterator[None]:
    """A slow test runs real-time parts in this process (the autopilot bridge, the camera, the pilot); a full
    garbage collection over a long session's heap stops them all (0.61 s measured at 760k objects, past
    PX4's COM_OF_LOSS_T). While it runs, the objects older than the test are not collected."""
    if request.node.get_closest_marker("slow") is None:
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _shared_dir() -> Path:
    return Path(os.environ.get("CLOUDTRACK_SHARED") or REPO_ROOT.parent / "shared").resolve()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    path = _shared_dir()
    if not (path / "models").is_dir() or not (path / "data" / "sequences").is_dir():
        pytest.fail(
            f"shared test data not found at {path} (expected models/ and data/sequences/); "
            "put ../shared beside the repo or set CLOUDTRACK_SHARED",
            pytrace=False,
        )
    return path


@pytest.fixture(scope="session")
def models_dir(shared_dir: Path) -> Path:
    return shared_dir / "models"


@pytest.fixture(scope="session")
def sequences_dir(shared_dir: Path) -> Path:
    return shared_dir / "data" / "sequences"


@pytest.fixture(scope="session")
def sequence_dirs(sequences_dir: Path) -> list[Path]:
    dirs = sorted(p for p in sequences_dir.iterdir() if (p / "groundtruth.txt").is_file())
    assert len(dirs) >= 5, f"expected five sequences in {sequences_dir}, found {len(dirs)}"
    return dirs


class SharedPx4:
    """One real PX4 (SIH) airborne at 10 m over the scenarios' home, shared by the tests marked `shares_px4`
    (its conformance half and its scenario flights): CI pays for one boot and take-off, not one per module.
    Started by the first test that asks for it, stopped as soon as the next test is not marked `shares_px4`
    (`pytest_runtest_teardown` below), so it never flies under another module's timings."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self.vehicle: Any = None
        self.boots = 0

    def get(self) -> Any:
        if self.vehicle is None:
            from sitl.px4_sitl import find_package, start_px4
            from sitl.scenario_runner import ALTITUDE_M, HOME_ALT_M, _home

            lat, lon = _home((0.0, 0.0))
            for boot in (1, 2):
                # A pilot whose vehicle refuses to take off reboots it once: a fresh SIH once armed and then
                # refused TAKEOFF ("battery warning", its position estimate 520 m off home right after boot),
                # in 1 of about 40 CI runs, cause not found. The tests are of what follows the take-off.
                self.boots += 1  # a fresh work directory each boot (parameters, dataman), as a scenario's
                vehicle = start_px4(
                    find_package(), self.work / f"boot-{self.boots}", (lat, lon, HOME_ALT_M), None
                )
                try:
                    took = vehicle.fly_up(ALTITUDE_M)
                except Exception as exc:
                    vehicle.gcs.stop()
                    vehicle.close()
                    if boot == 2:
                        raise
                    print(f"px4 boot {boot} did not take off, booting a fresh one: {exc}")
                    continue
                print(f"px4 airborne after {took:.1f} s ({vehicle.describe()})")
                self.vehicle = vehicle
                break
        return self.vehicle

    def close(self) -> None:
        vehicle, self.vehicle = self.vehicle, None
        if vehicle is not None:
            vehicle.gcs.stop()
            vehicle.close()


_SHARED_PX4_KEY = pytest.StashKey[SharedPx4]()


@pytest.fixture(scope="session")
def shared_px4(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SharedPx4]:
    holder = SharedPx4(tmp_path_factory.mktemp("px4-sitl"))
    request.config.stash[_SHARED_PX4_KEY] = holder
    try:
        yield holder
    finally:
        holder.close()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    holder = item.config.stash.get(_SHARED_PX4_KEY, None)
    if holder is not None and (nextitem is None or nextitem.get_closest_marker("shares_px4") is None):
        holder.close()
