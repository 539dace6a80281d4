"""Configuration fields declared once: default, range or choices, and description in one :func:`setting`.

Every concern's configuration is a frozen dataclass deriving from :class:`Settings` whose fields are
declared with :func:`setting` (kiss-icp's typed config is the model; the range and the description sit
beside the type as in pydantic's ``Field``)::

    @dataclass(frozen=True)
    class LaserConfig(Settings):
        patch_radius: float = setting(3.0, gt=0, doc="scans taken within this distance form the patch")

From that one declaration come the validation of every instance (:meth:`Settings.__post_init__`: the
annotation's type, finiteness, the bounds and the choices, the error naming ``Class.field``), the
descriptions and ranges of the nodes' ROS parameters, ``config/ptm.yaml`` and the JSON schema of the
parameter files (:func:`json_schema`). Rules that tie several fields together stay in the class, in a
``check`` method that :meth:`Settings.__post_init__` calls after the fields' own checks.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import reprlib
import textwrap
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar, overload

from ptm_ros.errors import ConfigError

T = TypeVar("T")

#: How a rejected value is shown (an integer of 400 digits, a long list: their ends).
_SHORT = reprlib.Repr()
_SHORT.maxlong, _SHORT.maxstring, _SHORT.maxother, _SHORT.maxlist, _SHORT.maxtuple = 24, 80, 80, 8, 8
#: Key of a field's :class:`Spec` in its ``dataclasses.Field.metadata``.
SPEC = "ptm_ros.setting"


@dataclass(frozen=True)
class Spec:
    """What a field admits besides its annotation's type, and what it means.

    Attributes:
        doc: the description (ROS parameter descriptors, the JSON schema, ``config/ptm.yaml``).
        ge, gt, le, lt: inclusive / exclusive bounds of a number (or of every number of a sequence).
        choices: the admitted values (of a string, or of every item of a sequence).
        finite: a float must be finite (the default); False also admits ±inf.
    """

    doc: str
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[Any, ...] | None = None
    finite: bool = True

    def bounds(self) -> str:
        """The bounds in words: ``> 0``, ``in [0, 1)``, ``>= 1``, or "" when unbounded."""
        low = (self.ge, "[") if self.ge is not None else (self.gt, "(") if self.gt is not None else None
        high = (self.le, "]") if self.le is not None else (self.lt, ")") if self.lt is not None else None
        if low is not None and high is not None:
            return f"in {low[1]}{_num(low[0])}, {_num(high[0])}{high[1]}"
        if low is not None:
            return f"{'>=' if low[1] == '[' else '>'} {_num(low[0])}"
        if high is not None:
            return f"{'<=' if high[1] == ']' else '<'} {_num(high[0])}"
        return ""

    def admits(self, value: float) -> bool:
        """Whether the number ``value`` lies within the bounds."""
        return (
            (self.ge is None or value >= self.ge)
            and (self.gt is None or value > self.gt)
            and (self.le is None or value <= self.le)
            and (self.lt is None or value < self.lt)
        )

    def range(self) -> tuple[float, float] | None:
        """``(low, high)``, inclusive, for a ROS parameter range (an exclusive bound given as inclusive;
        ±inf where unbounded); None when unbounded both ways."""
        low = self.ge if self.ge is not None else self.gt
        high = self.le if self.le is not None else self.lt
        if low is None and high is None:
            return None
        return (-math.inf if low is None else float(low), math.inf if high is None else float(high))


def _num(x: float | None) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


@overload
def setting(
    default: T,
    *,
    doc: str,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: Sequence[Any] | None = None,
    finite: bool = True,
) -> T: ...


@overload
def setting(*, factory: Callable[[], T], doc: str) -> T: ...


def setting(
    default: Any = dataclasses.MISSING,
    *,
    doc: str,
    factory: Callable[[], Any] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: Sequence[Any] | None = None,
    finite: bool = True,
) -> Any:
    """A configuration field: its default (or ``factory`` for a nested configuration), its bounds or
    choices and its description, checked by :class:`Settings`."""
    spec = Spec(
        doc=" ".join(doc.split()),
        ge=ge,
        gt=gt,
        le=le,
        lt=lt,
        choices=None if choices is None else tuple(choices),
        finite=finite,
    )
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata={SPEC: spec})
    return dataclasses.field(default=default, metadata={SPEC: spec})


def spec_of(field: dataclasses.Field[Any]) -> Spec | None:
    """The :class:`Spec` of a dataclass field declared with :func:`setting`, else None."""
    spec = field.metadata.get(SPEC) if field.metadata else None
    return spec if isinstance(spec, Spec) else None


class Settings:
    """Base of the configuration dataclasses: checks every :func:`setting` field on construction, then
    the class's own cross-field rules (:meth:`check`)."""

    def __post_init__(self) -> None:
        cls = type(self)
        for name, hint, spec in _specs(cls):
            _check(cls.__name__, name, getattr(self, name), hint, spec)
        self.check()

    def check(self) -> None:
        """Rules between fields (none here); raise :class:`~ptm_ros.errors.ConfigError`."""


_SPECS: dict[type, tuple[tuple[str, Any, Spec], ...]] = {}


def _specs(cls: type) -> tuple[tuple[str, Any, Spec], ...]:
    """``(name, type hint, spec)`` of every :func:`setting` field of ``cls`` (resolved once per class)."""
    out = _SPECS.get(cls)
    if out is None:
        hints = typing.get_type_hints(cls)
        out = tuple(
            (f.name, hints[f.name], s) for f in dataclasses.fields(cls) if (s := spec_of(f)) is not None
        )
        _SPECS[cls] = out
    return out


def unwrap_optional(hint: Any) -> tuple[Any, bool]:
    """``(X, True)`` for ``X | None``, else ``(hint, False)``."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1 and len(args) != len(typing.get_args(hint)):
            return args[0], True
    return hint, False


def _check(owner: str, name: str, value: Any, hint: Any, spec: Spec) -> None:
    hint, optional = unwrap_optional(hint)
    if value is None and optional:
        return
    problem = _problem(value, hint, spec)
    if problem is not None:
        msg = f"{owner}.{name} must be {problem}{' (or None)' if optional else ''}, got {_SHORT.repr(value)}"
        raise ConfigError(msg)


def _problem(value: Any, hint: Any, spec: Spec) -> str | None:
    """What ``value`` should have been, or None when it is admitted."""
    origin = typing.get_origin(hint)
    if origin in (tuple, list):
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        what = f"a list of {admitted(inner[0] if inner else Any, spec)}"
        if not isinstance(value, (tuple, list)):
            return what
        return what if any(_problem(v, inner[0] if inner else Any, spec) for v in value) else None
    if spec.choices is not None:
        return None if value in spec.choices and type(value) is not bool else admitted(hint, spec)
    if hint is bool:
        return None if isinstance(value, bool) else admitted(hint, spec)
    if hint is int:
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool) and spec.admits(int(value))
        return None if ok else admitted(hint, spec)
    if hint is float:
        if not isinstance(value, numbers.Real) or isinstance(value, bool):
            return admitted(hint, spec)
        try:
            number = float(value)
        except OverflowError:  # an integer beyond the floats
            return admitted(hint, spec)
        ok = math.isfinite(number) or (not spec.finite and not math.isnan(number))
        return None if ok and spec.admits(number) else admitted(hint, spec)
    if hint is str:
        return None if isinstance(value, str) else admitted(hint, spec)
    if isinstance(hint, type) and not isinstance(value, hint):
        return f"a {hint.__name__}"
    return None


def admitted(hint: Any, spec: Spec) -> str:
    """The values a field of type ``hint`` admits, in words: ``a finite number > 0``, ``an integer >= 1``,
    ``one of (...)``."""
    if spec.choices is not None:
        return f"one of {spec.choices}"
    bounds = spec.bounds()
    tail = f" {bounds}" if bounds else ""
    if hint is bool:
        return "true or false"
    if hint is int:
        return f"an integer{tail}"
    if hint is float:
        return f"{'a finite number' if spec.finite else 'a number'}{tail}"
    if hint is str:
        return "a string"
    return getattr(hint, "__name__", str(hint))


def settings_fields(cls: type) -> tuple[tuple[dataclasses.Field[Any], Any], ...]:
    """The init fields of a configuration dataclass with their resolved type hints."""
    hints = typing.get_type_hints(cls)
    return tuple((f, hints[f.name]) for f in dataclasses.fields(cls) if f.init)


def default_of(field: dataclasses.Field[Any]) -> Any:
    """A field's default value (a fresh one for a ``factory``); None when it has none."""
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


_JSON_TYPES = {bool: "boolean", int: "integer", float: "number", str: "string"}


def json_schema(cls: type, *, title: str | None = None) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a parameter file for the configuration dataclass ``cls``: every
    field optional (absent fields keep their defaults), no other keys, with types, bounds, choices,
    defaults and descriptions."""
    schema = _object_schema(cls)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    if title is not None:
        schema["title"] = title
    return schema


def _object_schema(cls: type) -> dict[str, Any]:
    props: dict[str, Any] = {}
    for f, hint in settings_fields(cls):
        spec = spec_of(f)
        props[f.name] = _field_schema(hint, spec, default_of(f))
    out: dict[str, Any] = {"type": "object", "additionalProperties": False, "properties": props}
    doc = (cls.__doc__ or "").strip().split("\n\n")[0]
    if doc:
        out["description"] = " ".join(doc.split())
    return out


def _field_schema(hint: Any, spec: Spec | None, default: Any) -> dict[str, Any]:
    hint, optional = unwrap_optional(hint)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        out = _object_schema(hint)
    else:
        out = _value_schema(hint, spec)
        if default is not None and not (isinstance(default, float) and not math.isfinite(default)):
            out["default"] = list(default) if isinstance(default, tuple) else default
    if spec is not None:
        out["description"] = spec.doc
    if optional:
        out = {"anyOf": [out, {"type": "null"}], **({"description": spec.doc} if spec else {})}
    return out


def _value_schema(hint: Any, spec: Spec | None) -> dict[str, Any]:
    if typing.get_origin(hint) in (tuple, list):
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return {"type": "array", "items": _value_schema(inner[0] if inner else Any, spec)}
    out: dict[str, Any] = {}
    if hint in _JSON_TYPES:
        out["type"] = _JSON_TYPES[hint]
    if spec is not None:
        if spec.choices is not None:
            out["enum"] = list(spec.choices)
        for key, bound in (
            ("minimum", spec.ge),
            ("exclusiveMinimum", spec.gt),
            ("maximum", spec.le),
            ("exclusiveMaximum", spec.lt),
        ):
            if bound is not None and hint in (int, float):
                out[key] = bound
    return out


def commented_yaml(config: Any, indent: int = 0, width: int = 100) -> list[str]:
    """YAML lines of the configuration dataclass instance ``config``, each field preceded by its
    description and bounds as comments (None values left out: a missing key takes its default)."""
    import yaml

    pad = " " * indent
    lines: list[str] = []
    for f, _hint in settings_fields(type(config)):
        value = getattr(config, f.name)
        if value is None:
            continue
        spec = spec_of(f)
        if spec is not None:
            note = spec.doc
            extra = f"one of {', '.join(map(str, spec.choices))}" if spec.choices else spec.bounds()
            if extra and not dataclasses.is_dataclass(value):
                note = f"{note.rstrip('.')}; {extra}"
            lines += [f"{pad}# {line}" for line in textwrap.wrap(note, max(40, width - indent - 2))]
        if dataclasses.is_dataclass(value):
            lines.append(f"{pad}{f.name}:")
            lines += commented_yaml(value, indent + 2, width)
            continue
        plain = list(value) if isinstance(value, tuple) else value
        text = yaml.safe_dump(plain, default_flow_style=True, width=10**6).strip()
        text = text.removesuffix("\n...").removesuffix("...").strip()
        lines.append(f"{pad}{f.name}: {text}")
    return lines
