"""Issue #25: output paths refused before the work, one exit-code convention, one-line errors.

Each tool is called in process with the work itself replaced by a function that fails the test: an
output error must come before it.
"""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import pytest
from cli_helpers import call, one_error_line

from ptm_ros.config import load_config
from ptm_ros.errors import ConfigError
from ptm_ros.tools import bringup, convert, run, sim
from ptm_ros.tools.paths import new_output, output_dir


def must_not_run(*args, **kwargs):
    pytest.fail("the tool started its work before checking its output path")


@pytest.fixture
def read_only_dir(tmp_path) -> Path:
    """An existing directory no file can be created in (for root: a read-only kernel file system)."""
    if os.geteuid() != 0:
        path = tmp_path / "ro"
        path.mkdir()
        path.chmod(0o555)
        return path
    for cand in (Path("/sys/fs"), Path("/proc")):
        try:
            (cand / ".ptm_probe").touch()
        except OSError:
            return cand
        (cand / ".ptm_probe").unlink()
    pytest.skip("no read-only directory found for root")


@pytest.fixture
def a_file(tmp_path) -> Path:
    path = tmp_path / "afile"
    path.write_text("not a directory\n")
    return path


@pytest.fixture
def no_work(monkeypatch):
    import ptm_ros.io.simulator
    import ptm_ros.tools.pipeline

    monkeypatch.setattr(ptm_ros.tools.pipeline, "run_offline", must_not_run)
    monkeypatch.setattr(ptm_ros.io.simulator, "simulate", must_not_run)
    monkeypatch.setattr(convert, "convert", must_not_run)
    monkeypatch.setattr(bringup, "Bringup", must_not_run)


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    from ptm_ros.io.bag import BagWriter

    path = tmp_path_factory.mktemp("paths") / "bag"
    with BagWriter(path) as w:
        for k in range(3):
            w.write_odometry(1.0 + k, (0.1 * k, 0.0, 0.0))
    return path


@pytest.fixture
def carmen_log(tmp_path) -> Path:
    path = tmp_path / "log.clf.gz"
    with gzip.open(path, "wt") as fh:
        fh.write("ODOM 0.0 0.0 0.0 0 0 0 1.0 x 1.0\n")
    return path


def test_an_existing_file_as_out_fails_at_once_in_every_tool(no_work, a_file, bag, carmen_log):
    cases = {
        "ptm-run": (run.main, [bag, "--out", a_file, "--quiet"], "is an existing file"),
        "ptm-bringup": (bringup.main, ["--bag", bag, "--out", a_file], "is an existing file"),
        "ptm-sim": (sim.main, [a_file], "exists already"),
        "ptm-convert": (convert.main, [carmen_log, a_file], "exists already"),
    }
    for prog, (main, argv, words) in cases.items():
        code, _, err = call(main, argv)
        assert code == 2, (prog, err)
        line = one_error_line(err, prog)
        assert str(a_file) in line and words in line and "choose" in line


def test_a_read_only_output_directory_fails_at_once_in_every_tool(no_work, read_only_dir, bag, carmen_log):
    cases = {
        "ptm-run": (run.main, [bag, "--out", read_only_dir, "--quiet"]),
        "ptm-bringup": (bringup.main, ["--bag", bag, "--out", read_only_dir]),
        "ptm-sim": (sim.main, [read_only_dir / "new_bag"]),
        "ptm-convert": (convert.main, [carmen_log, read_only_dir / "new_bag"]),
    }
    for prog, (main, argv) in cases.items():
        code, _, err = call(main, argv)
        assert code == 2, (prog, err)
        line = one_error_line(err, prog)
        assert f"cannot write into {read_only_dir}" in line and "choose a writable" in line


def test_bad_input_exits_2_with_one_line_in_convert_and_sim(tmp_path, carmen_log):
    code, _, err = call(convert.main, [tmp_path / "absent.clf", tmp_path / "out"])
    assert code == 2 and "does not exist" in one_error_line(err, "ptm-convert")
    (tmp_path / "garbage.clf").write_bytes(b"\x00\xff" * 100)
    code, _, err = call(convert.main, [tmp_path / "garbage.clf", tmp_path / "out2", "--strict"])
    assert code == 2
    one_error_line(err, "ptm-convert")
    code, _, err = call(sim.main, [tmp_path / "sim", "--landmarks", "0"])
    assert code == 2
    one_error_line(err, "ptm-sim")


def test_a_folder_that_is_not_a_bag_says_so(tmp_path):
    (tmp_path / "folder").mkdir()
    code, _, err = call(run.main, [tmp_path / "folder", "--out", tmp_path / "out", "--quiet"])
    assert code == 2
    assert one_error_line(err, "ptm-run").endswith(
        "folder is not a rosbag2 directory: it has no metadata.yaml"
    )


def test_broken_yaml_is_one_line(tmp_path, bag):
    params = tmp_path / "p.yaml"
    params.write_text("inference:\n  method: rbpf\n   particles: [1, 2\n")
    code, _, err = call(run.main, [bag, "--out", tmp_path / "out", "--params", params, "--quiet"])
    assert code == 2
    line = one_error_line(err, "ptm-run")
    assert f"malformed YAML in {params}, line 3, column 13: " in line


def test_a_wrong_value_in_the_parameter_file_is_an_error_even_where_a_flag_overrides_it(tmp_path, bag):
    """Issue #25: ``seed: "x"`` in the file and ``--seed 3`` on the command line used to run with seed 3,
    the file's error unseen; the file is now checked on its own, before any work."""
    params = tmp_path / "p.yaml"
    params.write_text('inference:\n  seed: "x"\n')
    code, _, err = call(
        run.main, [bag, "--out", tmp_path / "out", "--params", params, "--seed", "3", "--quiet"]
    )
    assert code == 2
    line = one_error_line(err, "ptm-run")
    assert "inference.seed: expected an integer, got 'x'" in line and str(params) in line
    assert not (tmp_path / "out").exists()
    good = tmp_path / "good.yaml"
    good.write_text("inference:\n  seed: 5\n")
    assert load_config(good, {"inference": {"seed": 3}}).inference.seed == 3  # a valid file: the flag wins


def test_output_checks_accept_new_and_existing_directories_and_create_nothing(tmp_path, a_file):
    assert output_dir(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    assert new_output(tmp_path / "x" / "bag") == tmp_path / "x" / "bag"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing created
    assert output_dir(tmp_path) == tmp_path  # existing: fine
    for check in (output_dir, new_output):
        with pytest.raises(ConfigError, match=f"{a_file} is a file, not a directory"):
            check(a_file / "sub")
