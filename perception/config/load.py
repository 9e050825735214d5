"""Loading, overriding, validating and saving configurations: :func:`load_config` (a YAML file
or a bare mission name, plus overrides nested with ``__``), :func:`resolve_config`,
:func:`apply_overrides`, :func:`save_config` and the shipped files (:func:`shipped_configs`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from perception.config.errors import ConfigError, _format_errors, _loc, short_repr
from perception.config.mission import MissionConfig
from perception.config.yamlio import MAX_NESTING, MAX_NODES, load_yaml

#: Folder of the shipped YAML files (``configs/`` at the repository root).
CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"

M = TypeVar("M", bound=BaseModel)


def _check_override_values(overrides: dict[Any, Any]) -> None:
    """Refuse overrides nested deeper than :data:`MAX_NESTING` or holding more than
    :data:`MAX_NODES` values (a list that contains itself never ends); iterative."""
    count = 0
    stack: list[tuple[Any, int, str]] = [(overrides, 1, "")]
    while stack:
        value, level, key = stack.pop()
        count += 1
        if level > MAX_NESTING:
            raise ConfigError(
                f"override {key} is nested deeper than {MAX_NESTING} levels; expected a plain value"
            )
        if isinstance(value, (dict, list, tuple, set, frozenset)):
            if count + len(value) > MAX_NODES:
                raise ConfigError(f"overrides hold more than {MAX_NODES} values; expected a few settings")
            if isinstance(value, dict):
                stack.extend((v, level + 1, key or _loc((k,))) for k, v in value.items())
            else:
                stack.extend((v, level + 1, key) for v in value)


def _split_key(key: Any) -> list[str]:
    if not isinstance(key, str):
        raise ConfigError(f"override key {short_repr(key)} is a {type(key).__name__}; expected a string "
                          "such as 'env__frame_skip'")
    parts = key.replace(".", "__").split("__")
    if not all(parts):
        raise ConfigError(f"override key {short_repr(key)} has an empty name; expected names joined by "
                          "'__' or '.' such as 'env__frame_skip'")
    return parts


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Merge overrides into a nested mapping. Keys nest with ``__`` or ``.`` (``sensor__tof__bias_m``);
    a mapping value is merged recursively.

    Raises:
        ConfigError: a key that is not a string or has an empty name; a key that goes through a
            value that is not a section (``{"env": 3, "env__frame_skip": 2}`` would otherwise
            drop the whole ``env`` section), or through a section an earlier override set to
            null; values nested past :data:`MAX_NESTING` or holding more than :data:`MAX_NODES`.
    """
    _check_override_values(overrides)
    out = _deep_copy(data)
    nulled: set[tuple[str, ...]] = set()  # sections an override of this call set to None
    for key, value in overrides.items():
        parts = _split_key(key)
        node = out
        for i, part in enumerate(parts[:-1]):
            path = tuple(parts[: i + 1])
            nxt = node.get(part)
            if nxt is None and path not in nulled:  # an absent (or null) section starts empty
                nxt = node[part] = {}
            elif not isinstance(nxt, dict):
                raise ConfigError(
                    f"override {key}: {'.'.join(path)} is {short_repr(nxt)}, not a section; "
                    f"expected a mapping to set {parts[-1]} in"
                )
            node = nxt
        leaf = parts[-1]
        current = node.get(leaf)
        if isinstance(value, dict) and isinstance(current, dict):
            node[leaf] = apply_overrides(current, value)
        else:
            if value is None and isinstance(current, dict):
                nulled.add(tuple(parts))
            node[leaf] = value
    return out


def flatten_overrides(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> ``{"a__b__c": value}`` overrides (the inverse of :func:`apply_overrides`)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}__{k}" if prefix else k
        if isinstance(v, dict):
            out.update(flatten_overrides(v, key))
        else:
            out[key] = v
    return out


def _deep_copy(d: dict[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, dict) else v for k, v in d.items()}


def config_path(path: str | Path, kind: str = "missions") -> Path:
    """A YAML path as given, or a bare name (``"final_approach"``) looked up in ``configs/<kind>``."""
    p = Path(path)
    try:
        exists = p.exists()
    except (OSError, ValueError):  # a name too long for the file system: load_yaml says why
        exists = False
    if not p.suffix and not exists:
        return CONFIG_DIR / kind / f"{p}.yaml"
    return p


def load_config(
    path: str | Path | None = None, model: type[M] = MissionConfig, **overrides: Any  # type: ignore[assignment]
) -> M:
    """Load and validate a config file (or just the defaults when ``path`` is None).

    Args:
        path: YAML file; a bare name such as ``"final_approach"`` is looked up in ``configs/missions``.
        model: the pydantic model the file describes (default :class:`MissionConfig`).
        **overrides: values that replace the file's, nested with ``__`` (``env__frame_skip=2``).

    Raises:
        ConfigError: a missing or unreadable file (see :func:`load_yaml`), bad overrides (see
            :func:`apply_overrides`), unknown keys, or values of the wrong type or out of range;
            the message is one line naming each field, its value and what was expected.
    """
    return resolve_config(path, overrides, model)


def resolve_config(
    path: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    model: type[M] = MissionConfig,  # type: ignore[assignment]
) -> M:
    """:func:`load_config` with the overrides as a mapping (a user's dict: a key that is not a
    string, or one named ``path`` or ``model``, is an override like any other, refused or applied,
    never a Python ``TypeError``)."""
    data: dict[str, Any] = {}
    source = "defaults"
    if path is not None:
        if not isinstance(path, (str, os.PathLike)):
            raise ConfigError(
                f"config={short_repr(path)} ({type(path).__name__}); expected a YAML path or a mission name"
            )
        p = config_path(path)
        data = load_yaml(p)
        source = f"config file {p}"
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            f"overrides={short_repr(overrides)} ({type(overrides).__name__}); expected a mapping"
        )
    if overrides:
        data = apply_overrides(data, overrides)
        source += f" (with overrides {short_repr(sorted(map(str, overrides)))})"
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_errors(exc, source)) from None


def save_config(cfg: BaseModel, path: str | Path) -> Path:
    """Write the resolved config (every default filled in) as YAML next to a result."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    return p


def shipped_configs() -> list[Path]:
    """Every YAML file under ``configs/``."""
    return sorted(CONFIG_DIR.rglob("*.yaml"))
