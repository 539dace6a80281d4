"""Configuration declared once (:mod:`ptm_ros.settings`): the checks, the JSON schema and the commented
YAML all come from each field's :func:`setting`, and the schema and the checks agree value for value."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import jsonschema
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from ptm_ros.config import PtmConfig
from ptm_ros.errors import ConfigError
from ptm_ros.settings import (
    Settings,
    Spec,
    _check,
    commented_yaml,
    json_schema,
    setting,
    settings_fields,
    spec_of,
    unwrap_optional,
)


@dataclass(frozen=True)
class Inner(Settings):
    """A nested section."""

    rate: float = setting(1.0, gt=0, doc="a rate [1/s]")
    fraction: float = setting(0.5, ge=0, lt=1, doc="a fraction")


@dataclass(frozen=True)
class Toy(Settings):
    """A toy configuration."""

    count: int = setting(3, ge=1, doc="how many")
    scale: float = setting(1.0, doc="any finite number")
    limit: float = setting(math.inf, gt=0, finite=False, doc="a bound, inf for none")
    mode: str = setting("a", choices=("a", "b"), doc="the mode")
    flag: bool = setting(True, doc="a switch")
    name: str | None = setting(None, doc="an optional name")
    weights: tuple[float, ...] = setting((1.0, 0.5), gt=0, le=1, doc="weights in (0, 1]")
    inner: Inner = setting(factory=Inner, doc="the section")

    def check(self) -> None:
        if self.count > 10 and self.mode == "b":
            msg = "Toy: mode 'b' takes at most 10"
            raise ConfigError(msg)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"count": 0}, "Toy.count must be an integer >= 1, got 0"),
        ({"count": True}, "Toy.count must be an integer >= 1, got True"),
        ({"count": 2.0}, "Toy.count must be an integer >= 1, got 2.0"),
        ({"scale": math.nan}, "Toy.scale must be a finite number, got nan"),
        ({"scale": math.inf}, "Toy.scale must be a finite number, got inf"),
        ({"scale": "1"}, "Toy.scale must be a finite number, got '1'"),
        ({"scale": 10**400}, r"Toy.scale must be a finite number, got 1000000000\.\.\.0+$"),
        ({"limit": 0.0}, "Toy.limit must be a number > 0, got 0.0"),
        ({"limit": math.nan}, "Toy.limit must be a number > 0, got nan"),
        ({"mode": "c"}, r"Toy.mode must be one of \('a', 'b'\), got 'c'"),
        ({"flag": 1}, "Toy.flag must be true or false, got 1"),
        ({"name": 3}, r"Toy.name must be a string \(or None\), got 3"),
        ({"weights": (0.5, 1.5)}, r"Toy.weights must be a list of a finite number in \(0, 1\], got"),
        ({"weights": 0.5}, "Toy.weights must be a list of"),
        ({"inner": {"rate": 1.0}}, "Toy.inner must be a Inner"),
        ({"count": 11, "mode": "b"}, "mode 'b' takes at most 10"),
    ],
)
def test_every_declared_rule_is_checked_with_the_field_named(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        Toy(**kwargs)


def test_admitted_values_pass():
    t = Toy(count=2, scale=-3, limit=math.inf, mode="b", flag=False, name="x", weights=(1, 0.1))
    assert t.scale == -3 and t.limit == math.inf
    assert Toy(name=None) == Toy()
    with pytest.raises(ConfigError, match=r"Inner.fraction must be a finite number in \[0, 1\), got 1"):
        dataclasses.replace(Toy().inner, fraction=1)


def test_spec_bounds_and_ros_range():
    assert Spec("x", gt=0).bounds() == "> 0" and Spec("x", gt=0).range() == (0.0, math.inf)
    assert Spec("x", ge=0, lt=1).bounds() == "in [0, 1)"
    assert Spec("x", le=5).range() == (-math.inf, 5.0)
    assert Spec("x").range() is None and Spec("x").bounds() == ""


def test_the_schema_describes_every_field():
    schema = json_schema(Toy)
    jsonschema.Draft202012Validator.check_schema(schema)
    props = schema["properties"]
    assert props["count"] == {"type": "integer", "minimum": 1, "default": 3, "description": "how many"}
    assert props["mode"]["enum"] == ["a", "b"]
    assert props["weights"]["items"] == {"type": "number", "exclusiveMinimum": 0, "maximum": 1}
    assert props["inner"]["properties"]["rate"]["exclusiveMinimum"] == 0
    assert "default" not in props["limit"]  # JSON has no inf
    assert {"type": "null"} in props["name"]["anyOf"]
    validator = jsonschema.Draft202012Validator(schema)
    assert not list(validator.iter_errors({"count": 2, "inner": {"rate": 2.0}}))
    assert list(validator.iter_errors({"cout": 2}))  # a misspelt key
    assert list(validator.iter_errors({"inner": {"rate": 0}}))


def _leaves(cls, prefix=""):
    for f, hint in settings_fields(cls):
        inner, _ = unwrap_optional(hint)
        if isinstance(inner, type) and dataclasses.is_dataclass(inner):
            yield from _leaves(inner, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", cls, f


LEAVES = list(_leaves(PtmConfig))
SCHEMA = json_schema(PtmConfig)


def _subschema(path):
    node = SCHEMA
    for part in path.split("."):
        node = node["properties"][part]
    return node


def test_every_parameter_of_ptm_is_declared_and_described():
    undeclared = [p for p, _, f in LEAVES if spec_of(f) is None or not spec_of(f).doc]
    assert not undeclared, undeclared
    jsonschema.Draft202012Validator.check_schema(SCHEMA)


def test_the_shipped_parameter_file_follows_the_schema():
    from pathlib import Path

    doc = yaml.safe_load((Path(__file__).parents[1] / "config" / "ptm.yaml").read_text())
    jsonschema.validate(doc["/**"]["ros__parameters"], SCHEMA)


VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 300),
    st.floats(-5, 300, allow_nan=False),
    st.sampled_from([0.0, 1.0, 0.5, 1e-9, -0.0]),
    st.sampled_from(["", "rbpf", "fourier", "auto", "dirichlet", "x"]),
    st.lists(st.one_of(st.floats(-2, 2, allow_nan=False), st.sampled_from(["fourier", "words"])), max_size=3),
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.sampled_from(LEAVES), VALUES)
def test_the_schema_and_the_checks_agree_on_every_value(leaf, value):
    """A value passes a field's declared checks exactly when it passes the field's JSON schema (rules
    between fields, ``check()``, are beyond the schema and not exercised here)."""
    path, cls, f = leaf
    spec = spec_of(f)
    hint = {g.name: h for g, h in settings_fields(cls)}[f.name]
    if unwrap_optional(hint)[0] is int and isinstance(value, float) and value.is_integer():
        return  # JSON does not tell 2.0 from 2; the YAML loader refuses 2.0 for an integer
    try:
        _check(cls.__name__, f.name, tuple(value) if isinstance(value, list) else value, hint, spec)
        checked = True
    except ConfigError:
        checked = False
    schema_ok = jsonschema.Draft202012Validator(_subschema(path)).is_valid(value)
    assert checked == schema_ok, (path, value)


def test_the_commented_yaml_loads_back_to_the_same_configuration():
    lines = commented_yaml(PtmConfig())
    assert any(line.lstrip().startswith("# ") for line in lines)
    from ptm_ros.configio import from_dict

    assert from_dict(PtmConfig, yaml.safe_load("\n".join(lines))) == PtmConfig()


PATHS = [path for path, _, _ in LEAVES]
WILD = st.one_of(
    VALUES,
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**70), 2**70),
    st.sampled_from([10**400, -(10**400)]),  # YAML reads integers of any length
    st.dictionaries(st.sampled_from(["a", "kind", "x"]), st.integers(), max_size=2),
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.lists(
        st.tuples(st.sampled_from([*PATHS, "model.bogus", "inference", "detector.kind.deeper"]), WILD),
        max_size=4,
    )
)
def test_any_parameter_file_gives_a_configuration_or_one_config_error(items):
    """Whatever a parameter file holds (values of any type, unknown keys, sections replaced by values),
    loading it gives a configuration or one ConfigError of one line naming where: never another
    exception (the nodes turn it into exit code 2, ``ptm-run`` into a one-line error)."""
    from ptm_ros.config import load_config

    doc: dict = {}
    for path, value in items:
        *parents, leaf = path.split(".")
        node = doc
        for part in parents:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                break
            node = child
        else:
            node[leaf] = value
    try:
        config = load_config(None, doc)
    except ConfigError as err:
        text = str(err)
        assert text and "\n" not in text, text
    else:
        assert isinstance(config, PtmConfig)
