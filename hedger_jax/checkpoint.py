"""Save and load a HEDGER agent to one file, bit for bit, atomically.

What is saved: the ``HedgerConfig``; the ``Memory`` (any leading batch axes), its five
arrays (a neighbour index, when the config uses one, is derived state, rebuilt on load by
``refresh_index``); optionally the ``RunConfig``; optional extra arrays (e.g. the learner's
PRNG key); and metadata (library, jax, numpy and Python versions, seed, env id, creation
time, user keys).

File format (format version 1): one uncompressed ``.npz`` (a zip, loaded without pickle)::

    header            0-d unicode array: JSON (see below)
    memory/points     float32 (..., d, capacity)
    memory/values     float32 (..., capacity)
    memory/size       int32 (...)
    memory/head       int32 (...)
    memory/flags      int32 (...)
    memory/transitions/reward, next_obs, terminated, present
                      (only where the config keeps transitions, ``backup_sweeps`` > 0)
    extra/<name>      any numeric array passed as ``extra_arrays``

    header = {"format": "hedger-jax-checkpoint", "format_version": 1,
              "hedger_config": {field: value}, "run_config": {field: value} | null,
              "metadata": {"library_version", "jax_version", "numpy_version",
                           "python_version", "created", "seed", "env_id", ...user keys},
              "arrays": {name: {"dtype", "shape", "sha256"}}}

Each array's sha256 (over its dtype, shape and bytes) is in the header, so corruption that the
zip's own CRCs would not see is still caught. Arrays are stored with their exact dtype and
bytes and loaded back as the same dtype: a round trip is bit-for-bit.

Writes are atomic: the file is written to a temporary file in the same folder, flushed and
``fsync``-ed, then ``os.replace``-d over the destination (and the folder fsync-ed): an
interrupted save leaves the previous file intact and no temporary file behind.

Every problem found while loading (missing, truncated, corrupt, wrong format or version,
checksum mismatch, a config different from the one expected) raises :class:`CheckpointError`
(a ``ValueError``) whose message names the file and the problem.
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import io
import json
import os
import platform
import zipfile
from typing import Any, Dict, NamedTuple, Optional, Union

import numpy as np

from hedger_jax.config import HedgerConfig
from hedger_jax.errors import CheckpointError  # noqa: F401 (re-exported)
from hedger_jax.files import atomic_write
from hedger_jax.memory import Memory, StoredTransitions, keeps_transitions, refresh_index
from hedger_jax.run_config import RunConfig
from hedger_jax.validation import InvalidInputError, check_memory, config_differences
from hedger_jax.version import __version__ as lib_version

__all__ = ["CheckpointError", "Checkpoint", "save_checkpoint", "load_checkpoint",
           "read_checkpoint_header", "FORMAT", "FORMAT_VERSION"]

#: The header's "format" value.
FORMAT = "hedger-jax-checkpoint"
#: The format version written, and the only one read.
FORMAT_VERSION = 1
#: The ``Memory`` arrays saved (the index is rebuilt, not saved).
_MEMORY_FIELDS = ("points", "values", "size", "head", "flags")
#: Their required dtypes.
_MEMORY_DTYPES = {"points": np.float32, "values": np.float32, "size": np.int32,
                  "head": np.int32, "flags": np.int32}
#: The ``StoredTransitions`` arrays saved where the config keeps transitions, and their dtypes.
_TRANSITION_DTYPES = {"reward": np.float32, "next_obs": np.float32, "terminated": np.bool_,
                      "present": np.bool_}
#: Bytes per write call of a save.
_CHUNK = 1 << 20

PathLike = Union[str, os.PathLike]


class Checkpoint(NamedTuple):
    """What ``load_checkpoint`` returns.

    config: HedgerConfig; memory: Memory (jax arrays, exact bits of what was saved; the
    index rebuilt); run_config: RunConfig or None; metadata: dict (see the module
    docstring); extra_arrays: dict name -> np.ndarray.
    """

    config: HedgerConfig
    memory: Memory
    run_config: Any
    metadata: Dict[str, Any]
    extra_arrays: Dict[str, np.ndarray]


def _digest(a: np.ndarray) -> str:
    """sha256 hex digest of an array's dtype, shape and bytes."""
    a = np.ascontiguousarray(a)
    h = hashlib.sha256(f"{a.dtype.str}|{a.shape}|".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def _config_to_json(cfg: Any) -> Dict[str, Any]:
    """A config dataclass as a JSON-ready dict (tuples as lists)."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if isinstance(v, tuple):
            v = [list(x) if isinstance(x, tuple) else x for x in v]
        out[f.name] = v
    return out


def _config_from_json(cls: type, data: Dict[str, Any], where: str) -> Any:
    """A ``cls`` config from ``_config_to_json``'s dict (validated by its constructor), else
    ``CheckpointError``."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise CheckpointError(f"{where}: {cls.__name__} fields {unknown} are unknown to this "
                              "version of hedger_jax")
    kwargs = {}
    for k, v in data.items():
        if isinstance(v, list):
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kwargs[k] = v
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{where}: stored {cls.__name__} is invalid ({exc})") from None


def _versions() -> Dict[str, str]:
    """The library, jax, numpy and Python versions for the metadata."""
    import jax

    return {"library_version": lib_version, "jax_version": jax.__version__,
            "numpy_version": np.__version__, "python_version": platform.python_version()}


def _write_bytes(f, data: bytes) -> None:
    """Write ``data`` to the open file ``f`` in chunks (a seam for tests of interrupted saves)."""
    view = memoryview(data)
    for start in range(0, len(view), _CHUNK):
        f.write(view[start:start + _CHUNK])


def save_checkpoint(path: PathLike, config: HedgerConfig, memory: Memory, run_config: Any = None,
                    *, seed: Optional[int] = None, env_id: Optional[str] = None,
                    extra_arrays: Optional[Dict[str, Any]] = None,
                    metadata: Optional[Dict[str, Any]] = None) -> str:
    """Write an agent to ``path`` (one ``.npz`` file) atomically. Returns the path.

    config: the HedgerConfig; memory: a Memory (optionally batched) matching it; run_config:
    a RunConfig (or any frozen dataclass of JSON values) or None; seed / env_id: recorded in
    the metadata; extra_arrays: numeric arrays stored bit-for-bit (e.g. a PRNG key);
    metadata: extra JSON-serialisable keys (may not override the library's own).
    """

    if not isinstance(config, HedgerConfig):
        raise TypeError(f"save_checkpoint: config must be a HedgerConfig, got {type(config).__name__}")
    try:
        check_memory(config, memory)
    except InvalidInputError as exc:
        raise ValueError(f"save_checkpoint: the memory does not fit the config: {exc}") from None
    arrays: Dict[str, np.ndarray] = {}
    for k in _MEMORY_FIELDS:
        arrays[f"memory/{k}"] = np.asarray(getattr(memory, k))
    if memory.transitions is not None:
        for k in _TRANSITION_DTYPES:
            arrays[f"memory/transitions/{k}"] = np.asarray(getattr(memory.transitions, k))
    for k, v in (extra_arrays or {}).items():
        a = np.asarray(v)
        if a.dtype == object or a.dtype.kind not in "biuf":
            raise ValueError(f"save_checkpoint: extra array {k!r} must be numeric, got {a.dtype}")
        arrays[f"extra/{k}"] = a
    meta = dict(metadata or {})
    own = _versions()
    own.update({"created": datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds"), "seed": None if seed is None else int(seed), "env_id": env_id})
    clash = sorted(set(meta) & set(own))
    if clash:
        raise ValueError(f"save_checkpoint: metadata keys {clash} are reserved")
    meta.update(own)
    header = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "hedger_config": _config_to_json(config),
        "run_config": None if run_config is None else _config_to_json(run_config),
        "run_config_type": None if run_config is None else type(run_config).__name__,
        "metadata": meta,
        "arrays": {k: {"dtype": a.dtype.str, "shape": list(a.shape), "sha256": _digest(a)}
                   for k, a in arrays.items()},
    }
    try:
        text = json.dumps(header, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"save_checkpoint: metadata is not JSON-serialisable ({exc})") from None
    buf = io.BytesIO()
    np.savez(buf, header=np.array(text), **arrays)
    data = buf.getvalue()

    return atomic_write(path, lambda f: _write_bytes(f, data), prefix=".ckpt-")


def _read(path: str):
    """Open and verify a checkpoint file -> (header, arrays by name, fail, where); every
    problem raises ``CheckpointError`` naming the file."""
    where = f"checkpoint {path!r}"

    def fail(msg):
        raise CheckpointError(f"{where}: {msg}")

    if not os.path.exists(path):
        fail("missing file (no such file)")
    if os.path.isdir(path):
        fail("is a directory, not a file")
    try:
        with np.load(path, allow_pickle=False) as z:
            names = list(z.files)
            raw = {k: np.array(z[k]) for k in names}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        if isinstance(exc, zipfile.BadZipFile) and "CRC" in str(exc):
            fail(f"corrupt file: {exc}")
        fail(f"truncated or corrupt file ({type(exc).__name__}: {exc})")
    except Exception as exc:  # zlib.error and other decoder failures
        fail(f"truncated or corrupt file ({type(exc).__name__}: {exc})")
    if "header" not in raw:
        fail(f"not a hedger-jax checkpoint (no header; arrays {sorted(names)})")
    h = raw.pop("header")
    if h.ndim != 0 or h.dtype.kind != "U":
        fail("header is not a JSON string")
    try:
        header = json.loads(str(h))
    except json.JSONDecodeError as exc:
        fail(f"header is not valid JSON ({exc})")
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        fail(f"not a hedger-jax checkpoint (format {header.get('format') if isinstance(header, dict) else None!r}, "
             f"expected {FORMAT!r})")
    if header.get("format_version") != FORMAT_VERSION:
        fail(f"unsupported format version {header.get('format_version')!r} (this hedger_jax "
             f"reads version {FORMAT_VERSION})")
    for k in ("hedger_config", "run_config", "metadata", "arrays"):
        if k not in header:
            fail(f"header lacks {k!r}")
    listed = header["arrays"]
    missing = sorted(set(listed) - set(raw))
    if missing:
        fail(f"missing arrays {missing}")
    unlisted = sorted(set(raw) - set(listed))
    if unlisted:
        fail(f"arrays {unlisted} are not listed in the header")
    for k, a in raw.items():
        spec = listed[k]
        if a.dtype.str != spec["dtype"] or list(a.shape) != list(spec["shape"]):
            fail(f"array {k!r} has dtype {a.dtype.str} shape {list(a.shape)}, header says "
                 f"{spec['dtype']} {spec['shape']}")
        if _digest(a) != spec["sha256"]:
            fail(f"checksum mismatch: array {k!r} is corrupt (sha256 differs from the header)")
    return header, raw, fail, where


def read_checkpoint_header(path: PathLike) -> Dict[str, Any]:
    """The (validated) JSON header of a checkpoint file."""
    return _read(os.fspath(path))[0]


def load_checkpoint(path: PathLike, config: Optional[HedgerConfig] = None,
                    run_config: Any = None, *, env_id: Optional[str] = None) -> Checkpoint:
    """Load a checkpoint written by ``save_checkpoint``.

    config / run_config / env_id: what the caller expects; when given, a stored value that
    differs is refused with a :class:`CheckpointError` listing the differing field names.
    Returns :class:`Checkpoint` with a ``Memory`` of jax arrays holding the exact saved bits.
    """
    import jax
    import jax.numpy as jnp


    header, raw, fail, where = _read(os.fspath(path))
    stored = _config_from_json(HedgerConfig, header["hedger_config"], where)
    if config is not None:
        diff = config_differences(stored, config)
        if diff:
            detail = ", ".join(f"{k}: file {getattr(stored, k)!r} != expected "
                               f"{getattr(config, k)!r}" for k in diff[:6])
            fail(f"config mismatch in fields {diff} ({detail})")
    stored_run = None
    if header["run_config"] is not None:

        if header.get("run_config_type", "RunConfig") != "RunConfig":
            fail(f"unknown run_config type {header.get('run_config_type')!r}")
        stored_run = _config_from_json(RunConfig, header["run_config"], where)
    if run_config is not None:
        if stored_run is None:
            fail("run_config mismatch: the file has no RunConfig")
        diff = config_differences(stored_run, run_config)
        if diff:
            fail(f"run_config mismatch in fields {diff}")
    meta = header["metadata"]
    if env_id is not None and meta.get("env_id") != env_id:
        fail(f"env_id mismatch: file is for {meta.get('env_id')!r}, expected {env_id!r}")
    missing = [f"memory/{k}" for k in _MEMORY_FIELDS if f"memory/{k}" not in raw]
    if missing:
        fail(f"missing arrays {missing}")
    for k, dt in {**_MEMORY_DTYPES, **{f"transitions/{t}": d for t, d in
                                       (_TRANSITION_DTYPES.items()
                                        if keeps_transitions(stored) else ())}}.items():
        if f"memory/{k}" not in raw:
            fail(f"missing array 'memory/{k}'")
        if raw[f"memory/{k}"].dtype != dt:
            fail(f"array 'memory/{k}' has dtype {raw[f'memory/{k}'].dtype}, expected "
                 f"{np.dtype(dt)}")
    transitions = None
    if keeps_transitions(stored):
        transitions = StoredTransitions(**{k: raw[f"memory/transitions/{k}"]
                                           for k in _TRANSITION_DTYPES})
    np_memory = Memory(**{k: raw[f"memory/{k}"] for k in _MEMORY_FIELDS},
                       transitions=transitions)
    try:
        check_memory(stored, np_memory)
    except InvalidInputError as exc:
        fail(f"the stored memory is invalid: {exc}")

    # The stored arrays come back bit for bit; the neighbour index is rebuilt from them.
    memory = refresh_index(stored, jax.tree_util.tree_map(jnp.asarray, np_memory))
    extra = {k[len("extra/"):]: a for k, a in raw.items() if k.startswith("extra/")}
    return Checkpoint(stored, memory, stored_run, meta, extra)
