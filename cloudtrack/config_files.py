"""Loading a typed configuration from TOML defaults, a user file, environment variables and flags.

Precedence, lowest first: the schema's defaults (mirrored in `config/*.toml`), the configuration
file(s), environment variables `<PREFIX><SECTION>__<KEY>` (e.g. `CLOUDTRACK_MAVLINK__CONNECTION`),
then `--set section.key=value` flags. The file is the one given with `--config`; without `--config`,
`/etc/cloudtrack/NAME` and then `$XDG_CONFIG_HOME/cloudtrack/NAME` (default `~/.config/cloudtrack/NAME`)
are read when they exist, the user's file over the system's (`config_search_path`). Any unknown key, wrong type or out-of-range value raises
`ConfigError` naming the source, the key and what is allowed.
"""

from __future__ import annotations

import json
import os
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

T = TypeVar("T", bound=BaseModel)

# Keys whose values are secrets: never printed by `config show`, never echoed in an error.
SECRET_SUFFIXES = ("token", "tokens", "_key", "secret", "password")
HIDDEN = "<hidden>"


def is_secret_key(dotted: str) -> bool:
    """Whether any part of a dotted key names a secret (e.g. auth.tokens.drone-1, mavlink.signing_key)."""
    return any(part.lower().endswith(SECRET_SUFFIXES) for part in dotted.split("."))


# In a URL: the password of `scheme://user:password@host` (a lone `scheme://token@host` is all secret), and
# query values whose names say they are secrets (`?token=`, `&api_key=`, ...).
_URL_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]*://)(?P<info>[^/@\s]+)@")
_URL_SECRET_QUERY = re.compile(
    r"(?P<name>[?&][^=&#\s]*(?:token|key|secret|password|passwd|pwd|auth|signature)[^=&#\s]*=)[^&#\s\"']*",
    re.IGNORECASE,
)


def _hidden_userinfo(match: re.Match[str]) -> str:
    user, colon, _ = match["info"].partition(":")
    return f"{match['scheme']}{user}:{HIDDEN}@" if colon else f"{match['scheme']}{HIDDEN}@"


def hide_url_secrets(text: str) -> str:
    """`text` with the secrets of any URL in it hidden: `https://pilot:<hidden>@host/?token=<hidden>`.
    For `config show`, error messages and every log line (cloudtrack.logging_setup)."""
    if "://" not in text and "=" not in text:
        return text
    return _URL_SECRET_QUERY.sub(lambda m: m["name"] + HIDDEN, _URL_USERINFO.sub(_hidden_userinfo, text))


def _holds_secret(value: Any) -> bool:
    """Whether a whole section given as a value (a model-level error's input) has a secret inside."""
    if isinstance(value, Mapping):
        return any(is_secret_key(str(k)) or _holds_secret(v) for k, v in value.items())
    return isinstance(value, (list, tuple)) and any(_holds_secret(v) for v in value)


SYSTEM_CONFIG_DIR = Path("/etc/cloudtrack")


def config_search_path(name: str, environ: Mapping[str, str] | None = None) -> list[Path]:
    """Where a configuration file NAME is looked for without `--config`, lowest precedence first:
    the system's (`/etc/cloudtrack/NAME`), then the user's (`$XDG_CONFIG_HOME/cloudtrack/NAME`)."""
    env = os.environ if environ is None else environ
    user_base = Path(env["XDG_CONFIG_HOME"]) if env.get("XDG_CONFIG_HOME") else Path.home() / ".config"
    return [SYSTEM_CONFIG_DIR / name, user_base / "cloudtrack" / name]


def config_search_help(name: str) -> str:
    """--config's help: the files read without it, as `config_search_path` looks them up."""
    system, _ = config_search_path(name, {})
    return f"TOML file (default: {system}, then $XDG_CONFIG_HOME/cloudtrack/{name}, where they exist)"


def default_config_files(name: str, environ: Mapping[str, str] | None = None) -> list[Path]:
    """The files of `config_search_path` that exist."""
    return [p for p in config_search_path(name, environ) if p.is_file()]


class ConfigSection(BaseModel):
    """Base of every configuration section: unknown keys are errors, values are re-validated on change."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=True)


class ConfigError(Exception):
    """A configuration that cannot be used; the message names the source, the key and what is allowed."""


def _set_nested(target: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = target
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"cannot set {dotted!r}: {part!r} is not a section")
        node = child
    node[parts[-1]] = value


def _deep_merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _parse_scalar(text: str) -> Any:
    """A flag or environment value: TOML/JSON literal when it parses as one, else the raw string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        pass
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _parse_value(dotted: str, text: str) -> Any:
    """A flag or environment value for this key; a secret stays the exact text unless it is a string or table
    literal (an all-digit token is a token, not the number it looks like)."""
    value = _parse_scalar(text)
    if is_secret_key(dotted) and not isinstance(value, (str, dict)):
        return text
    return value


def read_toml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such configuration file") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc


def env_overrides(prefix: str, environ: Mapping[str, str]) -> dict[str, Any]:
    """Values from variables named PREFIX + SECTION__KEY, e.g. CLOUDTRACK_MAVLINK__CONNECTION."""
    result: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(prefix) or "__" not in name:
            continue
        dotted = name[len(prefix) :].lower().replace("__", ".")
        _set_nested(result, dotted, _parse_value(dotted, raw))
    return result


def flag_overrides(assignments: Iterable[str]) -> dict[str, Any]:
    """Values from `--set section.key=value` flags."""
    result: dict[str, Any] = {}
    for item in assignments:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected section.key=value")
        key, raw = item.split("=", 1)
        _set_nested(result, key.strip(), _parse_value(key.strip(), raw.strip()))
    return result


def _describe(error: Mapping[str, Any], source_of: Mapping[str, str], allowed: list[str]) -> str:
    parts = [str(p) for p in error["loc"]]
    key = ".".join(parts)
    # The layer that set this key, or the nearest enclosing section that was set.
    source = next(
        (
            source_of[".".join(parts[:n])]
            for n in range(len(parts), 0, -1)
            if ".".join(parts[:n]) in source_of
        ),
        "defaults",
    )
    if error["type"] == "extra_forbidden":
        hint = f" (allowed here: {', '.join(sorted(allowed))})" if allowed else ""
        return f"{source}: unknown key {key!r}{hint}"
    if is_secret_key(key) or _holds_secret(error.get("input")):
        return f"{source}: key {key!r}: {error['msg']} (value hidden: it holds a secret)"
    return f"{source}: key {key!r}: {error['msg']} (got {error.get('input')!r})"


def _sources(layers: list[tuple[str, dict[str, Any]]]) -> dict[str, str]:
    """Which layer last set each dotted key, for error messages."""
    source_of: dict[str, str] = {}

    def walk(node: Mapping[str, Any], prefix: str, source: str) -> None:
        for key, value in node.items():
            dotted = f"{prefix}{key}"
            source_of[dotted] = source
            if isinstance(value, Mapping):
                walk(value, dotted + ".", source)

    for source, data in layers:
        walk(data, "", source)
    return source_of


def _allowed_keys(schema: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    model: Any = schema
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        if field is None or not (
            isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)
        ):
            return []
        model = field.annotation
    return list(model.model_fields)


def load_config(
    schema: type[T],
    path: Path | None = None,
    *,
    env_prefix: str = "CLOUDTRACK_",
    environ: Mapping[str, str] | None = None,
    assignments: Iterable[str] = (),
    default_files: Sequence[Path] = (),
) -> T:
    """Build the effective configuration; raise ConfigError on anything the schema does not allow.

    `default_files` (from `default_config_files`) are read, in order, only when no `path` is given.
    """
    layers: list[tuple[str, dict[str, Any]]] = []
    for file in [path] if path is not None else default_files:
        layers.append((str(file), read_toml(file)))
    layers.append(("environment", env_overrides(env_prefix, os.environ if environ is None else environ)))
    layers.append(("--set", flag_overrides(assignments)))
    merged: dict[str, Any] = {}
    for _, data in layers:
        merged = _deep_merge(merged, data)
    try:
        return schema.model_validate(merged)
    except ValidationError as exc:
        source_of = _sources(layers)
        lines = [_describe(err, source_of, _allowed_keys(schema, tuple(err["loc"]))) for err in exc.errors()]
        raise ConfigError("invalid configuration:\n  " + "\n  ".join(lines)) from None


def dump_toml(config: BaseModel) -> str:
    """The effective configuration as TOML (sections of scalars, lists and small tables); secrets hidden."""

    def literal(value: Any) -> str:
        if isinstance(value, bool):
            return "true" if value else "false"
        if isinstance(value, (int, float)):
            return repr(value)
        if isinstance(value, str):
            return json.dumps(hide_url_secrets(value))
        if isinstance(value, (list, tuple)):
            return "[" + ", ".join(literal(v) for v in value) + "]"
        if isinstance(value, Mapping):
            return "{ " + ", ".join(f"{k} = {literal(v)}" for k, v in value.items()) + " }"
        if value is None:
            return '""'
        return json.dumps(str(value))

    def _hidden(key: str, value: Any) -> Any:
        if not is_secret_key(key) or not value:
            return value
        if isinstance(value, Mapping):  # e.g. vehicle id -> token: the ids are not secret
            return {k: HIDDEN for k in value}
        return HIDDEN

    data = config.model_dump(mode="json")
    out: list[str] = []
    for section, values in data.items():
        if isinstance(values, Mapping):
            out.append(f"[{section}]")
            out.extend(f"{k} = {literal(_hidden(k, v))}" for k, v in values.items())
            out.append("")
        else:
            out.insert(0, f"{section} = {literal(values)}")
    return "\n".join(out)
