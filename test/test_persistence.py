"""Persistence of the filter state (issue #8): bit-identical round trips, a restored filter continuing
exactly like the original, atomic writes (also under kill -9), and clear errors for truncated, corrupt
and foreign files."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest

from ptm_ros.errors import DataError
from ptm_ros.inference import persistence
from ptm_ros.inference.persistence import (
    STATE_FILE_SCHEMA,
    load_filter_state,
    registrations_from_state,
    registrations_to_state,
    save_filter_state,
    visit_from_state,
    visit_to_state,
)
from ptm_ros.inference.rbpf import RbpfConfig, TopologyFilter
from ptm_ros.io.synthetic import grid_route, simulate_route, truth_registrar
from ptm_ros.model.geometry import NoMatch, RelativePose
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.posterior import ModelConfig, PosteriorModel
from ptm_ros.model.priors import PriorConfig, make_prior


def odd_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    nan_payload = np.array([0x7FF8_0000_DEAD_BEEF], dtype=np.uint64).view(np.float64)
    return {
        "f8": rng.normal(size=(3, 4, 5)),
        "f4": rng.normal(size=7).astype(np.float32),
        "specials": np.array([np.nan, np.inf, -np.inf, -0.0, 5e-324, np.finfo(float).max]),
        "nan_payload": nan_payload,
        "i8": rng.integers(-(2**62), 2**62, size=9),
        "u1": rng.integers(0, 255, size=(2, 3)).astype(np.uint8),
        "bool": rng.random(6) < 0.5,
        "big_endian": np.arange(4, dtype=">f8"),
        "fortran": np.asfortranarray(rng.normal(size=(3, 2))),
        "strided": rng.normal(size=(6, 6))[::2, 1::3],
        "empty": np.zeros((0, 3)),
        "zero_d": np.array(2.5),
        "complex": np.array([1 + 2j, -3.5j]),
    }


def assert_bit_identical(a: np.ndarray, b: np.ndarray) -> None:
    assert isinstance(b, np.ndarray) and b.dtype == a.dtype and b.shape == a.shape
    assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes()


def test_round_trip_is_bit_identical_and_keeps_types(tmp_path):
    arrays = odd_arrays()
    state = {
        "arrays": arrays,
        "nested": [1, (2, (3.0, None)), {"x": [True, "s"]}],
        "floats": [0.1, -0.0, float("nan"), float("inf"), -float("inf"), 1e-310],
        "big": 2**130 + 1,  # an RNG state holds 128-bit integers
        "scalars": (np.float32(1.5), np.int64(-7), np.bool_(True), np.float64(0.1)),
        "rng": np.random.default_rng(5).bit_generator.state,
        "single_tag_like": {"__array__": 0, "other": 1},  # tags only count alone in a mapping
    }
    meta = {"config": {"inference": {"particles": 100, "seed": 0}}, "who": "test"}
    path = save_filter_state(tmp_path / "state.npz", state, meta=meta)
    assert path.stat().st_mode & 0o777 == 0o644  # not the temporary file's rw-------
    got, got_meta = load_filter_state(path)
    assert got_meta == meta
    for name, arr in arrays.items():
        assert_bit_identical(arr, got["arrays"][name])
    assert got["nested"] == [1, (2, (3.0, None)), {"x": [True, "s"]}]
    assert isinstance(got["nested"][1], tuple) and isinstance(got["nested"][1][1], tuple)
    floats = np.array(got["floats"])
    assert np.array_equal(floats, state["floats"], equal_nan=True) and np.signbit(floats[1])
    assert got["big"] == 2**130 + 1 and got["rng"] == state["rng"]
    assert [type(x) for x in got["scalars"]] == [np.float32, np.int64, np.bool_, np.float64]
    assert got["scalars"] == state["scalars"]
    assert got["single_tag_like"] == {"__array__": 0, "other": 1}
    # the file is an .npz too: numpy reads its arrays; no pickles anywhere
    with np.load(path, allow_pickle=False) as npz:
        assert len([f for f in npz.files if f.startswith("arrays/")]) == len(arrays) + 4  # + 4 scalars
    with zipfile.ZipFile(path) as zf:
        header = json.loads(zf.read("header.json"))
    assert header["schema"] == STATE_FILE_SCHEMA and len(header["sha256"]) == 64


def test_visit_and_registration_pieces_round_trip():
    v = simulate_route([0, 1, 0], [(0.0, 0.0), (4.0, 0.0)], OdometryConfig(), signatures=True)[0][1]
    back = visit_from_state(visit_to_state(v))
    assert back == v and np.array_equal(back.signature, v.signature)
    pairs = {
        (0, 2): RelativePose(0, 2, np.array([0.1, 0.2, 0.3]), np.diag([0.01, 0.02, 0.003]), 1.5),
        (1, 2): NoMatch(1, 2, -2.0),
        (0, 1): None,
    }
    got = registrations_from_state(registrations_to_state(pairs))
    assert got.keys() == pairs.keys() and got[(0, 1)] is None and got[(1, 2)] == NoMatch(1, 2, -2.0)
    assert np.array_equal(got[(0, 2)].mean, pairs[(0, 2)].mean) and got[(0, 2)].log_bayes == 1.5
    with pytest.raises(DataError, match="bad visit entry"):
        visit_from_state({"index": 0})
    with pytest.raises(DataError, match="bad registration row"):
        registrations_from_state([[0]])


def test_a_filter_restored_from_the_file_continues_exactly(tmp_path):
    places, route = grid_route(18, seed=0)
    odo = OdometryConfig(n_samples=0, a_xy=0.1**2)
    visits, true = simulate_route(route, places, odo, seed=0, signatures=True)
    appearance = PosteriorModel(visits, ModelConfig(odometry=odo)).appearance
    laser = truth_registrar(true, route, fitness=True)

    def registrar(i, j):  # matches, failed matches and pairs without information
        return None if (i + j) % 4 == 0 and route[i] != route[j] else laser(i, j)

    args = (RbpfConfig(particles=12), make_prior(PriorConfig()), odo)
    original = TopologyFilter(*args, appearance=appearance, registrar=registrar, seed=11)
    for v in visits[:12]:
        original.update(v)
    state = original.state_dict()
    kinds = {type(z) for z in original._pairs.values()}
    assert kinds == {RelativePose, NoMatch, type(None)}  # every kind of registration is in the file
    save_filter_state(tmp_path / "f.npz", state, meta={"k": 12})
    loaded, meta = load_filter_state(tmp_path / "f.npz")
    assert meta == {"k": 12}
    for key in ("log_weights", "mean", "cov", "counts", "last", "n_places", "penalty"):
        assert_bit_identical(state[key], loaded[key])
    restored = TopologyFilter.from_state_dict(loaded, *args, appearance=appearance, registrar=registrar)
    assert restored.log_weights() == original.log_weights()
    for v in visits[12:]:
        original.update(v)
        restored.update(v)
        assert restored.log_weights() == original.log_weights()  # exactly, after every update
    assert restored.log_evidence == original.log_evidence
    assert_bit_identical(original.covariances(), restored.covariances())
    assert [h.n_topologies for h in restored.history] == [h.n_topologies for h in original.history]


def small_state():
    return {"w": np.arange(1000.0), "n": 3}


def test_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path, monkeypatch):
    path = save_filter_state(tmp_path / "s.npz", small_state(), meta={"v": 1})

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(persistence.os, "fsync", broken_fsync)
    with pytest.raises(DataError, match=r"cannot write the filter state.*disk full"):
        save_filter_state(path, {"w": np.zeros(3)}, meta={"v": 2})
    monkeypatch.undo()
    assert load_filter_state(path)[1] == {"v": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]
    with pytest.raises(DataError, match="cannot write"):
        save_filter_state(tmp_path / "missing" / "s.npz", small_state(), meta={})
    # unsavable values are refused before the file is touched
    for bad, match in (
        ({"o": np.array([object()])}, "Python objects"),
        ({1: 2}, "keys must be strings"),
        ({"x": {"__tuple__": [1]}}, "reserved"),
        ({"x": {1, 2}}, "type set"),
    ):
        with pytest.raises(DataError, match=match):
            save_filter_state(path, bad, meta={})
    assert load_filter_state(path)[1] == {"v": 1}


WRITER = """
import sys
import numpy as np
from ptm_ros.inference.persistence import save_filter_state
path = sys.argv[1]
states = [np.full(400_000, float(k)) for k in range(2)]
k = 0
while True:
    save_filter_state(path, {"w": states[k % 2], "k": k % 2}, meta={"k": k % 2})
    print(k, flush=True)
    k += 1
"""


@pytest.mark.slow
def test_kill_9_while_writing_never_leaves_a_broken_file(tmp_path):
    path = tmp_path / "state.npz"
    env = {**os.environ, "PYTHONPATH": str(persistence.__file__).rsplit("/ptm_ros/", 1)[0]}
    rng = np.random.default_rng(1)
    for _ in range(4):
        proc = subprocess.Popen(
            [sys.executable, "-c", WRITER, str(path)], env=env, stdout=subprocess.PIPE, text=True
        )
        assert proc.stdout is not None
        proc.stdout.readline()  # one complete save, then kill at a random moment of the next ones
        time.sleep(float(rng.uniform(0.0, 0.3)))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stdout.close()
        state, meta = load_filter_state(path)
        assert state["k"] == meta["k"] and np.all(state["w"] == float(state["k"]))
        assert state["w"].shape == (400_000,)
    save_filter_state(path, small_state(), meta={})  # the next writer clears a killed one's leftovers
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.npz"]


def rewrite(path, header_change=None, member_change=None):
    """Re-pack a state file with a changed header or array member (CRCs valid, checksum not)."""
    with zipfile.ZipFile(path) as zf:
        members = {name: zf.read(name) for name in zf.namelist()}
    header = json.loads(members["header.json"])
    if header_change:
        header_change(header)
    members["header.json"] = json.dumps(header).encode()
    if member_change:
        member_change(members)
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)


def test_truncated_corrupt_and_foreign_files_are_clear_data_errors(tmp_path):
    good = save_filter_state(tmp_path / "good.npz", small_state(), meta={"v": 1})
    data = good.read_bytes()
    cases = []
    for cut in (4, 100, len(data) // 2, len(data) - 10):
        p = tmp_path / f"cut{cut}.npz"
        p.write_bytes(data[:cut])
        cases.append((p, "truncated or corrupt"))
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x01  # inside the array member: its CRC fails
    (tmp_path / "flip.npz").write_bytes(bytes(flipped))
    cases.append((tmp_path / "flip.npz", "truncated or corrupt"))

    def tamper_array(members):
        arr = np.lib.format.read_array(io.BytesIO(members["arrays/0.npy"]))
        arr[3] += 1.0
        buf = io.BytesIO()
        np.lib.format.write_array(buf, arr)
        members["arrays/0.npy"] = buf.getvalue()

    for name, kwargs in (
        ("arr", {"member_change": tamper_array}),
        ("hdr", {"header_change": lambda h: h["state"].update(n=4)}),
        ("meta", {"header_change": lambda h: h["meta"].update(v=2)}),
    ):
        p = tmp_path / f"{name}.npz"
        p.write_bytes(data)
        rewrite(p, **kwargs)
        cases.append((p, "checksum mismatch"))
    text = tmp_path / "text.npz"
    text.write_text("hello")
    cases.append((text, "not a ptm_ros filter state \\(not a ZIP"))
    npz = tmp_path / "plain.npz"
    np.savez(npz, a=np.arange(3))
    cases.append((npz, "not a ptm_ros filter state \\(no header.json"))
    for name, schema, match in (
        ("other", "something/1", "not a ptm_ros filter state \\(schema"),
        ("newer", "ptm_ros.filter_state/2", "unsupported filter state schema"),
    ):
        p = tmp_path / f"{name}.npz"
        p.write_bytes(data)
        rewrite(p, header_change=lambda h, s=schema: h.update(schema=s))
        cases.append((p, match))
    p = tmp_path / "noheader_keys.npz"
    p.write_bytes(data)
    rewrite(p, header_change=lambda h: h.pop("state"))
    cases.append((p, "header lacks \\['state'\\]"))
    cases.append((tmp_path / "absent.npz", "no filter state at"))
    for path, match in cases:
        with pytest.raises(DataError, match=match):
            load_filter_state(path)
    assert load_filter_state(good)[1] == {"v": 1}
