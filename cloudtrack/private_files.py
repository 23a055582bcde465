"""Files only their owner reads (0600 in folders 0700), whatever the umask of whoever starts the process.

The systemd units set `UMask=0027`, but a process started by hand under the common umask 022 wrote the
back-end's session store (decisions, rejections, positions) and the companion's flight record (events,
keyframes of the people it looked at) readable by every user of the machine. Modes are given when a file
or folder is created (a umask only ever removes bits, so 0600 and 0700 survive any umask); a file that
already exists is narrowed to 0600. Folders that already exist are left alone: a store's parent may be a
shared one such as /tmp.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO, Any

FILE_MODE = 0o600
DIR_MODE = 0o700


def private_dir(path: Path) -> Path:
    """Create `path` and its missing parents as 0700; an existing folder keeps its mode."""
    missing = [p for p in (path, *path.parents) if not p.exists()]
    for folder in reversed(missing):
        folder.mkdir(mode=DIR_MODE, exist_ok=True)
    return path


def private_file(path: Path) -> Path:
    """Make sure `path` exists as a file only its owner reads (created 0600, or narrowed to it)."""
    fd = os.open(path, os.O_CREAT | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0), FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE)
    finally:
        os.close(fd)
    return path


def open_private(path: Path, mode: str, encoding: str | None = None) -> IO[Any]:
    """`open(path, mode)` of a file created 0600 (narrowed to 0600 if it existed): "a", "ab", "w", "wb"."""
    flags = os.O_CREAT | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
    flags |= os.O_APPEND if mode.startswith("a") else os.O_TRUNC
    fd = os.open(path, flags, FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE)
        return os.fdopen(fd, mode, encoding=encoding)
    except BaseException:
        os.close(fd)
        raise


def write_private(path: Path, data: bytes) -> None:
    """`path.write_bytes(data)` for a file only its owner reads."""
    with open_private(path, "wb") as out:
        out.write(data)
