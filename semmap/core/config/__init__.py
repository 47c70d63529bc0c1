"""The run configuration: one typed tree (a section per service, plus `run`), the single source of every default.

`load_config(path, overrides)` layers a user YAML file and `--set section.key=value` overrides on the defaults and
validates the whole tree at once: types (strict: no 'maybe' for a bool, no 1.5 for a count, no text for a
number), ranges, list syntax (`a,b` or a YAML list), files that must exist, no unknown keys. Every error names the
key and the form it expects. `semmap run` calls it before any process starts; every service calls it again at
its start (one started by hand, or by compose, is checked the same way). `semmap config show` prints the
effective tree as commented YAML (`render_yaml`).

This package is the core layer: it imports nothing from algorithms, runtime, services or CLI. The algorithms
take their own section (`MapperParams`, `TrackerParams`, `BackendParams`, ...) as their parameters.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .associator import AssociatorConfig, MapperParams, PriorParams
from .base import ConfigError, Section, parse_value, parse_yaml
from .sections import (
    BackendParams,
    CorrectionsParams,
    DetectorConfig,
    LoopClosureParams,
    OdometryConfig,
    RosbagConfig,
    RunConfig,
    SecurityConfig,
    TrackerParams,
    VizConfig,
)

__all__ = [
    "AssociatorConfig",
    "BackendParams",
    "Config",
    "ConfigError",
    "CorrectionsParams",
    "DetectorConfig",
    "LoopClosureParams",
    "MapperParams",
    "OdometryConfig",
    "PriorParams",
    "RosbagConfig",
    "RunConfig",
    "Section",
    "SecurityConfig",
    "TrackerParams",
    "VizConfig",
    "load_config",
    "render_yaml",
    "run_overrides",
]


class Config(BaseModel):
    """The whole configuration: `config.tracker.sigma_iou` is the YAML `tracker: sigma_iou:`."""

    model_config = ConfigDict(strict=True, extra="forbid")

    run: RunConfig = Field(default_factory=RunConfig)
    security: SecurityConfig = Field(default_factory=SecurityConfig)
    rosbag: RosbagConfig = Field(default_factory=RosbagConfig)
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    tracker: TrackerParams = Field(default_factory=TrackerParams)
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    associator: AssociatorConfig = Field(default_factory=AssociatorConfig)  # type: ignore[valid-type]
    backend: BackendParams = Field(default_factory=BackendParams)
    loop_closure: LoopClosureParams = Field(default_factory=LoopClosureParams)
    corrections: CorrectionsParams = Field(default_factory=CorrectionsParams)
    viz: VizConfig = Field(default_factory=VizConfig)


def _set(tree: dict[str, Any], dotted: str, value: Any) -> None:
    *parents, last = dotted.split(".")
    node = tree
    for part in parents:
        child = node.get(part)
        if not isinstance(child, dict):
            child = node[part] = {}
        node = child
    node[last] = value


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> None:
    for key, value in extra.items():
        if isinstance(base.get(key), dict) and isinstance(value, dict):
            _merge(base[key], value)
        else:
            base[key] = value


def run_overrides(mode: str | None = None, robot: str | None = None) -> list[str]:
    """The `--mode` and `--robot` flags as the settings they are (`run.mode`, `run.robot`): overrides validated
    with the rest of the tree, never a change to a validated configuration. (The robot is quoted: a name of
    digits stays text.)"""
    return [f"run.mode={mode}"] * bool(mode) + [f"run.robot={json.dumps(robot)}"] * bool(robot)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults <- YAML file <- `section.key=value` overrides (values read as YAML: numbers, true/false, lists),
    validated as a whole. Raises ConfigError listing every bad key."""
    tree: dict[str, Any] = {}
    if path:
        try:
            user = parse_yaml(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from None
        if not isinstance(user, dict):
            raise ConfigError(f"config {path} must be a mapping of sections (section: {{key: value}})")
        _merge(tree, user)
    for item in overrides or []:
        key, sep, value = item.partition("=")
        parts = key.split(".")
        if not sep or len(parts) < 2 or not all(parts):
            raise ConfigError(f"override {item!r} must look like section.key=value")
        _set(tree, key, parse_value(value))
    try:
        return Config.model_validate(tree)
    except ValidationError as exc:
        raise ConfigError(_describe(exc)) from None


_EXPECTED = {  # pydantic's error types, as the form a value must take
    "float_type": "expected a number",
    "int_type": "expected an integer",
    "bool_type": "expected true or false",
    "string_type": "expected text (quote it in YAML if it looks like a number)",
    "finite_number": "expected a finite number",
    "model_type": "expected a mapping of key: value",
    "dict_type": "expected a mapping of key: value",
}


_BOUNDS = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _known(loc: tuple) -> list[str]:
    model: Any = Config
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(model, type) and issubclass(model, BaseModel) else None
        if field is None:
            return []
        model = field.annotation
    return list(model.model_fields) if isinstance(model, type) and issubclass(model, BaseModel) else []


def _describe(exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        loc = tuple(str(p) for p in err["loc"] if not isinstance(p, int))
        where = ".".join(loc) or "config"
        kind = err["type"]
        if kind == "extra_forbidden":
            lines.append(f"unknown setting '{where}' (known: {', '.join(_known(loc))})")
            continue
        ctx = err.get("ctx", {})
        message = _EXPECTED.get(kind) or err["msg"].removeprefix("Value error, ")
        if kind in _BOUNDS:
            message = f"expected a number {_BOUNDS[kind]} {next(iter(ctx.values()), '?')}"
        elif kind in ("literal_error", "string_too_short"):
            message = "expected " + message.removeprefix("Input should ").removeprefix("be ")
        if "input" in err and kind != "value_error" and not isinstance(err["input"], dict):
            message += f", got {err['input']!r}"
        lines.append(f"{where}: {message}")
    return "; ".join(lines) if len(lines) == 1 else "invalid settings:\n  " + "\n  ".join(lines)


def _scalar(value: Any) -> str:
    if isinstance(value, tuple):
        value = list(value)
    text = yaml.safe_dump(value, default_flow_style=True, width=10_000, allow_unicode=True).strip()
    return text.removesuffix("\n...").removesuffix("...").strip()


def render_yaml(config: Config | None = None) -> str:
    """The configuration as commented YAML: loadable with `--config`, each key with its description."""
    config = config or Config()
    out = [
        "# semmap configuration (`semmap config show`): every key with its value; descriptions as comments.",
        "# Override with `--config FILE` (same layout, any subset) or `--set section.key=value`.",
    ]
    for name in Config.model_fields:
        section = getattr(config, name)
        out.append("")
        doc = " ".join((type(section).__doc__ or "").split())
        out.append(f"{name}:" + (f"  # {doc}" if doc else ""))
        for key, sub in type(section).model_fields.items():
            line = f"  {key}: {_scalar(getattr(section, key))}"
            if not sub.description:
                out.append(line)
                continue
            width = max(len(line), 40)
            comments = textwrap.wrap(sub.description, 116 - width) or [""]
            out.append(f"{line:<{width}}  # {comments[0]}")
            out.extend(f"{'':<{width}}  # {more}" for more in comments[1:])
    return "\n".join(out) + "\n"
