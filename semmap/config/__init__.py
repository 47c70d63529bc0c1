"""Run configuration: the packaged defaults, a user YAML on top, then `--set a.b=value` overrides.

Unknown sections or keys are errors (a typo must not silently fall back to a default). The `associator` and
`backend` sections are checked against their algorithms' parameter dataclasses instead (`validate_sections`).
"""

from __future__ import annotations

import dataclasses
import math
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml

P = TypeVar("P")


class ConfigError(ValueError):
    """A configuration file or override that does not fit the known settings."""


def params_from_section(cls: type[P], section: dict | None, name: str) -> P:
    """A parameter dataclass from its YAML section; unknown keys are errors (a typo must not fall back to a
    default). The dataclass checks the values."""
    section = dict(section or {})
    known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(section) - known)
    if unknown:
        raise ValueError(f"unknown {name} setting(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    return cls(**section)


def check_field_types(params: Any, name: str) -> None:
    """In a parameter dataclass's `__post_init__`: floats finite (ints become floats), ints and bools what they
    say (YAML `yes` or `1.5` must not pass as either); ranges are the dataclass's own business."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if f.type == "float":
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{name}.{f.name} must be a finite number, got {value!r}")
            setattr(params, f.name, float(value))
        elif f.type == "int" and (isinstance(value, bool) or not isinstance(value, int)):
            raise ValueError(f"{name}.{f.name} must be an integer, got {value!r}")
        elif f.type == "bool" and not isinstance(value, bool):
            raise ValueError(f"{name}.{f.name} must be true or false, got {value!r}")


def default_config() -> dict[str, Any]:
    text = resources.files("semmap.config").joinpath("default.yaml").read_text()
    return yaml.safe_load(text)


def _merge(base: dict, extra: dict, path: str, open_sections: set[str]) -> None:
    for key, value in extra.items():
        where = f"{path}{key}"
        if key not in base and path.rstrip(".") not in open_sections:
            raise ConfigError(f"unknown setting '{where}' (known: {', '.join(sorted(base))})")
        if isinstance(base.get(key), dict) and isinstance(value, dict):
            _merge(base[key], value, where + ".", open_sections)
        else:
            base[key] = value


def _parse_value(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> dict[str, Any]:
    """Defaults <- YAML file <- `section.key=value` overrides (values parsed as YAML scalars/lists)."""
    config = default_config()
    open_sections = set(DATACLASS_SECTIONS)
    if path:
        try:
            user = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from None
        if not isinstance(user, dict):
            raise ConfigError(f"config {path} must be a mapping of sections")
        _merge(config, user, "", open_sections)
    for item in overrides or []:
        key, sep, value = item.partition("=")
        if not sep or "." not in key:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        nested: Any = _parse_value(value)
        for part in reversed(key.split(".")):
            nested = {part: nested}
        _merge(config, nested, "", open_sections)
    return config


DATACLASS_SECTIONS = ("associator", "backend")


def validate_sections(config: dict[str, Any]) -> None:
    """Check the sections owned by parameter dataclasses now, before any process starts."""
    from services.associator.params import MapperParams
    from services.associator.service import PRIOR_KEYS, SERVICE_DEFAULTS
    from services.backend.corrections import CorrectionsParams
    from services.backend.loop_closure import LoopClosureParams
    from services.backend.pose_graph import BackendParams

    confidence = config["detector"]["confidence"]
    if isinstance(confidence, bool) or not isinstance(confidence, int | float) or not 0.0 < confidence <= 1.0:
        raise ConfigError(f"detector.confidence must be in (0, 1], got {confidence!r}")
    gate_u = config["associator"].get("gate_u", 1.0)
    if isinstance(gate_u, bool) or not isinstance(gate_u, int | float) or not (math.isfinite(gate_u) and gate_u > 0):
        raise ConfigError(f"associator.gate_u must be a positive number, got {gate_u!r}")
    try:
        MapperParams.from_dict({k: v for k, v in config["associator"].items()
                                if k not in SERVICE_DEFAULTS and k not in PRIOR_KEYS})
        BackendParams.from_config(config["backend"])
        LoopClosureParams.from_config(config["loop_closure"])
        CorrectionsParams.from_config(config["corrections"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(str(exc)) from None

