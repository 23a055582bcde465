"""Fixtures for the shared test data (../shared beside the repo, or $CLOUDTRACK_SHARED).

Missing data fails the run loudly: a skipped test proves nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

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
