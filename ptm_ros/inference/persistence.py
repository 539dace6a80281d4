r"""Persistence of the topology filter: one file holding a filter's state, to resume a run (issue #8).

The state saved is what :meth:`ptm_ros.inference.rbpf.TopologyFilter.state_dict` returns (the particles —
labels, log weights, the Gaussians of eq. 40–41 —, the RNG, the visits with their measurements, the laser
registrations, the history), possibly wrapped with more bookkeeping by its owner (the
``topology_filter`` node adds its stream position). A filter restored from it continues exactly as the
original: same log weights after any further updates under the same seed.

File format (schema ``ptm_ros.filter_state/1``)
-----------------------------------------------
An uncompressed ZIP archive (so ``numpy.load`` reads its arrays as an ``.npz``) of

* ``header.json`` (UTF-8 JSON): ``{"schema", "created_unix", "meta", "state", "arrays", "sha256"}``;
* ``arrays/<k>.npy``: the ``k``-th numpy array of the state, in ``.npy`` format (never pickled).

``state`` and ``meta`` are JSON trees in which a numpy array is ``{"__array__": k}``, a numpy scalar
``{"__scalar__": k}`` (a 0-d array member, restored with its dtype), a tuple ``{"__tuple__": [...]}`` and
a non-finite float ``{"__float__": "nan" | "inf" | "-inf"}``; finite floats are written with ``repr``
(exact round trip), integers at any size (an RNG state has 128-bit ones). ``arrays`` lists each member's
dtype and shape; ``sha256`` is the SHA-256 of the header written without it (``sort_keys``, compact)
followed by every array member's bytes in order: any change to the file is detected on load.
``meta`` is the owner's description: the configuration the state was made with, what made it.

Writing is atomic: a temporary file beside the target, flushed and fsync'ed, then renamed over it;
a process killed at any moment leaves either the previous file or the new one, never a mixture.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import io
import json
import math
import os
import tempfile
import time
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import DataError, ModelError, PtmError
from ptm_ros.inference.rbpf import registration_from_row, registration_row, visit_dict, visit_from_dict
from ptm_ros.model.appearance import AppearanceModel, NigPrior
from ptm_ros.model.geometry import NoMatch, RelativePose
from ptm_ros.model.visits import Visit

#: Schema tag of the file's header.
STATE_FILE_SCHEMA = "ptm_ros.filter_state/1"
_SCHEMA_FAMILY = "ptm_ros.filter_state/"
_HEADER = "header.json"
_ARRAY_DIR = "arrays/"
_TAGS = ("__array__", "__scalar__", "__tuple__", "__float__")


# --------------------------------------------------------------------------------------------- encoding


def _encode(value: Any, arrays: list[np.ndarray], where: str) -> Any:
    """A JSON tree of ``value``; arrays and numpy scalars are appended to ``arrays`` and referenced."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (np.ndarray, np.generic)):
        arr = np.asarray(value)
        if arr.dtype.hasobject:
            msg = f"{where}: arrays of Python objects cannot be saved"
            raise DataError(msg)
        arrays.append(np.array(arr, copy=True, order="C"))
        return {"__array__" if isinstance(value, np.ndarray) else "__scalar__": len(arrays) - 1}
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else {"__float__": repr(float(value))}
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v, arrays, f"{where}[{i}]") for i, v in enumerate(value)]}
    if isinstance(value, list):
        return [_encode(v, arrays, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for key, v in value.items():
            if not isinstance(key, str):
                msg = f"{where}: dictionary keys must be strings, got {key!r}"
                raise DataError(msg)
            if key in _TAGS and len(value) == 1:
                msg = f"{where}: a dictionary with the single key {key!r} is reserved by the file format"
                raise DataError(msg)
            out[key] = _encode(v, arrays, f"{where}.{key}")
        return out
    msg = f"{where}: cannot save a value of type {type(value).__name__}"
    raise DataError(msg)


def _decode(tree: Any, arrays: list[np.ndarray]) -> Any:
    if isinstance(tree, list):
        return [_decode(v, arrays) for v in tree]
    if not isinstance(tree, dict):
        return tree
    if len(tree) == 1:
        (key, value), *_ = tree.items()
        if key in ("__array__", "__scalar__"):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(arrays):
                msg = f"corrupt filter state: bad array reference {value!r}"
                raise DataError(msg)
            arr = arrays[value]
            return arr.copy() if key == "__array__" else arr[()]
        if key == "__tuple__":
            return tuple(_decode(v, arrays) for v in value)
        if key == "__float__":
            return float(value)
    return {k: _decode(v, arrays) for k, v in tree.items()}


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _digest(header: dict[str, Any], members: list[bytes]) -> str:
    h = hashlib.sha256(json.dumps(header, sort_keys=True, separators=(",", ":")).encode())
    for data in members:
        h.update(data)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------- writing


@contextlib.contextmanager
def _atomic_target(path: Path) -> Iterator[Any]:
    """A temporary file beside ``path`` that replaces it (fsync'ed) on success, vanishes on failure.

    Temporary files a killed writer left behind are removed first (one writer per file is assumed)."""
    for stale in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        with contextlib.suppress(OSError):
            stale.unlink()
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as f:
            try:  # the previous file's permissions, else rw-r--r-- (mkstemp's are rw-------)
                mode = path.stat().st_mode & 0o777
            except OSError:
                mode = 0o644
            os.fchmod(f.fileno(), mode)
            yield f
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable (not possible on every system)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def save_filter_state(path: str | Path, state: dict[str, Any], *, meta: dict[str, Any]) -> Path:
    """Write ``state`` (plain Python values and numpy arrays) and ``meta`` to ``path`` atomically.

    Returns:
        The path written.

    Raises:
        DataError: a value that cannot be saved (objects, non-string keys), or the file cannot be written
            (the previous file, if any, is then unchanged).
    """
    target = Path(path)
    if not isinstance(state, dict) or not isinstance(meta, dict):
        msg = "the filter state and its meta data must be dictionaries"
        raise DataError(msg)
    arrays: list[np.ndarray] = []
    header: dict[str, Any] = {
        "schema": STATE_FILE_SCHEMA,
        "created_unix": time.time(),
        "meta": _encode(meta, arrays, "meta"),
        "state": _encode(state, arrays, "state"),
    }
    header["arrays"] = [{"dtype": a.dtype.str, "shape": list(a.shape)} for a in arrays]
    members = [_npy_bytes(a) for a in arrays]
    header["sha256"] = _digest(header, members)
    try:
        text = json.dumps(header, allow_nan=False).encode()
        with _atomic_target(target) as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as zf:
            zf.writestr(_HEADER, text)
            for k, data in enumerate(members):
                zf.writestr(f"{_ARRAY_DIR}{k}.npy", data)
    except (OSError, ValueError) as err:
        msg = f"cannot write the filter state to {target}: {err}"
        raise DataError(msg) from err
    return target


# --------------------------------------------------------------------------------------------- reading


def _read_header(zf: zipfile.ZipFile, path: Path) -> dict[str, Any]:
    if _HEADER not in zf.namelist():
        msg = f"{path} is not a ptm_ros filter state (no {_HEADER} in the archive)"
        raise DataError(msg)
    try:
        header = json.loads(zf.read(_HEADER).decode())
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        msg = f"{path}: corrupt filter state (header is not JSON: {err})"
        raise DataError(msg) from err
    schema = header.get("schema") if isinstance(header, dict) else None
    if not isinstance(schema, str) or not schema.startswith(_SCHEMA_FAMILY):
        msg = f"{path} is not a ptm_ros filter state (schema {schema!r})"
        raise DataError(msg)
    if schema != STATE_FILE_SCHEMA:
        msg = f"{path}: unsupported filter state schema {schema!r} (this version reads {STATE_FILE_SCHEMA})"
        raise DataError(msg)
    keys = {"meta", "state", "arrays", "sha256"}
    if not keys <= set(header) or not isinstance(header["arrays"], list):
        msg = f"{path}: corrupt filter state (header lacks {sorted(keys - set(header))})"
        raise DataError(msg)
    return header


def load_filter_state(path: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Read a file written by :func:`save_filter_state`: ``(state, meta)``, arrays bit-identical.

    Raises:
        DataError: a missing file, a truncated or corrupt one (bad archive, CRC or checksum), or a
            foreign one (not a ptm_ros filter state, or another schema version).
    """
    source = Path(path)
    try:
        with source.open("rb") as f:
            magic = f.read(4)
    except FileNotFoundError as err:
        msg = f"no filter state at {source}"
        raise DataError(msg) from err
    except OSError as err:
        msg = f"cannot read the filter state {source}: {err}"
        raise DataError(msg) from err
    if magic != b"PK\x03\x04":
        msg = f"{source} is not a ptm_ros filter state (not a ZIP archive)"
        raise DataError(msg)
    try:
        with zipfile.ZipFile(source) as zf:
            header = _read_header(zf, source)
            members = [zf.read(f"{_ARRAY_DIR}{k}.npy") for k in range(len(header["arrays"]))]
    except (zipfile.BadZipFile, KeyError, EOFError, OSError) as err:
        msg = f"{source}: truncated or corrupt filter state (not a readable archive: {err})"
        raise DataError(msg) from err
    expected = header.pop("sha256")
    if _digest(header, members) != expected:
        msg = f"{source}: corrupt filter state (checksum mismatch)"
        raise DataError(msg)
    arrays = []
    for k, (data, spec) in enumerate(zip(members, header["arrays"], strict=True)):
        try:
            arr = np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
        except (ValueError, OSError, EOFError) as err:
            msg = f"{source}: corrupt filter state (array {k}: {err})"
            raise DataError(msg) from err
        if arr.dtype.str != spec.get("dtype") or list(arr.shape) != spec.get("shape"):
            msg = f"{source}: corrupt filter state (array {k} is not the {spec} the header lists)"
            raise DataError(msg)
        arrays.append(arr)
    state, meta = _decode(header["state"], arrays), _decode(header["meta"], arrays)
    if not isinstance(state, dict) or not isinstance(meta, dict):
        msg = f"{source}: corrupt filter state (state and meta must be mappings)"
        raise DataError(msg)
    return state, meta


# ------------------------------------------------------------------------------ pieces of a filter state


def visit_to_state(visit: Visit) -> dict[str, Any]:
    """A visit as plain values and arrays (the form :meth:`TopologyFilter.state_dict` uses)."""
    return visit_dict(visit)


def visit_from_state(d: dict[str, Any]) -> Visit:
    """Inverse of :func:`visit_to_state`.

    Raises:
        DataError: a malformed entry.
    """
    try:
        return visit_from_dict(d)
    except (KeyError, TypeError, ValueError, ModelError) as err:
        msg = f"corrupt filter state: bad visit entry ({type(err).__name__}: {err})"
        raise DataError(msg) from err


def appearance_to_state(model: AppearanceModel | None) -> dict[str, Any] | None:
    """Fitted appearance priors (:class:`~ptm_ros.model.appearance.AppearanceModel`) as plain values and
    arrays: a restored filter then scores with exactly the priors it was built with."""
    if model is None:
        return None
    nig = model.nig
    return {
        "nig": None
        if nig is None
        else {"mu": nig.mu, "kappa": nig.kappa, "alpha": nig.alpha, "beta": nig.beta},
        "dcm_alpha": model.dcm_alpha,
    }


def appearance_from_state(d: Mapping[str, Any] | None) -> AppearanceModel | None:
    """Inverse of :func:`appearance_to_state`.

    Raises:
        DataError: a malformed entry.
    """
    if d is None:
        return None
    try:
        nig = (
            None
            if d["nig"] is None
            else NigPrior(**{k: d["nig"][k] for k in ("mu", "kappa", "alpha", "beta")})
        )
        return AppearanceModel(nig=nig, dcm_alpha=d["dcm_alpha"])
    except (KeyError, TypeError, ValueError, PtmError) as err:
        msg = f"corrupt filter state: bad appearance priors ({type(err).__name__}: {err})"
        raise DataError(msg) from err


def registrations_to_state(pairs: Mapping[tuple[int, int], RelativePose | NoMatch | None]) -> list[list[Any]]:
    """Laser registration outcomes per pair ``(i, j)`` as rows ``[i, j, mean, cov, log_bayes]``."""
    return [registration_row(i, j, z) for (i, j), z in pairs.items()]


def registrations_from_state(
    rows: Sequence[Sequence[Any]],
) -> dict[tuple[int, int], RelativePose | NoMatch | None]:
    """Inverse of :func:`registrations_to_state`.

    Raises:
        DataError: a malformed row.
    """
    out: dict[tuple[int, int], RelativePose | NoMatch | None] = {}
    try:
        for row in rows:
            out[(int(row[0]), int(row[1]))] = registration_from_row(row)
    except (IndexError, TypeError, ValueError) as err:
        msg = f"corrupt filter state: bad registration row ({type(err).__name__}: {err})"
        raise DataError(msg) from err
    return out


# ---------------------------------------------------------------------------- checking a state's origin


def _hash_array(h: Any, name: str, value: Any, dtype: type) -> None:
    if value is None:
        h.update(f"{name}:none;".encode())
        return
    arr: NDArray[Any] = np.ascontiguousarray(np.asarray(value, dtype=dtype))
    h.update(f"{name}:{arr.dtype.str}{list(arr.shape)};".encode())
    h.update(arr.tobytes())


def visit_fingerprint(visit: Visit) -> str:
    """SHA-256 of every field of a visit: scalars by ``repr``, arrays by dtype, shape and bytes.

    Arrays are first cast to the dtypes :func:`visit_from_state` restores (float64, words int64), so a
    visit and its saved copy have the same fingerprint; any changed value changes it.
    """
    h = hashlib.sha256()
    odom = None if visit.odom_pose is None else [float(x) for x in visit.odom_pose]
    scalars = [
        int(visit.index),
        float(visit.stamp),
        [float(x) for x in visit.pose],
        odom,
        float(visit.travel),
        float(visit.rotation),
    ]
    h.update(repr(scalars).encode())
    _hash_array(h, "signature", visit.signature, np.float64)
    _hash_array(h, "words", visit.words, np.int64)
    _hash_array(h, "patch", visit.patch, np.float64)
    if visit.signature_spread is not None:  # visits without one hash as before the field existed
        _hash_array(h, "signature_spread", visit.signature_spread, np.float64)
    return h.hexdigest()


def visits_fingerprint(visits: Sequence[Visit]) -> str:
    """SHA-256 of a visit sequence (its :func:`visit_fingerprint` s in order): equal iff every visit is."""
    h = hashlib.sha256(f"{len(visits)} visits;".encode())
    for v in visits:
        h.update(visit_fingerprint(v).encode())
    return h.hexdigest()


def first_different_visit(saved: Sequence[Visit], fresh: Sequence[Visit]) -> int | None:
    """The first index at which ``saved`` differs from the first ``len(saved)`` of ``fresh`` (by
    :func:`visit_fingerprint`; ``len(fresh)`` when ``fresh`` is shorter), None when it is their prefix."""
    for k, v in enumerate(saved):
        if k >= len(fresh):
            return len(fresh)
        if visit_fingerprint(v) != visit_fingerprint(fresh[k]):
            return k
    return None


def differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    """Dotted paths at which two nested mappings (e.g. a state's meta configuration and this run's)
    differ; ``[]`` when they are equal."""
    if isinstance(saved, Mapping) and isinstance(current, Mapping):
        out: list[str] = []
        for key in sorted(set(saved) | set(current), key=str):
            out += differences(saved.get(key), current.get(key), f"{prefix}{key}.")
        return out
    return [] if saved == current else [prefix.rstrip(".") or "(value)"]
