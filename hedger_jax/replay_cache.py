"""Neighbour sets found while acting, reused by the reverse replay of the same episode.

An episode's rollout reads one memory M (it writes nothing); the replay then starts from M
and, experience by experience (newest first), appends one point per step. At rollout step t
the greedy search found K for (s_t, a) for every greedy candidate a, and for the action it
took; the replay of experience t needs K for (s_t, a_t) and for (s_{t+1}, a) for every
candidate a -- the same queries, over M plus the points appended since.

Under ``full_policy="error"`` points are only appended (slots [size_M, size) are the new
ones, every older slot unchanged), so the exact K over the grown memory is the k nearest,
by (squared distance, slot), of K over M and the appended points within ``k_thresh``: a
point of M outside K over M is beaten by all k of it. ``merge_appended`` computes that from
the cached K and the appended slots alone (a window of at most ``width`` of them). Its result
is the search's, entry for entry in canonical order (tested), so the replay fits the same
neighbour sets with and without the cache.

A replay step searches all its queries instead when one set is missing (a random
exploratory step ran no greedy search; the episode's last state was never acted in), when
the memory is not M grown by at most ``width`` points, or when a query meets more than
``APPENDED_WIDTH`` appended points; and always under ``"overwrite_oldest"``.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from hedger_jax.config import HedgerConfig
from hedger_jax.kselect import true_positions
from hedger_jax.memory import Memory, Neighbours, squared_distances


class StepNeighbours(NamedTuple):
    """What one rollout step's greedy search found, for the replay (an episode's record has a
    leading time axis T on every field). Sets are slots of K in canonical order, then -1.

    size:           int32 () the memory's size when searched (the rollout's memory M).
    candidates:     int32 (n, k) K of (obs, a) for each of ``greedy_candidates`` a.
    chosen:         int32 (k,) K of (obs, action taken).
    has_candidates: bool () whether ``candidates`` was searched (not on a random step).
    has_chosen:     bool () whether ``chosen`` is K of the action taken.
    """

    size: jax.Array
    candidates: jax.Array
    chosen: jax.Array
    has_candidates: jax.Array
    has_chosen: jax.Array


def usable(config: HedgerConfig) -> bool:
    """Whether the replay can use cached sets for this config: only under
    ``full_policy="error"``, where the memory only grows by appends."""
    return config.full_policy == "error"


def missing(config: HedgerConfig, n_candidates: int, size: jax.Array) -> StepNeighbours:
    """The record of a step without sets (e.g. a random exploratory action): every set -1,
    nothing cached; ``size`` int32 () the memory's size."""
    k = config.max_neighbours
    none = jnp.full((k,), -1, jnp.int32)
    return StepNeighbours(jnp.asarray(size, jnp.int32), jnp.broadcast_to(none, (n_candidates, k)),
                          none, jnp.zeros((), bool), jnp.zeros((), bool))


def record_shapes(config: HedgerConfig, n_candidates: int) -> StepNeighbours:
    """The shapes and dtypes of one step's record (``jax.ShapeDtypeStruct`` leaves)."""
    k = config.max_neighbours
    i32, b = jnp.int32, jnp.bool_
    return StepNeighbours(jax.ShapeDtypeStruct((), i32),
                          jax.ShapeDtypeStruct((n_candidates, k), i32),
                          jax.ShapeDtypeStruct((k,), i32), jax.ShapeDtypeStruct((), b),
                          jax.ShapeDtypeStruct((), b))


def replay_sets(record: StepNeighbours, t: jax.Array, length: jax.Array):
    """The cached sets the replay of experience t (of an episode of ``length`` steps) uses:
    -> (sets int32 (1 + n, k): K of (s_t, a_t) then of (s_{t+1}, a) per candidate; their
    memory size (); which are cached, bool (1 + n,)). After a random exploratory action at t
    the first is not (no search chose it) while the candidates of t + 1 may be; at the
    episode's last step, or after a random action at t + 1, the candidates are not."""
    nxt = jnp.minimum(t + 1, record.size.shape[0] - 1)
    sets = jnp.concatenate([record.chosen[t][None], record.candidates[nxt]])
    candidates = (t + 1 < length) & record.has_candidates[nxt] \
        & (record.size[nxt] == record.size[t])
    n = record.candidates.shape[-2]
    ok = jnp.concatenate([record.has_chosen[t][None], jnp.broadcast_to(candidates, (n,))])
    return sets, record.size[t], ok


def appended_window(memory: Memory, size0: jax.Array, width: int):
    """Slots appended since the memory had ``size0`` points, as a window of ``width``:
    -> (points (d, width), slots int32 (width,), appended bool (width,), fits bool ()).
    ``fits``: every appended slot is in the window (size0 <= size <= size0 + width)."""
    n = memory.points.shape[-1]
    width = min(int(width), n)
    start = jnp.clip(size0, 0, n - width).astype(jnp.int32)
    pts = jax.lax.dynamic_slice_in_dim(memory.points, start, width, axis=1)
    slots = start + jnp.arange(width, dtype=jnp.int32)
    appended = (slots >= size0) & (slots < memory.size)
    fits = (size0 <= memory.size) & (memory.size - size0 <= width)
    return pts, slots, appended, fits


#: ``RunConfig(reuse_neighbours=None)`` reuses sets from this capacity on; below it searches
#: are cheap and the larger program's compile time does not pay.
REUSE_MIN_CAPACITY = 100_000

#: Most appended points within ``k_thresh`` of a query that the merge takes (more: the step
#: searches instead).
APPENDED_WIDTH = 16


def merge_appended(config: HedgerConfig, memory: Memory, z: jax.Array, cached: jax.Array,
                   window, d2w: jax.Array, near: jax.Array, k_thresh) -> Neighbours:
    """K of the scaled query z (d,) over the memory, from K over its first size0 slots and
    the points appended since, without a search.

    cached: int32 (k,) slots of K over size0 slots in canonical order, then -1. window:
    ``appended_window``'s result (which must ``fit``); d2w float32 (W,) its points' squared
    distances to z; near bool (W,) which of them are appended and within ``k_thresh`` (at
    most ``APPENDED_WIDTH`` are taken). Returns the same ``Neighbours`` as
    ``select_neighbours``, entry for entry."""
    _, slots, _, _ = window
    k = cached.shape[-1]
    w = d2w.shape[-1]
    r2 = jnp.float32(k_thresh) ** 2
    real = cached >= 0
    old = jnp.where(real, cached, 0)
    pos = true_positions(near, jnp.arange(min(APPENDED_WIDTH, w), dtype=jnp.int32))
    got = pos < w
    pos = jnp.minimum(pos, w - 1)
    # Distances by the search's formula (bit-identical, so ties resolve the same way).
    d2 = jnp.concatenate([jnp.where(real, squared_distances(memory.points[:, old], z), jnp.inf),
                          jnp.where(got, d2w[pos], jnp.inf)])
    d2 = jnp.where(d2 <= r2, d2, jnp.inf)
    slot = jnp.concatenate([old, slots[pos]])
    # Positions are in slot order (cached slots < size0 <= appended ones), so K -- the k
    # nearest, ties to the lower slot (the brute-force and grid order) -- is what remains
    # after dropping the farthest entry, ties to the higher position, while more than k
    # remain (at most ``APPENDED_WIDTH`` times); its first k entries in position order are
    # then in canonical order.
    p = jnp.arange(d2.shape[-1], dtype=jnp.int32)

    def drop(_, d2):
        far = jnp.max(jnp.where(d2 < jnp.inf, d2, -1.0))
        last = jnp.max(jnp.where(d2 == far, p, -1))
        over = jnp.sum((d2 < jnp.inf).astype(jnp.int32)) > k
        return jnp.where(over & (p == last), jnp.inf, d2)

    d2 = jax.lax.fori_loop(0, pos.shape[0], drop, d2)
    at = true_positions(d2 < jnp.inf, jnp.arange(k, dtype=jnp.int32))
    mask = at < d2.shape[-1]
    at = jnp.minimum(at, d2.shape[-1] - 1)
    return Neighbours(indices=slot[at].astype(jnp.int32), sqdist=jnp.where(mask, d2[at], 0.0),
                      mask=mask)


def cached_neighbours(config: HedgerConfig, memory: Memory, zs: jax.Array,
                      cached: Optional[tuple], search, k_thresh) -> Neighbours:
    """K of each query zs (q, d) within ``k_thresh`` -> ``Neighbours`` with leading axis q.

    cached: None, or (sets int32 (q, k), size0 int32 (), ok bool (q,) or (), width) --
    ``replay_sets``'s result and a static int, the most appended points looked at (e.g. the
    episode's length). When every set is usable they are merged (``merge_appended``); else
    ``search(zs)`` (-> ``Neighbours``, leading q) runs for all of them. Under ``vmap`` with
    members that disagree, every member searches. The result is the search's either way."""
    from hedger_jax.loops import batch_cond

    if cached is None or not usable(config):
        return search(zs)
    sets, size0, ok, width = cached
    window = appended_window(memory, size0, width)
    pts, _, appended, fits = window
    d2w = jax.vmap(lambda z: squared_distances(pts, z))(zs)                 # (q, W)
    near = appended & (d2w <= jnp.float32(k_thresh) ** 2)
    crowded = jnp.sum(near.astype(jnp.int32), axis=1) > APPENDED_WIDTH      # (q,)
    use = jnp.broadcast_to(jnp.asarray(ok, bool), zs.shape[:1]) & fits & ~crowded

    def merged(_):
        return jax.vmap(lambda z, c, d, m: merge_appended(config, memory, z, c, window, d, m,
                                                          k_thresh))(zs, sets, d2w, near)

    return batch_cond(jnp.all(use), merged, lambda _: search(zs), None, equal=True)

