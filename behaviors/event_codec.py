"""Events and actions (and any other value of this package) to and from JSON-able dicts, losslessly.

A dataclass becomes `{"type": ClassName, field: value, ...}`; enums become their value, tuples lists,
and non-finite floats the strings "NaN", "Infinity", "-Infinity" so the result is strict JSON. Decoding is
driven by the declared field types, so `decode_event(encode_event(e)) == e` for every event. The flight
record stores events this way and replays them through `behaviors.mission.step`.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from enum import Enum
from typing import Any

from behaviors import (
    actions,
    camera_model,
    control_law,
    detection,
    events,
    geolocation,
    geometry,
    mission,
    mission_commands,
    mission_config,
    rejection_memory,
    safety_limits,
    setpoint,
    telemetry,
    track_result,
)

_MODULES = (
    actions,
    camera_model,
    control_law,
    detection,
    events,
    geolocation,
    geometry,
    mission,
    mission_commands,
    mission_config,
    rejection_memory,
    safety_limits,
    setpoint,
    telemetry,
    track_result,
)
_NON_FINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


def _field_types() -> dict[type[Any], dict[str, Any]]:
    """Declared field types of every dataclass in the package, resolved once (decoding is driven by them)."""
    found: dict[type[Any], dict[str, Any]] = {}
    for module in _MODULES:
        for value in vars(module).values():
            if (
                isinstance(value, type)
                and dataclasses.is_dataclass(value)
                and value.__module__ == module.__name__
            ):
                found[value] = typing.get_type_hints(value)
    return found


_FIELD_TYPES = _field_types()


class CodecError(ValueError):
    """A dict that is not a valid encoding; the message names where in it the problem is."""


def encode(value: Any) -> Any:
    """Any value built from this package's dataclasses, enums, tuples and scalars as JSON-able data."""
    if isinstance(value, Enum):
        return value.value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out: dict[str, Any] = {"type": type(value).__name__}
        for f in dataclasses.fields(value):
            out[f.name] = encode(getattr(value, f.name))
        return out
    if isinstance(value, (tuple, list)):
        return [encode(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise CodecError(f"cannot encode {type(value).__name__}")


def decode(data: Any, hint: Any, path: str = "$") -> Any:
    """The value of type `hint` that `encode` turned into `data`."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return _decode_union(data, typing.get_args(hint), path)
    if hint is type(None):
        if data is not None:
            raise CodecError(f"{path}: expected null, got {data!r}")
        return None
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(data, list):
            raise CodecError(f"{path}: expected a list, got {type(data).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(decode(v, args[0], f"{path}[{i}]") for i, v in enumerate(data))
        if len(args) != len(data):
            raise CodecError(f"{path}: expected {len(args)} items, got {len(data)}")
        return tuple(decode(v, a, f"{path}[{i}]") for i, (v, a) in enumerate(zip(data, args, strict=True)))
    if isinstance(hint, type) and issubclass(hint, Enum):
        try:
            return hint(data)
        except ValueError as exc:
            raise CodecError(f"{path}: {data!r} is not a {hint.__name__}") from exc
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return _decode_dataclass(data, hint, path)
    if hint is bool:
        if not isinstance(data, bool):
            raise CodecError(f"{path}: expected true or false, got {data!r}")
        return data
    if hint is int:
        if isinstance(data, bool) or not isinstance(data, int):
            raise CodecError(f"{path}: expected an integer, got {data!r}")
        return data
    if hint is float:
        if isinstance(data, str) and data in _NON_FINITE:
            return _NON_FINITE[data]
        if isinstance(data, bool) or not isinstance(data, (int, float)):
            raise CodecError(f"{path}: expected a number, got {data!r}")
        return data
    if hint is str:
        if not isinstance(data, str):
            raise CodecError(f"{path}: expected a string, got {data!r}")
        return data
    raise CodecError(f"{path}: cannot decode into {hint!r}")


def _decode_union(data: Any, options: tuple[Any, ...], path: str) -> Any:
    if data is None:
        if type(None) in options:
            return None
        raise CodecError(f"{path}: null is not allowed here")
    if isinstance(data, dict):
        name = data.get("type")
        for option in options:
            if isinstance(option, type) and option.__name__ == name:
                return _decode_dataclass(data, option, path)
        allowed = sorted(o.__name__ for o in options if isinstance(o, type) and dataclasses.is_dataclass(o))
        raise CodecError(f"{path}: type {name!r} is not one of {allowed}")
    for option in options:
        if option is type(None):
            continue
        try:
            return decode(data, option, path)
        except CodecError:
            continue
    raise CodecError(f"{path}: {data!r} fits none of {options}")


def _decode_dataclass(data: Any, cls: type[Any], path: str) -> Any:
    if not isinstance(data, dict):
        raise CodecError(f"{path}: expected an object for {cls.__name__}, got {type(data).__name__}")
    if data.get("type") != cls.__name__:
        raise CodecError(f"{path}: expected type {cls.__name__!r}, got {data.get('type')!r}")
    hints = _FIELD_TYPES.get(cls) or typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields) - {"type"}
    if unknown:
        raise CodecError(f"{path}: unknown field(s) {sorted(unknown)} for {cls.__name__}")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = decode(data[name], hints[name], f"{path}.{name}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise CodecError(f"{path}: missing field {name!r} for {cls.__name__}")
    return cls(**kwargs)


def encode_event(event: events.Event) -> dict[str, Any]:
    encoded: dict[str, Any] = encode(event)
    return encoded


def decode_event(data: Any) -> events.Event:
    decoded: events.Event = decode(data, events.Event)
    return decoded


def encode_action(action: actions.Action) -> dict[str, Any]:
    encoded: dict[str, Any] = encode(action)
    return encoded


def decode_action(data: Any) -> actions.Action:
    decoded: actions.Action = decode(data, actions.Action)
    return decoded


def decode_as(data: Any, cls: type[Any]) -> Any:
    """Decode any registered dataclass (the mission `State`, `MissionConfig` ...) by its class."""
    return decode(data, cls)
