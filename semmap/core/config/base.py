"""What every configuration section shares: strict typing, no unknown keys, and the value types settings use.

Strict on purpose: YAML and `--set` give real types (numbers, true/false, lists), so a string where a number goes
('banana'), a word where a bool goes ('maybe') or 1.5 where a count goes is a mistake to report, not to coerce.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field


class ConfigError(ValueError):
    """A configuration file or override that does not fit the known settings."""


class Section(BaseModel):
    """One section of the configuration (one service, or `run`): its fields are the YAML keys."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, validate_default=True)


# numbers (ints are accepted where a float goes, never bools or strings)
Float = Annotated[float, Field()]
NonNegative = Annotated[float, Field(ge=0)]
Positive = Annotated[float, Field(gt=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]  # a share or a rate in [0, 1]
Probability = Annotated[float, Field(gt=0, le=1)]  # in (0, 1]
Count = Annotated[int, Field(ge=0)]
AtLeastOne = Annotated[int, Field(ge=1)]


def _names(value: Any) -> tuple[str, ...]:
    """`a,b` (one string, as `--set` gives it) or a YAML list of names; empty or null: none."""
    if value is None:
        return ()
    if isinstance(value, str):
        items: Any = value.split(",")
    elif isinstance(value, list | tuple):
        items = value
    else:
        raise ValueError(f"expected a list of names ([a, b] or a,b), got {value!r}")
    if not all(isinstance(x, str) for x in items):
        raise ValueError(f"expected a list of names ([a, b] or a,b), got {value!r}")
    return tuple(x.strip() for x in items if x.strip())


Names = Annotated[tuple[str, ...], BeforeValidator(_names)]


def _six_numbers(value: Any) -> tuple[Any, ...]:
    """`1,2,3,4,5,6` or a YAML list of six; the items are then checked as numbers."""
    items = tuple(parse_value(x) for x in value.split(",")) if isinstance(value, str) else value
    if not isinstance(items, list | tuple) or len(items) != 6:
        raise ValueError(f"expected a list of 6 numbers ([0, 0, 0, 0, 0, 0] or 0,0,0,0,0,0), got {value!r}")
    return tuple(items)


Numbers6 = Annotated[tuple[float, float, float, float, float, float], BeforeValidator(_six_numbers)]


def _existing_file(value: str) -> str:
    if value and not Path(value).expanduser().is_file():
        raise ValueError(f'expected an existing file (or "" for none), {value!r} does not exist')
    return value


OptionalFile = Annotated[str, AfterValidator(_existing_file)]


class _Loader(yaml.SafeLoader):
    """YAML as PyYAML reads it, plus floats without a dot (`1e-4`), which YAML 1.1 would leave a string."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def parse_yaml(text: str) -> Any:
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass


def parse_value(text: str) -> Any:
    """An override's value as YAML reads it (`0.3` a number, `[a, b]` a list); unparsable text stays text."""
    try:
        return parse_yaml(text)
    except yaml.YAMLError:
        return text
