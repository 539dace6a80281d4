"""Configuration: strict loading with precise errors, the shipped defaults file, round trips."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from ptm_ros.config import PtmConfig, load_config, ros_parameters_yaml, save_config
from ptm_ros.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def test_shipped_defaults_file_matches_the_dataclasses():
    assert (REPO / "config" / "ptm.yaml").read_text() == ros_parameters_yaml()
    assert load_config(REPO / "config" / "ptm.yaml") == PtmConfig()


def test_the_shipped_parameter_schema_is_generated_from_the_declarations():
    """``ptm_ros/schema/params.schema.json`` is ``python -m ptm_ros.config --schema`` (package data)."""
    import json
    from importlib.resources import files

    from ptm_ros.config import PARAMS_SCHEMA_FILE, params_schema

    shipped = json.loads((REPO / "ptm_ros" / "/".join(PARAMS_SCHEMA_FILE)).read_text())
    assert shipped == params_schema()
    assert json.loads((files("ptm_ros") / "/".join(PARAMS_SCHEMA_FILE)).read_text()) == params_schema()


#: Fields the shipped ptm.yaml leaves out: their default is None ("unset"), which a ROS 2 parameter cannot
#: hold; a missing key takes the default.
UNSET_BY_DEFAULT = {
    "model.appearance.nig_kappa",
    "model.appearance.dcm_alpha",
    "detector.kind",
    "detector.vocabulary",
}


def default_fields(config: Any, prefix: str = "") -> dict[str, Any]:
    """Every leaf field of a config dataclass instance by dotted name, with its value."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out |= default_fields(value, f"{prefix}{f.name}.")
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def yaml_leaves(doc: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Every leaf of a nested YAML mapping by dotted name (lists are leaves)."""
    out: dict[str, Any] = {}
    for key, value in doc.items():
        if isinstance(value, dict):
            out |= yaml_leaves(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_shipped_defaults_file_lists_every_field_with_its_default():
    """config/ptm.yaml against PtmConfig field by field: every key is a field with that default, every
    field is a key (except those unset by default, named above)."""
    doc = yaml.safe_load((REPO / "config" / "ptm.yaml").read_text())
    listed = yaml_leaves(doc["/**"]["ros__parameters"])
    fields = default_fields(PtmConfig())
    assert sorted(set(listed) - set(fields)) == [], "keys of config/ptm.yaml that PtmConfig lacks"
    assert sorted(set(fields) - set(listed)) == sorted(UNSET_BY_DEFAULT)
    assert all(fields[name] is None for name in UNSET_BY_DEFAULT)
    differing = {
        name: (value, fields[name])
        for name, value in listed.items()
        if (list(fields[name]) if isinstance(fields[name], tuple) else fields[name]) != value
    }
    assert differing == {}, "config/ptm.yaml value, PtmConfig default"


def write(tmp_path, text):
    p = tmp_path / "p.yaml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("inference: {particlez: 3}\n", r"inference: unknown key\(s\) \['particlez'\]"),
        ("inference: {particles: three}\n", r"inference.particles: expected an integer"),
        ("inference: {particles: 0}\n", r"InferenceConfig\.particles must be an integer >= 1, got 0"),
        ("model: {odometry: {area_m2: .nan}}\n", r"model.odometry.area_m2: NaN"),
        ("model: {prior: {kind: uniform}}\n", r"PriorConfig\.kind must be one of"),
        ("model: {use_laser: 1}\n", r"model.use_laser: expected true/false"),
        ("inference: [1, 2]\n", r"inference: expected a mapping"),
        ("inference: {method: rbpf\n", r"^malformed YAML in \S+, line 2, column 1: [^\n]+$"),
        (
            "inference:\n  method: rbpf\n   particles: 3\n",
            r"^malformed YAML in \S+, line 3, column 13: [^\n]+$",
        ),
        ("- 1\n", r"top level must be a mapping"),
    ],
)
def test_bad_parameter_files_are_rejected_with_the_field_named(tmp_path, text, match):
    with pytest.raises(ConfigError, match=match):
        load_config(write(tmp_path, text))


@pytest.mark.parametrize(
    ("written", "fixed"), [("5e-05", "5.0e-05"), ("1.0e3", "1.0e+3"), ("2E-3", "2.0e-3")]
)
def test_an_exponent_yaml_reads_as_text_gets_the_form_it_reads_as_a_number(tmp_path, written, fixed):
    """YAML 1.1 (PyYAML, as ROS 2 parameter files are read) needs a decimal point and a signed exponent:
    ``5e-05`` is a string. The error says so and names the spelling that loads, which then loads."""
    got, hint = re.escape(written), re.escape(fixed)
    want = rf"model\.odometry\.b_th: expected a number, got '{got}' .*write {hint}\)"
    with pytest.raises(ConfigError, match=want):
        load_config(write(tmp_path, f"model:\n  odometry:\n    b_th: {written}\n"))
    cfg = load_config(write(tmp_path, f"model:\n  odometry:\n    b_th: {fixed}\n"))
    assert cfg.model.odometry.b_th == float(fixed)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read parameter file"):
        load_config(tmp_path / "absent.yaml")


def test_ros_parameter_file_sections_are_merged(tmp_path):
    text = (
        "/**:\n  ros__parameters:\n    use_sim_time: true\n    inference: {particles: 7}\n"
        "topology_filter:\n  ros__parameters:\n    inference: {seed: 3}\n"
    )
    cfg = load_config(write(tmp_path, text))
    assert (cfg.inference.particles, cfg.inference.seed) == (7, 3)
    with pytest.raises(ConfigError, match="only"):
        load_config(write(tmp_path, "/**:\n  ros__parameters: {}\nextra: 1\n"))


def test_overrides_and_round_trip(tmp_path):
    cfg = load_config(None, {"inference": {"method": "exact", "top": 5}, "detector": {"kind": "equidistant"}})
    assert cfg.inference.method == "exact" and cfg.inference.top == 5
    assert load_config(save_config(cfg, tmp_path / "c.yaml")) == cfg


def test_node_only_parameters_are_known_to_the_loader():
    common = pytest.importorskip("ptm_ros.nodes.common", reason="rclpy not installed")
    from ptm_ros.config import ROS_ONLY_PARAMETERS

    assert set(common.NODE_PARAMETERS) <= ROS_ONLY_PARAMETERS


def test_a_negative_seed_is_refused_before_any_work(tmp_path, capsys):
    """Issue #25: ``--seed -1`` fails at once with one line and exit 2 (it used to end a whole run in a
    numpy traceback), in ptm-run (the configuration) and in ptm-sim (its argument parser)."""
    from ptm_ros.tools import run as run_cli
    from ptm_ros.tools import sim as sim_cli

    with pytest.raises(ConfigError, match=r"InferenceConfig\.seed must be an integer >= 0, got -1"):
        load_config(None, {"inference": {"seed": -1}})
    assert run_cli.main([str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o"), "--seed", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ptm-run: error: ") and "seed" in err and "\n" not in err
    with pytest.raises(SystemExit) as stop:
        sim_cli.main([str(tmp_path / "b"), "--seed", "-1"])
    assert stop.value.code == 2 and "expected an integer >= 0" in capsys.readouterr().err
    assert not (tmp_path / "b").exists() and not (tmp_path / "o").exists()
