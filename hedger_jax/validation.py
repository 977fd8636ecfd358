"""Input checks: on the host before values reach jitted code, and at trace time.

Inside jitted code nothing can raise; there the mechanism is the memory's error flags
(``FLAG_NONFINITE``: a NaN/inf value tried to enter the memory and was refused;
``FLAG_FULL``: a point was dropped because the memory was full), which the host raises with
``memory.memory_check``.

Host checks (``check_*``, ``action_indices``; used by the ``Hedger`` learner's methods and
``load_*``): NumPy on concrete values, never inside ``jit``. Each raises
:class:`InvalidInputError` (a ``ValueError``) naming the argument, the problem and the
offending value, and returns the value as a NumPy array of the canonical dtype (float32 for
observations, actions and rewards; bool for flags).

Trace-time checks (``expect*``; used by the functional API): shapes and dtypes only, on
arrays or tracers, inside ``jit`` and ``vmap`` too, before any value exists.
"""
from __future__ import annotations

from typing import Any, Optional, Tuple

import numpy as np

from hedger_jax.config import HedgerConfig
from hedger_jax.errors import InvalidInputError  # noqa: F401 (re-exported)
from hedger_jax.transition import Transition

__all__ = ["InvalidInputError", "check_array", "check_observations", "check_actions",
           "check_rewards", "check_transitions", "check_key", "check_memory",
           "action_indices", "config_differences"]

#: Relative slack on the action bounds and on membership in a discrete action set (the values
#: arrive as float32 while the config holds float64).
ACTION_RTOL = 1e-6


def _first_bad(bad: np.ndarray) -> Tuple[int, ...]:
    """Index of the first True entry of ``bad`` (() for a scalar)."""
    return tuple(int(i) for i in np.argwhere(bad)[0]) if bad.ndim else ()


def _fmt(x: Any) -> str:
    """A short text of a value for messages."""
    a = np.asarray(x)
    return repr(a.item()) if a.ndim == 0 else np.array2string(a, precision=8, threshold=12)


def check_array(name: str, x: Any, *, dtype: Any = np.float32, ndim: Optional[Tuple[int, ...]] = None,
                last_dim: Optional[int] = None, finite: bool = True) -> np.ndarray:
    """Convert ``x`` to a NumPy array of ``dtype`` after checking it.

    name: the argument's name, used in messages. dtype: float32 (numeric input required;
    booleans and strings refused) or bool (0/1 or bool input). ndim: allowed numbers of
    dimensions. last_dim: required size of the last axis. finite: refuse NaN/inf, and
    values that overflow float32. Raises :class:`InvalidInputError`.
    """
    try:
        a = np.asarray(x)
    except Exception as exc:  # ragged lists and the like
        raise InvalidInputError(f"{name}: cannot be converted to an array ({exc})") from None
    if a.dtype == object:
        raise InvalidInputError(f"{name}: not a numeric array (got dtype object: {x!r:.80})")
    if ndim is not None and a.ndim not in ndim:
        raise InvalidInputError(f"{name}: expected {' or '.join(map(str, ndim))} dimensions, "
                                f"got shape {a.shape}")
    if last_dim is not None and (a.ndim == 0 or a.shape[-1] != last_dim):
        raise InvalidInputError(f"{name}: expected last dimension {last_dim}, got shape {a.shape}")
    if np.dtype(dtype) == np.bool_:
        if a.dtype != np.bool_:
            if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
                raise InvalidInputError(f"{name}: expected booleans, got dtype {a.dtype}")
            if not np.isin(a, (0, 1)).all():
                bad = ~np.isin(a, (0, 1))
                raise InvalidInputError(f"{name}: expected booleans (0/1), got {_fmt(a[bad][0])} "
                                        f"at index {_first_bad(bad)}")
        return a.astype(np.bool_)
    if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.integer)
                                   or np.issubdtype(a.dtype, np.floating)):
        raise InvalidInputError(f"{name}: expected a real numeric array, got dtype {a.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        out = a.astype(dtype)
    if finite:
        bad = ~np.isfinite(out)
        if bad.any():
            idx = _first_bad(bad)
            what = "overflows float32" if np.isfinite(a[idx] if idx else a).all() else "is NaN or inf"
            raise InvalidInputError(f"{name}: {int(bad.sum())} value(s) {what}; first at index "
                                    f"{idx}: {_fmt(a[idx] if idx else a)}")
    return out


def check_observations(config: HedgerConfig, obs: Any, name: str = "observation"):
    """One observation (S,) or a batch (B, S) -> (float32 (B, S), batched: bool).

    Raises :class:`InvalidInputError` for a wrong shape, a non-numeric dtype, NaN or inf.
    """
    a = check_array(name, obs, ndim=(1, 2), last_dim=config.state_dim)
    return (a, True) if a.ndim == 2 else (a[None], False)


def check_actions(config: HedgerConfig, action: Any, name: str = "action") -> np.ndarray:
    """Action *values* (..., A) -> float32 (..., A), checked against the config's action space.

    Continuous: every entry within [action_low, action_high] (relative slack ``ACTION_RTOL``).
    Discrete: every action one of ``config.discrete_actions``. The last axis must be A, also
    when A == 1: pass shape (..., 1).
    """
    a = check_array(name, action, last_dim=config.action_dim)
    if config.is_discrete:
        action_indices(config, a, name=name)
        return a
    low = np.asarray(config.action_low)
    high = np.asarray(config.action_high)
    slack = ACTION_RTOL * np.maximum(1.0, np.maximum(np.abs(low), np.abs(high)))
    bad = (a < low - slack) | (a > high + slack)
    if bad.any():
        idx = _first_bad(bad)
        raise InvalidInputError(
            f"{name}: {int(bad.any(-1).sum())} action(s) outside the bounds [{config.action_low}, "
            f"{config.action_high}]; first at index {idx[:-1]}: {_fmt(a[idx[:-1]])}")
    return a


def action_indices(config: HedgerConfig, action: Any, name: str = "action") -> np.ndarray:
    """Discrete action values (..., A) -> int64 (...,) indices into ``config.discrete_actions``.

    Raises :class:`InvalidInputError` if an action is not in the set (relative slack
    ``ACTION_RTOL``) or the config is continuous.
    """
    if not config.is_discrete:
        raise InvalidInputError(f"{name}: the action space is continuous, it has no indices")
    a = np.asarray(action, np.float64)
    values = np.asarray(config.discrete_actions, np.float64)            # (n, A)
    tol = ACTION_RTOL * np.maximum(1.0, np.abs(values))
    match = np.all(np.abs(a[..., None, :] - values) <= tol, axis=-1)    # (..., n)
    ok = match.any(-1)
    if not np.all(ok):
        idx = _first_bad(~ok)
        raise InvalidInputError(
            f"{name}: {int((~ok).sum())} action(s) not in the discrete set "
            f"{config.discrete_actions}; first at index {idx}: {_fmt(a[idx])}")
    return np.argmax(match, axis=-1).astype(np.int64)


def check_rewards(rewards: Any, name: str = "reward") -> np.ndarray:
    """Rewards of any shape -> float32, refusing NaN/inf and non-numeric dtypes."""
    return check_array(name, rewards)


def check_transitions(config: HedgerConfig, transitions: Any, name: str = "transitions",
                      require_prefix: bool = True):
    """Check a ``Transition``-like batch with leading axes L (e.g. (E, T) or (T,)).

    Fields: obs (L, S), action (L, A), reward (L), next_obs (L, S), terminated (L), valid (L).
    Values on padding steps (valid False) are checked for finiteness only (actions are
    checked against the action space on valid steps). With ``require_prefix`` the valid
    steps of each episode (last leading axis is time) must be a prefix. Returns a
    ``hedger_jax.train.Transition`` of NumPy arrays of canonical dtypes.
    """
    try:
        fields = {k: getattr(transitions, k) for k in Transition._fields}
    except AttributeError as exc:
        raise InvalidInputError(f"{name}: not a Transition-like object ({exc})") from None
    obs = check_array(f"{name}.obs", fields["obs"], last_dim=config.state_dim)
    lead = obs.shape[:-1]
    if len(lead) < 1:
        raise InvalidInputError(f"{name}.obs: need a leading time axis, got shape {obs.shape}")
    nxt = check_array(f"{name}.next_obs", fields["next_obs"], last_dim=config.state_dim)
    act = check_array(f"{name}.action", fields["action"], last_dim=config.action_dim)
    rew = check_rewards(fields["reward"], f"{name}.reward")
    term = check_array(f"{name}.terminated", fields["terminated"], dtype=np.bool_)
    valid = check_array(f"{name}.valid", fields["valid"], dtype=np.bool_)
    for k, arr, shape in (("next_obs", nxt, lead + (config.state_dim,)),
                          ("action", act, lead + (config.action_dim,)),
                          ("reward", rew, lead), ("terminated", term, lead), ("valid", valid, lead)):
        if arr.shape != shape:
            raise InvalidInputError(f"{name}.{k}: expected shape {shape} (from obs {obs.shape}), "
                                    f"got {arr.shape}")
    if valid.any():
        check_actions(config, act[valid], f"{name}.action (valid steps)")
    if require_prefix:
        T = lead[-1]
        lengths = valid.sum(-1)
        prefix = np.arange(T) < lengths[..., None]
        if not np.array_equal(valid, prefix):
            bad = np.argwhere((valid != prefix).any(-1))
            raise InvalidInputError(f"{name}.valid: the valid steps of episode "
                                    f"{tuple(int(i) for i in bad[0])} are not a prefix")
    return Transition(obs, act, rew, nxt, term, valid)


def check_key(key: Any, name: str = "key") -> np.ndarray:
    """A raw JAX PRNG key uint32 (2,) (``jax.random.PRNGKey``), or a typed key -> its data as
    NumPy uint32 (2,). Raises :class:`InvalidInputError` otherwise."""
    import jax

    if hasattr(key, "dtype") and jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    a = np.asarray(key)
    if a.shape != (2,) or a.dtype != np.uint32:
        raise InvalidInputError(f"{name}: expected a raw PRNG key of shape (2,) and dtype uint32 "
                                f"(jax.random.PRNGKey(seed)), got shape {a.shape} dtype {a.dtype}")
    return a


def check_memory(config: HedgerConfig, memory: Any, name: str = "memory") -> None:
    """Check that a ``Memory`` (optionally with leading batch axes) fits ``config``.

    points float32 (..., d, capacity), values float32 (..., capacity), size/head/flags int32
    (...); 0 <= size <= capacity, 0 <= head < capacity, no NaN/inf among the valid values
    and points. Raises :class:`InvalidInputError` naming the field.
    """
    d, cap = config.dim, config.capacity
    try:
        points, values = np.asarray(memory.points), np.asarray(memory.values)
        size, head, flags = (np.asarray(memory.size), np.asarray(memory.head),
                             np.asarray(memory.flags))
    except AttributeError as exc:
        raise InvalidInputError(f"{name}: not a Memory ({exc})") from None
    batch = size.shape
    expect = {"points": (points, np.float32, batch + (d, cap)),
              "values": (values, np.float32, batch + (cap,)),
              "size": (size, np.int32, batch), "head": (head, np.int32, batch),
              "flags": (flags, np.int32, batch)}
    for k, (arr, dt, shape) in expect.items():
        if arr.dtype != dt:
            raise InvalidInputError(f"{name}.{k}: expected dtype {np.dtype(dt)}, got {arr.dtype}")
        if arr.shape != shape:
            raise InvalidInputError(f"{name}.{k}: expected shape {shape} for dim={d}, "
                                    f"capacity={cap}, got {arr.shape}")
    if np.any((size < 0) | (size > cap)):
        raise InvalidInputError(f"{name}.size: must be in [0, {cap}], got {_fmt(size)}")
    if np.any((head < 0) | (head >= cap)):
        raise InvalidInputError(f"{name}.head: must be in [0, {cap}), got {_fmt(head)}")
    used = np.arange(cap) < size[..., None]                               # (..., cap)
    if np.any(used & ~np.isfinite(values)):
        raise InvalidInputError(f"{name}.values: NaN/inf among the stored values")
    if np.any(used[..., None, :] & ~np.isfinite(points)):
        raise InvalidInputError(f"{name}.points: NaN/inf among the stored points")
    _check_transitions_kept(config, getattr(memory, "transitions", None), batch, name)


def _check_transitions_kept(config: HedgerConfig, stored: Any, batch: Tuple[int, ...],
                            name: str) -> None:
    """The memory keeps transitions exactly when the config asks (``backup_sweeps`` > 0),
    with the shapes of ``memory.StoredTransitions``."""
    if config.backup_sweeps == 0:
        if stored is not None:
            raise InvalidInputError(f"{name}.transitions: the config keeps none "
                                    "(backup_sweeps=0) but the memory has them")
        return
    if stored is None:
        raise InvalidInputError(f"{name}.transitions: the config keeps transitions "
                                f"(backup_sweeps={config.backup_sweeps}) but the memory has none")
    cap, S = config.capacity, config.state_dim
    shapes = {"reward": batch + (cap,), "next_obs": batch + (S, cap),
              "terminated": batch + (cap,), "present": batch + (cap,)}
    for k, shape in shapes.items():
        arr = np.asarray(getattr(stored, k))
        if arr.shape != shape:
            raise InvalidInputError(f"{name}.transitions.{k}: expected shape {shape}, "
                                    f"got {arr.shape}")


def config_differences(a: Any, b: Any) -> list:
    """Names of the dataclass fields whose values differ between two configs (same type)."""
    import dataclasses

    if type(a) is not type(b):
        return [f"<type: {type(a).__name__} vs {type(b).__name__}>"]
    return [f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)]


# ------------------------------------------------------------------------------------------
# Trace-time checks: shapes and dtypes are static, so they can be checked inside jit and vmap.
# ------------------------------------------------------------------------------------------
def expect(name: str, x: Any, shape: Tuple[int, ...], kind: str = "real") -> None:
    """Raise :class:`InvalidInputError` unless ``x`` (an array or tracer) has ``shape`` and a
    dtype of ``kind``: "real" (integer or floating, not bool), "bool" (bool or integer)."""
    import jax.numpy as jnp

    got = tuple(jnp.shape(x))
    if got != tuple(shape):
        raise InvalidInputError(f"{name}: expected shape {tuple(shape)}, got {got}")
    dtype = jnp.result_type(x)
    integer = jnp.issubdtype(dtype, jnp.integer)
    ok = (integer or jnp.issubdtype(dtype, jnp.floating)) if kind == "real" else \
        (dtype == jnp.bool_ or integer)
    if not ok or (kind == "real" and dtype == jnp.bool_):
        want = "a real number dtype" if kind == "real" else "bool"
        raise InvalidInputError(f"{name}: expected {want}, got dtype {dtype}")


def expect_key(name: str, key: Any) -> None:
    """Raise :class:`InvalidInputError` unless ``key`` is one PRNG key: a typed key of shape
    (), or raw uint32 (2,)."""
    import jax
    import jax.numpy as jnp

    dtype = jnp.result_type(key)
    if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        if jnp.shape(key) != ():
            raise InvalidInputError(f"{name}: expected one PRNG key, got shape {jnp.shape(key)}")
        return
    if tuple(jnp.shape(key)) != (2,) or dtype != jnp.uint32:
        raise InvalidInputError(f"{name}: expected a PRNG key (jax.random.PRNGKey(seed): uint32 "
                                f"(2,)), got shape {tuple(jnp.shape(key))} dtype {dtype}")


def expect_transition(config: HedgerConfig, t: Any, lead: Tuple[int, ...] = (),
                      name: str = "transition") -> None:
    """Raise :class:`InvalidInputError` unless ``t`` is a ``Transition`` with leading axes
    ``lead`` (default: those of its reward): obs/next_obs (S,), action (A,), reward,
    terminated and valid () after them."""
    import jax.numpy as jnp

    lead = tuple(lead) if lead else tuple(jnp.shape(t.reward))
    S, A = config.state_dim, config.action_dim
    for field, shape, kind in (("obs", (S,), "real"), ("action", (A,), "real"),
                               ("reward", (), "real"), ("next_obs", (S,), "real"),
                               ("terminated", (), "bool"), ("valid", (), "bool")):
        expect(f"{name}.{field}", getattr(t, field), lead + shape, kind)
