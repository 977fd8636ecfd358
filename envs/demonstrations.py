"""The demonstrations file format: recorded episodes for HEDGER's phase 1.

A :class:`Demonstrations` holds E episodes padded to T steps (leading axes (E, T)); step ``t`` of
episode ``e`` is the transition ``obs -> action -> (reward, next_obs)``. The field names are the
contract with the core library, which turns them into its
``Transition(obs, action, reward, next_obs, terminated, valid)``:

  obs        float32 (E, T, obs_dim)
  action     float32 (E, T, action_dim)   the action *value* (as passed to ``env.step``)
  reward     float32 (E, T)
  next_obs   float32 (E, T, obs_dim)
  terminated bool    (E, T)   a true terminal (no bootstrapping from ``next_obs``)
  truncated  bool    (E, T)   cut by a time limit (bootstrapping continues)
  valid      bool    (E, T)   real steps; valid steps are contiguous from t = 0 (a prefix)
  env_id     str              the functional env's ``name``, e.g. "mountain_car_discrete"
  source     str              who produced it ("simulated_person(seed=0)", "keyboard", ...)

Padding steps (``valid`` False) hold zeros and False flags. ``terminated``/``truncated`` may only be
set on the last valid step of an episode, and never both.

On disk: one ``.npz`` (``numpy.savez_compressed``) with those seven arrays plus ``metadata``, a
0-d unicode array holding JSON::

  {"schema": "hedger-demonstrations", "schema_version": 1, "env_id", "obs_dim",
   "action_dim", "n_episodes", "lengths", "source", "created", "sha256", ...user keys}

``sha256`` is a digest of the arrays (name, dtype, shape, bytes), so corruption that the zip
CRCs would not see is still caught. Files are written atomically (temporary file in the same
folder, then ``os.replace``) and loaded without pickle. Every problem found while loading
raises :class:`DemonstrationFileError` (a ``ValueError``) whose message names the file and the
problem.
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import tempfile
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

__all__ = ["Demonstrations", "DemonstrationFileError", "save_demonstrations",
           "load_demonstrations", "concatenate", "SCHEMA", "SCHEMA_VERSION", "ARRAY_FIELDS"]

SCHEMA = "hedger-demonstrations"
SCHEMA_VERSION = 1
ARRAY_FIELDS: Tuple[str, ...] = ("obs", "action", "reward", "next_obs", "terminated",
                                 "truncated", "valid")
_FLOAT_FIELDS = ("obs", "action", "reward", "next_obs")
_BOOL_FIELDS = ("terminated", "truncated", "valid")
_RESERVED_KEYS = ("schema", "schema_version", "env_id", "obs_dim", "action_dim", "n_episodes",
                  "lengths", "source", "created", "sha256")

PathLike = Union[str, os.PathLike]


class DemonstrationFileError(ValueError):
    """A demonstrations file (or in-memory ``Demonstrations``) is missing, corrupt or invalid."""


def _validate_arrays(arrays: Dict[str, np.ndarray], where: str) -> None:
    """Raise DemonstrationFileError naming the problem if the arrays do not form valid demos."""
    def fail(msg):
        raise DemonstrationFileError(f"{where}: {msg}")

    missing = [k for k in ARRAY_FIELDS if k not in arrays]
    if missing:
        fail(f"missing arrays {missing}")
    for k in _FLOAT_FIELDS:
        if arrays[k].dtype != np.float32:
            fail(f"array {k!r} has dtype {arrays[k].dtype}, expected float32")
    for k in _BOOL_FIELDS:
        if arrays[k].dtype != np.bool_:
            fail(f"array {k!r} has dtype {arrays[k].dtype}, expected bool")
    obs, action = arrays["obs"], arrays["action"]
    if obs.ndim != 3:
        fail(f"shape mismatch: obs must be (E, T, obs_dim), got shape {obs.shape}")
    if action.ndim != 3:
        fail(f"shape mismatch: action must be (E, T, action_dim), got shape {action.shape}")
    E, T, _ = obs.shape
    if E < 1 or T < 1:
        fail(f"no data: obs has shape {obs.shape} (need at least one episode and one step)")
    expected = {"obs": obs.shape, "action": (E, T, action.shape[2]), "next_obs": obs.shape,
                "reward": (E, T), "terminated": (E, T), "truncated": (E, T), "valid": (E, T)}
    for k, shape in expected.items():
        if arrays[k].shape != shape:
            fail(f"shape mismatch: {k!r} has shape {arrays[k].shape}, expected {shape} "
                 f"(from obs {obs.shape} and action {action.shape})")
    for k in _FLOAT_FIELDS:
        bad = ~np.isfinite(arrays[k])
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            fail(f"array {k!r} contains NaN or inf ({int(bad.sum())} entries, first at {idx})")
    valid = arrays["valid"]
    lengths = valid.sum(axis=1)
    prefix = np.arange(T)[None, :] < lengths[:, None]
    if not np.array_equal(valid, prefix):
        e = int(np.nonzero((valid != prefix).any(axis=1))[0][0])
        fail(f"valid mask is not a prefix: episode {e} has invalid steps before valid ones "
             "(valid steps must be contiguous from t=0)")
    if (lengths == 0).any():
        fail(f"episode {int(np.nonzero(lengths == 0)[0][0])} has no valid step")
    term, trunc = arrays["terminated"], arrays["truncated"]
    for name, flag in (("terminated", term), ("truncated", trunc)):
        if (flag & ~valid).any():
            fail(f"{name!r} is set on padding (invalid) steps")
    if (term & trunc).any():
        fail("a step is both terminated and truncated")
    last = prefix & ~(np.arange(T)[None, :] < (lengths - 1)[:, None])  # the last valid step
    ended = term | trunc
    if (ended & ~last).any():
        e = int(np.nonzero((ended & ~last).any(axis=1))[0][0])
        fail(f"episode {e} continues after a terminated/truncated step")
    for k in ARRAY_FIELDS:
        pad = arrays[k][~valid]
        if pad.size and np.any(pad != 0):
            fail(f"array {k!r} is not zero on padding (invalid) steps")


@dataclasses.dataclass(frozen=True, eq=False)
class Demonstrations:
    """Recorded episodes, padded (see the module docstring for shapes and meaning).

    Construction validates the arrays (raising :class:`DemonstrationFileError`)."""
    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    valid: np.ndarray
    env_id: str
    source: str = ""

    def __post_init__(self):
        for k in ARRAY_FIELDS:
            a = np.asarray(getattr(self, k))
            if k in _FLOAT_FIELDS and a.dtype != np.float32 and np.issubdtype(a.dtype, np.number):
                a = a.astype(np.float32)
            if k in _BOOL_FIELDS and a.dtype != np.bool_ and np.issubdtype(a.dtype, np.number):
                if not np.isin(a, (0, 1)).all():
                    raise DemonstrationFileError(f"Demonstrations: {k!r} is not boolean")
                a = a.astype(np.bool_)
            object.__setattr__(self, k, a)
        if not isinstance(self.env_id, str) or not self.env_id:
            raise DemonstrationFileError("Demonstrations: env_id must be a non-empty string")
        if not isinstance(self.source, str):
            raise DemonstrationFileError("Demonstrations: source must be a string")
        _validate_arrays(self.arrays(), "Demonstrations")

    # -- views --------------------------------------------------------------------------------
    def arrays(self) -> Dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ARRAY_FIELDS}

    @property
    def n_episodes(self) -> int:
        return int(self.obs.shape[0])

    @property
    def obs_dim(self) -> int:
        return int(self.obs.shape[2])

    @property
    def action_dim(self) -> int:
        return int(self.action.shape[2])

    @property
    def lengths(self) -> np.ndarray:
        """int64 (E,): number of valid steps of each episode."""
        return self.valid.sum(axis=1).astype(np.int64)

    @property
    def n_transitions(self) -> int:
        return int(self.valid.sum())

    def equals(self, other: "Demonstrations") -> bool:
        """Bit-exact equality of every array (dtype and shape included), env_id and source."""
        if not isinstance(other, Demonstrations):
            return False
        if (self.env_id, self.source) != (other.env_id, other.source):
            return False
        return all(a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
                   for a, b in ((getattr(self, k), getattr(other, k)) for k in ARRAY_FIELDS))

    def episode(self, e: int) -> Dict[str, np.ndarray]:
        """The valid steps of episode ``e``: dict of arrays with leading axis lengths[e]."""
        n = int(self.lengths[e])
        return {k: getattr(self, k)[e, :n] for k in ARRAY_FIELDS}

    def pad_to(self, T: int) -> "Demonstrations":
        """The same episodes padded (with zeros/False) to ``T >= self.obs.shape[1]`` steps."""
        T0 = self.obs.shape[1]
        if T < T0:
            raise ValueError(f"pad_to({T}) is shorter than the current {T0} steps")
        def pad(a):
            width = [(0, 0), (0, T - T0)] + [(0, 0)] * (a.ndim - 2)
            return np.pad(a, width)
        return Demonstrations(**{k: pad(getattr(self, k)) for k in ARRAY_FIELDS},
                              env_id=self.env_id, source=self.source)


def concatenate(demos_list: Sequence[Demonstrations], source: Optional[str] = None) -> Demonstrations:
    """Stack episodes of several ``Demonstrations`` (same env_id and dims), padding to the longest.

    ``source`` defaults to the common source, or the distinct sources joined with " + "."""
    demos_list = list(demos_list)
    if not demos_list:
        raise ValueError("concatenate: empty list")
    first = demos_list[0]
    for d in demos_list[1:]:
        if d.env_id != first.env_id:
            raise ValueError(f"concatenate: env_id {d.env_id!r} != {first.env_id!r}")
        if (d.obs_dim, d.action_dim) != (first.obs_dim, first.action_dim):
            raise ValueError(f"concatenate: dims (obs {d.obs_dim}, action {d.action_dim}) != "
                             f"(obs {first.obs_dim}, action {first.action_dim})")
    T = max(d.obs.shape[1] for d in demos_list)
    padded = [d.pad_to(T) for d in demos_list]
    if source is None:
        sources = list(dict.fromkeys(d.source for d in demos_list))
        source = sources[0] if len(sources) == 1 else " + ".join(sources)
    return Demonstrations(**{k: np.concatenate([getattr(d, k) for d in padded], axis=0)
                             for k in ARRAY_FIELDS},
                          env_id=first.env_id, source=source)


def _digest(arrays: Dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in ARRAY_FIELDS:
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_demonstrations(path: PathLike, demos: Demonstrations,
                        metadata: Optional[Dict[str, Any]] = None) -> str:
    """Write ``demos`` to ``path`` (one ``.npz``) atomically. Returns the path written.

    ``metadata``: extra JSON-serialisable keys stored alongside the schema keys (which they may
    not override)."""
    if not isinstance(demos, Demonstrations):
        raise TypeError(f"save_demonstrations: expected Demonstrations, got {type(demos).__name__}")
    extra = dict(metadata or {})
    clash = [k for k in extra if k in _RESERVED_KEYS]
    if clash:
        raise ValueError(f"save_demonstrations: metadata keys {clash} are reserved")
    arrays = demos.arrays()
    meta = dict(extra)
    meta.update({
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "env_id": demos.env_id,
        "obs_dim": demos.obs_dim, "action_dim": demos.action_dim,
        "n_episodes": demos.n_episodes, "lengths": [int(n) for n in demos.lengths],
        "source": demos.source,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "sha256": _digest(arrays),
    })
    text = json.dumps(meta, sort_keys=True)
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".demos-", suffix=".npz.tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, metadata=np.array(text), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _default_mode())      # mkstemp's 0600 -> what open() would give
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def _default_mode() -> int:
    """0o666 less the umask (read from /proc where Linux reports it, else by os.umask)."""
    try:
        with open("/proc/self/status") as f:
            umask = next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, ValueError, IndexError, StopIteration):
        umask = os.umask(0o022)
        os.umask(umask)
    return 0o666 & ~umask


def read_metadata(path: PathLike) -> Dict[str, Any]:
    """The JSON metadata of a demonstrations file (validated like ``load_demonstrations``)."""
    return load_demonstrations(path, return_metadata=True)[1]


def load_demonstrations(path: PathLike, env_id: Optional[str] = None,
                        obs_dim: Optional[int] = None, action_dim: Optional[int] = None,
                        return_metadata: bool = False):
    """Load and validate a demonstrations file.

    ``env_id``/``obs_dim``/``action_dim``: what the caller expects (checked when given).
    Returns ``Demonstrations`` (or ``(Demonstrations, metadata dict)`` with
    ``return_metadata=True``). Raises :class:`DemonstrationFileError` on any problem."""
    path = os.fspath(path)
    where = f"demonstrations file {path!r}"

    def fail(msg):
        raise DemonstrationFileError(f"{where}: {msg}")

    if not os.path.exists(path):
        fail("missing file (no such file)")
    if os.path.isdir(path):
        fail("is a directory, not a file")
    try:
        with np.load(path, allow_pickle=False) as z:
            names = set(z.files)
            arrays = {k: np.array(z[k]) for k in z.files}
    except DemonstrationFileError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError...
        fail(f"truncated or corrupt file ({type(exc).__name__}: {exc})")
    missing = [k for k in ("metadata",) + ARRAY_FIELDS if k not in names]
    if missing:
        fail(f"missing arrays {missing} (found {sorted(names)})")
    raw = arrays.pop("metadata")
    if raw.ndim != 0 or raw.dtype.kind != "U":
        fail("metadata is not a JSON string")
    try:
        meta = json.loads(str(raw))
    except json.JSONDecodeError as exc:
        fail(f"metadata is not valid JSON ({exc})")
    if not isinstance(meta, dict):
        fail("metadata is not a JSON object")
    if meta.get("schema") != SCHEMA:
        fail(f"wrong schema {meta.get('schema')!r}, expected {SCHEMA!r}")
    if meta.get("schema_version") != SCHEMA_VERSION:
        fail(f"unsupported schema_version {meta.get('schema_version')!r}, expected {SCHEMA_VERSION}")
    for k in ("env_id", "obs_dim", "action_dim", "n_episodes", "lengths", "source", "sha256"):
        if k not in meta:
            fail(f"metadata lacks {k!r}")
    _validate_arrays(arrays, where)
    if meta["sha256"] != _digest(arrays):
        fail("checksum mismatch: the arrays are corrupt (sha256 differs from the metadata)")
    E, _, od = arrays["obs"].shape
    ad = arrays["action"].shape[2]
    if meta["obs_dim"] != od:
        fail(f"metadata obs_dim {meta['obs_dim']} disagrees with obs arrays ({od})")
    if meta["action_dim"] != ad:
        fail(f"metadata action_dim {meta['action_dim']} disagrees with action array ({ad})")
    if meta["n_episodes"] != E:
        fail(f"metadata n_episodes {meta['n_episodes']} disagrees with arrays ({E})")
    mask_lengths = [int(n) for n in arrays["valid"].sum(axis=1)]
    if list(meta["lengths"]) != mask_lengths:
        fail(f"metadata lengths {meta['lengths']} disagree with the valid mask {mask_lengths}")
    if env_id is not None and meta["env_id"] != env_id:
        fail(f"env_id mismatch: file is for {meta['env_id']!r}, expected {env_id!r}")
    if obs_dim is not None and od != obs_dim:
        fail(f"obs_dim mismatch: file has {od}, expected {obs_dim}")
    if action_dim is not None and ad != action_dim:
        fail(f"action_dim mismatch: file has {ad}, expected {action_dim}")
    try:
        demos = Demonstrations(**arrays, env_id=meta["env_id"], source=meta["source"])
    except DemonstrationFileError as exc:
        fail(str(exc))
    return (demos, meta) if return_metadata else demos
