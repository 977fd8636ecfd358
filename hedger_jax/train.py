"""Algorithm 2 (HEDGER training) for one experience, and reverse replay of an episode."""
from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.config import HedgerConfig
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.params import HedgerParams, constant, flag, resolve, to_fit_space
from hedger_jax.transition import Transition
from hedger_jax.validation import expect_transition
from hedger_jax.greedy import greedy_candidates, greedy_value_from
from hedger_jax.memory import (FLAG_NONFINITE, Memory, add_scaled, scale_inputs,
                               select_neighbours)
from hedger_jax.prediction import predict_from_neighbours, predict_scaled
from hedger_jax.replay_cache import cached_neighbours


class TrainInfo(NamedTuple):
    """What one training step saw (an episode's has a leading time axis T on every field).

    q: float32 () Q(s, a) before the update; q_next: float32 () max_a' Q(s', a') (0 at a
    terminal); q_new: float32 () the target stored with (s, a); known: bool ()
    whether Q(s, a) was known.
    """

    q: jax.Array
    q_next: jax.Array
    q_new: jax.Array
    known: jax.Array


def region_update(memory: Memory, indices: jax.Array, weights: jax.Array, mask: jax.Array,
                  target: jax.Array, apply: jax.Array = True) -> Memory:
    """Q_i <- Q_i + kappa_i (target - Q_i) for every masked neighbour i (Algorithm 2, l. 7-8).

    indices int32 (k,) slots (distinct where masked), weights float32 (k,) in [0, 1], mask
    bool (k,), target (), apply bool () -> memory. Each new value lies between the old one
    and the target. A non-finite target is refused (flag ``FLAG_NONFINITE``), so the memory
    never receives NaN.
    """
    finite = jnp.isfinite(target)
    use = mask & jnp.asarray(apply, bool) & finite
    old = memory.values[indices]
    # Convex form, clipped: in float32 ``old + k (target - old)`` can leave [old, target]
    # (old = 1, k = 1, target = 1e-8 gives 0), losing tiny gamma^n values.
    new = (1.0 - weights) * old + weights * target
    new = jnp.clip(new, jnp.minimum(old, target), jnp.maximum(old, target))
    # Unused entries (padding may repeat a slot) are dropped, so each slot is written once.
    capacity = memory.values.shape[-1]
    values = memory.values.at[jnp.where(use, indices, capacity)].set(new, mode="drop")
    flags = memory.flags | jnp.where(jnp.asarray(apply, bool) & ~finite, FLAG_NONFINITE, 0)
    return memory._replace(values=values, flags=flags.astype(jnp.int32))


def train_step(config: HedgerConfig, memory: Memory, transition: Transition, cached=None,
               params: Optional[HedgerParams] = None, q_floor=None):
    """Algorithm 2 for one experience: transition (fields as ``Transition``, no leading
    axis) -> (memory, ``TrainInfo``). Jittable, vmappable.

    q = Q(s, a) with its neighbour set K and weights kappa; q_next = max_a' Q(s', a')
    (0 if terminated); q_new = q + alpha (r + gamma q_next - q); (s, a) -> q_new is stored as
    a new point; with ``region_update`` every neighbour in K moves toward q_new by kappa_i.
    K is the set found before storing, and is updated whether or not q was known (the paper's
    Algorithm 2 updates "each point in K"). An invalid transition changes nothing; a valid
    one whose reward, observation, action or (non-terminal) next observation is NaN/inf
    stores nothing and sets ``FLAG_NONFINITE``.

    cached: optional neighbour sets found while acting (``replay_cache.replay_sets``'s result
    and the window width), used instead of searching where usable: the same sets.
    params: ``HedgerParams`` (alpha, gamma, ... traced), or None for the config's values.
    q_floor: optional float32 (), the least q_next may be (``replay_floor``: the reverse
    replay passes the value it has just stored for the next step; -inf for none).
    """
    t = transition
    expect_transition(config, t, ())
    params = with_data_bandwidth(config, memory, params)
    p = resolve(config, params)
    valid = jnp.asarray(t.valid, bool)
    z = scale_inputs(config, t.obs, t.action, params)
    # Q(s, a) and the first candidates Q(s', a') of max_a' as one vmapped batch: one copy of
    # the search and fit in the program, not two. Same values as predict + greedy_value.
    acts = greedy_candidates(config)                                          # (n, A)
    zs = jnp.concatenate([z[None], scale_inputs(
        config, jnp.broadcast_to(t.next_obs, (acts.shape[0],) + t.next_obs.shape), acts,
        params)])
    if cached is None:
        batch = jax.vmap(lambda zz: predict_scaled(config, memory, zz, params))(zs)
    else:
        nb = cached_neighbours(config, memory, zs, cached, jax.vmap(
            lambda zz: select_neighbours(config, memory, zz, params)), p.k_thresh)
        batch = jax.vmap(lambda zz, n: predict_from_neighbours(config, memory, zz, n, params))(
            zs, nb)
    pred = jax.tree_util.tree_map(lambda x: x[0], batch)
    q_next, _ = greedy_value_from(config, memory, t.next_obs, batch.value[1:], batch.known[1:],
                                  params)
    if q_floor is not None:
        q_next = jnp.maximum(q_next, q_floor)       # NaN stays NaN: still refused below
    q_next = jnp.where(jnp.asarray(t.terminated, bool), 0.0, q_next)
    reward = jnp.asarray(t.reward, jnp.float32)
    q_new = pred.value + p.alpha * (reward + p.gamma * q_next - pred.value)
    # A non-finite next observation would look like "don't know" (no neighbours) and give a
    # finite target: refuse it instead, so the memory flags it (FLAG_NONFINITE).
    next_ok = jnp.all(jnp.isfinite(t.next_obs)) | jnp.asarray(t.terminated, bool)
    q_new = jnp.where(next_ok, q_new, jnp.nan)
    if constant(p.region_update) is not False:   # a constant False: not in the program
        memory = region_update(memory, pred.indices, pred.weights, pred.mask,
                               to_fit_space(p, q_new), flag(p.region_update, valid, False))
    memory = add_scaled(config, memory, z, to_fit_space(p, q_new), valid,
                        (reward, t.next_obs, t.terminated))
    return memory, TrainInfo(pred.value, q_next, q_new, pred.known)


def replay_floor_on(p: HedgerParams) -> bool:
    """Whether the reverse replay carries a floor for max_a' Q(s', a') (``replay_floor`` not
    a constant False: without it the replay is the same program as the paper's)."""
    return constant(p.replay_floor) is not False


def next_floor(p: HedgerParams, info: TrainInfo, stored: jax.Array) -> jax.Array:
    """The floor for the step before this one in time, float32 (): the target q_new this
    step stored (``stored`` bool (): it was valid and finite), else -inf; -inf without
    ``replay_floor``."""
    ok = stored & jnp.isfinite(info.q_new) & jnp.asarray(p.replay_floor, bool)
    return jnp.where(ok, info.q_new, -jnp.inf).astype(jnp.float32)


def train_episode(config: HedgerConfig, memory: Memory, episode: Transition,
                  params: Optional[HedgerParams] = None):
    """Reverse replay (Lin 1992): ``train_step`` over an episode newest-first.

    episode: ``Transition`` with leading axis T (padded steps have valid=False and change
    nothing). params: ``HedgerParams``, or None for the config's values. Returns (memory,
    ``TrainInfo`` with leading axis T, in the episode's time order). With ``replay_floor``
    each step's max_a' Q(s', a') is at least the target the step after it stored.
    """

    expect_transition(config, episode, jnp.shape(episode.reward)[:1], "episode")
    params = with_data_bandwidth(config, memory, params)     # once, from the memory before

    if not replay_floor_on(resolve(config, params)):
        def body(mem, t):
            return train_step(config, mem, t, params=params)

        return jax.lax.scan(body, memory, episode, reverse=True)

    def floored(carry, t):
        mem, floor = carry
        mem, info = train_step(config, mem, t, params=params, q_floor=floor)
        return (mem, next_floor(resolve(config, params), info, jnp.asarray(t.valid, bool))), info

    (memory, _), info = jax.lax.scan(floored, (memory, jnp.float32(-jnp.inf)), episode,
                                     reverse=True)
    return memory, info
