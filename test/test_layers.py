"""The layers of ptm_ros (``.importlinter``, checked by ``make lint``): every module is in the core or in an
adapter subpackage, the core's subpackages are ordered in layers, and the core imports and runs without
ROS installed."""

from __future__ import annotations

import configparser
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADAPTERS = {"io", "nodes", "tools"}  # the subpackages above the core


def core_parts() -> set[str]:
    """The core as the contracts name it: the top-level modules and every subpackage that is no adapter."""
    pkg = REPO / "ptm_ros"
    modules = {f"ptm_ros.{p.stem}" for p in pkg.glob("*.py") if p.stem != "__init__"}
    subpackages = {f"ptm_ros.{p.name}" for p in pkg.iterdir() if (p / "__init__.py").is_file()}
    return modules | {s for s in subpackages if s.removeprefix("ptm_ros.") not in ADAPTERS}


def core_modules() -> set[str]:
    """Every module of the core, subpackages' modules included."""
    pkg = REPO / "ptm_ros"
    out = set()
    for part in core_parts():
        path = pkg / part.removeprefix("ptm_ros.")
        if path.is_dir():
            out |= {f"{part}.{p.stem}" for p in path.glob("*.py") if p.stem != "__init__"}
        else:
            out.add(part)
    return out


def contract(name: str) -> configparser.SectionProxy:
    parser = configparser.ConfigParser()
    parser.read(REPO / ".importlinter")
    return parser[f"importlinter:contract:{name}"]


def test_every_part_of_the_core_is_in_the_core_contract_and_its_layers():
    listed = set(contract("core")["source_modules"].split())
    assert listed == core_parts(), (
        f"add to / remove from .importlinter's core contract: missing {sorted(core_parts() - listed)}, "
        f"stale {sorted(listed - core_parts())}"
    )
    layered = set(re.split(r"[\s|]+", contract("core-layers")["layers"].strip()))
    assert layered == core_parts(), "a core module or subpackage needs its place in the core-layers contract"
    assert set(contract("adapters")["layers"].split()) == ADAPTERS


def imports_without(modules: list[str], contract_name: str) -> None:
    """Import ``modules`` in a fresh interpreter in which the external modules the contract forbids cannot
    be imported (a finder that refuses them); afterwards none of them, nor any ptm_ros module the
    contract forbids, may be loaded."""
    forbidden = contract(contract_name)["forbidden_modules"].split()
    blocked = tuple(m for m in forbidden if not m.startswith("ptm_ros."))  # the external ones
    internal = tuple(m for m in forbidden if m.startswith("ptm_ros."))
    code = f"""
import importlib, importlib.abc, sys
BLOCKED = {blocked!r}
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is not available here")
sys.meta_path.insert(0, Refuse())
for mod in {sorted(modules)!r}:
    importlib.import_module(mod)
INTERNAL = {internal!r}
loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED or m.startswith(INTERNAL))
assert not loaded, loaded
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_the_core_imports_with_ros_and_bags_absent():
    """Every core module imports without rclpy, rosbags and the message packages, and loads no adapter."""
    imports_without(sorted(core_modules()), "core")


def test_the_nodes_logic_imports_without_ros():
    """The nodes' rclpy-free modules (their logic and wire format) import without rclpy and the message
    packages, and load no node module."""
    logic = contract("node-logic")["source_modules"].split()
    imports_without(logic, "node-logic")
