"""SB3-style queries of a memory: greedy or epsilon-greedy actions and Q-values for one
observation or a batch of any size, checked at the host boundary.

A batch is evaluated in padded buckets (powers of two from 8 to 256 rows, longer batches in
chunks of 256), so any batch size reuses a few compiled functions.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.agent import RunConfig, explore_action
from hedger_jax.config import HedgerConfig
from hedger_jax.cpu import jit as _jit
from hedger_jax.greedy import greedy_action
from hedger_jax.memory import Memory
from hedger_jax.prediction import predict
from hedger_jax.validation import (InvalidInputError, check_actions, check_key,
                                   check_observations)

__all__ = ["MIN_BUCKET", "MAX_BUCKET", "bucket", "bucketed", "config_index", "greedy_batch",
           "explore_batch", "q_batch", "act", "q_value"]

MIN_BUCKET, MAX_BUCKET = 8, 256


def bucket(n: int) -> int:
    """Padded batch size for n rows: the next power of two in [8, 256]."""
    b = MIN_BUCKET
    while b < n and b < MAX_BUCKET:
        b *= 2
    return b


def bucketed(fn: Callable, *arrays: np.ndarray) -> Tuple[np.ndarray, ...]:
    """Apply a jitted batch function to rows (B, ...) in padded buckets of ``bucket`` rows
    (chunks of at most 256). fn returns a tuple of arrays with leading axis = the bucket; the
    result is the tuple of NumPy arrays (B, ...)."""
    n = arrays[0].shape[0]
    outs = []
    for start in range(0, n, MAX_BUCKET):
        rows = [a[start:start + MAX_BUCKET] for a in arrays]
        m = rows[0].shape[0]
        b = bucket(m)
        padded = [np.concatenate([r, np.repeat(r[-1:], b - m, axis=0)]) if b > m else r
                  for r in rows]
        res = fn(*(jnp.asarray(p) for p in padded))
        outs.append([np.asarray(x)[:m] for x in res])
    return tuple(np.concatenate(parts) for parts in zip(*outs))


def config_index(config: HedgerConfig, actions: jax.Array) -> jax.Array:
    """Index into ``config.discrete_actions`` of action values (..., A) -> int32 (...)
    (0 for continuous actions)."""
    if not config.is_discrete:
        return jnp.zeros(actions.shape[:-1], jnp.int32)
    table = jnp.asarray(config.discrete_actions, jnp.float32)              # (n, A)
    d = jnp.sum(jnp.abs(actions[..., None, :] - table), axis=-1)           # (B, n)
    return jnp.argmin(d, axis=-1).astype(jnp.int32)


@functools.partial(_jit, static_argnames=("config",))
def greedy_batch(memory: Memory, obs: jax.Array, key: jax.Array, *, config: HedgerConfig):
    """Greedy actions for obs (B, S) with the *same* key for every row (so an observation's
    action does not depend on its batch position) -> (actions (B, A), values (B,), known (B,),
    config action index (B,))."""
    acts, vals, known = jax.vmap(lambda o: greedy_action(config, memory, o, key))(obs)
    return acts, vals, known, config_index(config, acts)


@functools.partial(_jit, static_argnames=("config", "run"))
def explore_batch(memory: Memory, obs: jax.Array, key: jax.Array, *, config: HedgerConfig,
                  run: RunConfig):
    """Epsilon-greedy actions for obs (B, S), one key per row -> (actions (B, A), index (B,))."""
    keys = jax.random.split(key, obs.shape[0])
    acts = jax.vmap(lambda o, k: explore_action(config, run, memory, o, k))(obs, keys)
    return acts, config_index(config, acts)


@functools.partial(_jit, static_argnames=("config",))
def q_batch(memory: Memory, obs: jax.Array, actions: jax.Array, *, config: HedgerConfig):
    """Q(s, a) for obs (B, S), actions (B, A) -> (values (B,), known (B,), n_neighbours (B,))."""
    return jax.vmap(lambda o, a: predict(config, memory, o, a))(obs, actions)


def act(memory: Memory, observation: Any, key: Any, next_key: Callable[[], jax.Array], *,
        config: HedgerConfig, run: RunConfig,
        deterministic: bool) -> Tuple[np.ndarray, np.ndarray, bool]:
    """Actions for an observation (S,) or a batch (B, S) -> (action values float32 (B, A),
    config action index int32 (B,), whether the input was a batch).

    deterministic: the greedy action, ties and "don't know" resolved with one key for every
    row (``key``, default ``PRNGKey(0)``), so the action is a function of the observation and
    the memory only. Else the epsilon-greedy policy, one key per row drawn from ``key``
    (default ``next_key()``, the learner's stream). Raises ``InvalidInputError``.
    """
    obs, batched = check_observations(config, observation)
    if key is not None:
        key = jnp.asarray(check_key(key))
    else:
        key = jax.random.PRNGKey(0) if deterministic else next_key()
    if deterministic:
        acts, idx = bucketed(lambda o: greedy_batch(memory, o, key, config=config)[::3], obs)
    else:
        chunk_keys = iter(jax.random.split(key, -(-obs.shape[0] // MAX_BUCKET)))
        acts, idx = bucketed(lambda o: explore_batch(memory, o, next(chunk_keys), config=config,
                                                     run=run), obs)
    return acts, idx, batched


def q_value(memory: Memory, observation: Any, action_value: Any, *, config: HedgerConfig):
    """Q(s, a) for an observation (S,) and action values (A,), or a batch (B, S) and (B, A)
    -> (value float32, known bool), scalars or (B,). Raises ``InvalidInputError``."""
    obs, batched = check_observations(config, observation)
    acts = check_actions(config, action_value, "action_value")
    want = (obs.shape[0], config.action_dim)
    if acts.shape != (want if batched else want[1:]):
        raise InvalidInputError(f"action_value: expected shape "
                                f"{want if batched else want[1:]}, got {acts.shape}")
    vals, known = bucketed(lambda o, a: q_batch(memory, o, a, config=config)[:2], obs,
                           acts.reshape(want))
    return (vals, known) if batched else (vals[0], known[0])
