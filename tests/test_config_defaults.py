"""Each default in one place: config/*.toml mirror the schemas' defaults key by key (select: -k defaults).

The schemas (`companion/config.py`, `backend/config.py`) hold every default; the committed files must list
every key of every section with the schema's value, and nothing else, so reading a file tells the truth.
The companion's control gains are the pure core's (`behaviors.control_law.ControlGains`), read by the schema.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel

from backend.config import BackendConfig
from behaviors.control_law import ControlGains
from cloudtrack.config_files import read_toml
from companion.config import CompanionConfig, ControlConfig

REPO = Path(__file__).resolve().parents[1]


def _leaves(data: dict[str, Any]) -> dict[str, Any]:
    """section.key -> value; a table-valued key (e.g. tracker.score_threshold) is one leaf."""
    return {f"{section}.{key}": value for section, values in data.items() for key, value in values.items()}


@pytest.mark.parametrize(
    ("schema", "name"), [(CompanionConfig, "companion.toml"), (BackendConfig, "backend.toml")]
)
def test_config_file_lists_every_schema_default_key_by_key(schema: type[BaseModel], name: str) -> None:
    on_disk = read_toml(REPO / "config" / name)
    written = _leaves(on_disk)
    defaults = _leaves(schema().model_dump(mode="json"))
    assert sorted(set(defaults) - set(written)) == [], f"config/{name} lacks these schema keys"
    assert sorted(set(written) - set(defaults)) == [], f"config/{name} has keys the schema does not know"
    # Compared after validation, so 2 and 2.0 or a list and a tuple are the same value.
    parsed = _leaves(schema.model_validate(on_disk).model_dump(mode="json"))
    differ = {key: (parsed[key], defaults[key]) for key in defaults if parsed[key] != defaults[key]}
    assert differ == {}, f"config/{name} (file, schema) disagree"


def test_control_defaults_are_the_control_laws_own() -> None:
    gains, schema = ControlGains(), ControlConfig()
    for key in (
        "yaw_kp",
        "yaw_ki",
        "forward_kp",
        "forward_ki",
        "lateral_kp",
        "distance_dead_band_m",
        "filter_time_constant_s",
        "max_accel_m_s2",
    ):
        assert getattr(schema, key) == getattr(gains, key), key
    assert math.isclose(math.radians(schema.yaw_dead_band_deg), gains.yaw_dead_band)
    assert math.isclose(math.radians(schema.max_yaw_accel_deg_s2), gains.max_yaw_accel)
