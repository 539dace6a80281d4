"""Strict conversion between nested frozen config dataclasses and plain dicts / YAML.

Every concern has its own frozen dataclass with inline defaults (``PriorConfig``, ``OdometryConfig``,
…) under one root (:class:`ptm_ros.config.PtmConfig`). Loading is strict: an unknown key, a wrong type
or a value its dataclass rejects raises :class:`ConfigError` naming the dotted path of the field, so a
misspelt parameter never passes silently.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from ptm_ros.errors import ConfigError

T = TypeVar("T")


def _exponent_hint(value: object) -> str:
    """A hint for a number that YAML 1.1 (PyYAML, which reads ROS 2 parameter files) takes for text: an
    exponent without a decimal point or without a sign (``5e-05``, ``1.0e3``); empty for anything else."""
    if not isinstance(value, str) or "e" not in value.lower():
        return ""
    try:
        number = float(value)
    except ValueError:
        return ""
    if not math.isfinite(number):
        return ""
    mantissa, _, exponent = value.lower().partition("e")
    mantissa = mantissa if "." in mantissa else f"{mantissa}.0"
    exponent = exponent if exponent[:1] in "+-" else f"+{exponent}"
    fixed = f"{mantissa}e{exponent}"
    if fixed == value.lower():  # already a YAML number: it was quoted
        return ""
    return f" (YAML reads an exponent without a decimal point and a sign as text: write {fixed})"


def _convert(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not isinstance(value, Mapping):
            msg = f"{where}: expected a mapping, got {type(value).__name__}"
            raise ConfigError(msg)
        return from_dict(hint, value, where)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError("; ".join(errors))
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            msg = f"{where}: expected a list, got {type(value).__name__}"
            raise ConfigError(msg)
        args = typing.get_args(hint)
        inner = args[0] if args else Any
        return tuple(_convert(v, inner, f"{where}[{i}]") for i, v in enumerate(value))
    if hint is bool:
        if not isinstance(value, bool):
            msg = f"{where}: expected true/false, got {value!r}"
            raise ConfigError(msg)
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            msg = f"{where}: expected an integer, got {value!r}"
            raise ConfigError(msg)
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            msg = f"{where}: expected a number, got {value!r}{_exponent_hint(value)}"
            raise ConfigError(msg)
        try:
            number = float(value)
        except OverflowError:  # an integer beyond the floats (YAML reads any number of digits)
            msg = f"{where}: an integer of {len(str(abs(value)))} digits is beyond the range of a number"
            raise ConfigError(msg) from None
        if math.isnan(number):
            msg = f"{where}: NaN is not a valid value"
            raise ConfigError(msg)
        return number
    if hint is str:
        if not isinstance(value, str):
            msg = f"{where}: expected a string, got {value!r}"
            raise ConfigError(msg)
        return value
    return value


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "") -> T:
    """Build the dataclass ``cls`` from ``data``; missing keys take their defaults, unknown keys fail."""
    if not dataclasses.is_dataclass(cls):
        msg = f"{cls!r} is not a dataclass"
        raise TypeError(msg)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        msg = f"{where or 'config'}: unknown key(s) {unknown}; known keys: {sorted(fields)}"
        raise ConfigError(msg)
    kwargs = {
        name: _convert(value, hints[name], f"{where}.{name}" if where else name)
        for name, value in data.items()
    }
    try:
        return cls(**kwargs)
    except ConfigError as err:
        msg = f"{where or 'config'}: {err}"
        raise ConfigError(msg) from err
    except (TypeError, ValueError) as err:
        msg = f"{where or 'config'}: {err}"
        raise ConfigError(msg) from err


def to_dict(config: Any) -> dict[str, Any]:
    """The plain-dict form of a config dataclass (tuples become lists), for saving beside results."""

    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(dataclasses.asdict(config))


def yaml_problem(err: Exception) -> str:
    """One line for a PyYAML error (its own text spans several, with a caret drawing): ``line L, column
    C: problem`` when it knows where, else its text joined on one line."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None)
    if mark is not None and problem:
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    return " ".join(str(err).split())


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping (empty file → {}); malformed YAML or a non-mapping raises ConfigError."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as err:
        msg = f"cannot read parameter file {path}: {err}"
        raise ConfigError(msg) from err
    except yaml.YAMLError as err:
        msg = f"malformed YAML in {path}, {yaml_problem(err)}"
        raise ConfigError(msg) from err
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        msg = f"{path}: the top level must be a mapping, got {type(doc).__name__}"
        raise ConfigError(msg)
    return doc
