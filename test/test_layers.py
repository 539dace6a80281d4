"""The layers of ptm_ros (``.importlinter``, checked by ``make lint``): every top-level module is core and
listed in the core contract, and the core imports and runs without ROS installed."""

from __future__ import annotations

import configparser
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADAPTERS = {"io", "nodes", "tools"}  # the subpackages above the core


def core_modules() -> set[str]:
    """The top-level modules of the package (everything that is not an adapter subpackage)."""
    pkg = REPO / "ptm_ros"
    return {f"ptm_ros.{p.stem}" for p in pkg.glob("*.py") if p.stem != "__init__"}


def contract(name: str) -> configparser.SectionProxy:
    parser = configparser.ConfigParser()
    parser.read(REPO / ".importlinter")
    return parser[f"importlinter:contract:{name}"]


def test_every_top_level_module_is_in_the_core_contract():
    listed = set(contract("core")["source_modules"].split())
    assert listed == core_modules(), (
        f"add to / remove from .importlinter's core contract: missing {sorted(core_modules() - listed)}, "
        f"stale {sorted(listed - core_modules())}"
    )
    subpackages = {p.name for p in (REPO / "ptm_ros").iterdir() if (p / "__init__.py").is_file()}
    assert subpackages == ADAPTERS, "a new subpackage needs its place in .importlinter's layers"
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
