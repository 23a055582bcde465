"""Where the real autopilots built for the simulator are found: one lookup for every autopilot."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_sitl_path(env_var: str, name: str) -> Path:
    """$<env_var>, else $CLOUDTRACK_SHARED/sitl/<name>, else ../shared/sitl/<name> beside the repository."""
    if os.environ.get(env_var):
        return Path(os.environ[env_var])
    shared = os.environ.get("CLOUDTRACK_SHARED")
    return (Path(shared) if shared else REPO_ROOT.parent / "shared") / "sitl" / name
