"""The package builds with colcon (ament_python) in a fresh workspace, as the README says, and its
installed executables and shared files are where ROS 2 looks for them (``lib/ptm_ros``, ``share``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXECUTABLES = (
    "ptm-convert",
    "ptm-sim",
    "ptm-run",
    "ptm-eval",
    "ptm-calibrate",
    "ptm-bringup",
    "ptm-bag-player",
    "landmark_detector",
    "topology_filter",
    "map_publisher",
)


def tracked_files() -> list[str]:
    """The repository's files as a clone has them (git's list; without git, the package's own parts)."""
    out = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=False)
    if out.returncode == 0 and out.stdout.strip():
        return out.stdout.split()
    keep = ("package.xml", "setup.py", "setup.cfg", "resource", "ptm_ros", "config", "bags")
    return [str(p.relative_to(REPO)) for k in keep for p in (REPO / k).rglob("*") if p.is_file()] + list(
        keep[:3]
    )


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, check=False, **kwargs)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    colcon = Path(sys.executable).with_name("colcon")
    if not colcon.exists():
        pytest.skip("colcon is not installed (requirements.txt installs colcon-common-extensions)")
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "ptm_ros"
    for name in tracked_files():
        if (REPO / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, src / name)
    env = {"PATH": f"{colcon.parent}:/usr/bin:/bin", "HOME": str(ws)}
    out = subprocess.run(
        [str(colcon), "build", "--base-paths", "src"],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return ws / "install" / "ptm_ros"


@pytest.mark.slow
def test_colcon_installs_the_executables_where_ros2_run_finds_them(workspace):
    lib = workspace / "lib" / "ptm_ros"
    assert sorted(p.name for p in lib.iterdir()) == sorted(EXECUTABLES)
    site = next((workspace / "lib").glob("python3*/site-packages"))
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    for name in ("ptm-run", "ptm-sim", "ptm-eval", "ptm-bringup"):
        out = run([str(lib / name), "--help"], env=env, cwd=workspace)
        assert out.returncode == 0 and "usage" in out.stdout.lower(), (name, out.stderr[-2000:])
    module = run([sys.executable, "-c", "import ptm_ros; print(ptm_ros.__file__)"], env=env, cwd=workspace)
    assert module.stdout.strip().startswith(str(site))  # the installed copy, not the checkout


def test_colcon_installs_the_shared_files(workspace):
    share = workspace / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "ptm_ros").is_file()
    pkg = share / "ptm_ros"
    assert (pkg / "package.xml").read_text() == (REPO / "package.xml").read_text()
    assert (pkg / "config" / "ptm.yaml").read_text() == (REPO / "config" / "ptm.yaml").read_text()
    assert (pkg / "config" / "fastdds.xml").is_file()
    assert sorted(p.name for p in (pkg / "bags").iterdir()) == sorted(
        p.name for p in (REPO / "bags").iterdir()
    )


def test_colcon_installs_the_ptm_json_schema_as_package_data(workspace):
    """``ptm_ros.model.ptm.ptm_schema`` finds the schema in the installed package (setup.py
    ``package_data``)."""
    site = next((workspace / "lib").glob("python3*/site-packages"))
    assert (site / "ptm_ros" / "schema" / "ptm.schema.json").is_file()
    code = (
        "from ptm_ros.model.ptm import ptm_schema; import ptm_ros; "
        "print(ptm_ros.__file__, ptm_schema()['$id'])"
    )
    out = run(
        [sys.executable, "-c", code], env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}, cwd=workspace
    )
    assert out.returncode == 0, out.stderr[-2000:]
    where, schema_id = out.stdout.split()
    assert where.startswith(str(site)) and schema_id == "urn:ptm_ros:schema:ptm/1"
