"""The fixed-capacity, preallocated point memory and its neighbour selection.

``Memory`` is a pytree of preallocated arrays, so every operation on it is jittable and
vmappable (a batch of memories is one seed each). Points are stored *scaled* (see
``HedgerConfig.input_scale``) and feature-major, shape (d, capacity), so the distance pass
is d elementwise passes over contiguous rows.

Slots ``[0, size)`` hold valid points under ``full_policy="error"``; under
``"overwrite_oldest"`` the memory is a ring buffer (``head`` is the next slot to write) and
once full every slot is valid. Invalid slots are masked out of every neighbour search.

Errors inside jitted code cannot raise, so they are recorded in ``flags`` and raised on the
host by ``memory_check``:
  bit ``FLAG_FULL`` (1)       a point was dropped because the memory was full ("error" policy);
  bit ``FLAG_NONFINITE`` (2)  a NaN/inf value tried to enter the memory (it was not stored).
The stored data are never corrupted by either event.

With ``backup_sweeps`` > 0 each point also keeps the transition that stored it
(``StoredTransitions``: reward, next observation, terminated), so that ``hedger_jax.backup``
can back every point up again.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax import index as _grid
from hedger_jax.canonical import canonical_order
from hedger_jax.config import HedgerConfig
from hedger_jax.params import HedgerParams, resolve, to_fit_space
from hedger_jax.errors import MemoryFullError, NonFiniteValueError  # noqa: F401 (re-exported)
from hedger_jax.validation import expect

#: ``Memory.flags`` bit: a point was dropped because the memory was full ("error" policy).
FLAG_FULL = 1
#: ``Memory.flags`` bit: a NaN/inf value or point was refused.
FLAG_NONFINITE = 2
#: Brute force reads a memory of more than two blocks' capacity this many slots at a time,
#: up to its stored points only.
BRUTE_BLOCK = 2048


class StoredTransitions(NamedTuple):
    """The transition beside each stored point, for memory-wide backups (``hedger_jax.backup``).

    reward: float32 (capacity,); next_obs: float32 (S, capacity) raw (unscaled) next
    observations, feature-major like ``Memory.points``; terminated: bool (capacity,);
    present: bool (capacity,) whether the slot's point came from a transition (a point stored
    with ``add_points`` has none and is never backed up).
    """

    reward: jax.Array
    next_obs: jax.Array
    terminated: jax.Array
    present: jax.Array


class Memory(NamedTuple):
    """HEDGER's training points.

    Attributes:
      points: float32 (d, capacity) scaled inputs; column i is point i.
      values: float32 (capacity,) the Q-value stored with each point.
      size:   int32 () number of valid points (<= capacity).
      head:   int32 () next slot to write.
      flags:  int32 () error bits (``FLAG_FULL``, ``FLAG_NONFINITE``).
      index:  the neighbour index (``hedger_jax.index.GridIndex``) when the config uses the
              grid search (``HedgerConfig.index_kind``), else ``None`` (no leaves). Kept up
              to date by ``refresh_index``; searches through it are exact even when stale.
      transitions: ``StoredTransitions`` when the config keeps them (``backup_sweeps`` > 0),
              else ``None``.
    """

    points: jax.Array
    values: jax.Array
    size: jax.Array
    head: jax.Array
    flags: jax.Array
    index: Any = None
    transitions: Any = None


class Neighbours(NamedTuple):
    """The neighbour set K of one query (fixed size ``max_neighbours``, masked).

    indices: int32 (k,) slots in the memory (arbitrary where ``mask`` is False).
    sqdist:  float32 (k,) squared scaled distance to the query (0 where masked).
    mask:    bool (k,) True for real neighbours (within ``k_thresh``).
    """

    indices: jax.Array
    sqdist: jax.Array
    mask: jax.Array


def init_memory(config: HedgerConfig) -> Memory:
    """An empty memory: points (d, capacity), values (capacity,), size = head = flags = 0,
    and an empty grid index when the config uses one."""
    return Memory(
        points=jnp.zeros((config.dim, config.capacity), jnp.float32),
        values=jnp.zeros((config.capacity,), jnp.float32),
        size=jnp.zeros((), jnp.int32),
        head=jnp.zeros((), jnp.int32),
        flags=jnp.zeros((), jnp.int32),
        index=_grid.empty(config) if uses_index(config) else None,
        transitions=empty_transitions(config) if keeps_transitions(config) else None,
    )


def keeps_transitions(config: HedgerConfig) -> bool:
    """Whether the memory keeps each point's transition (memory-wide backups are on)."""
    return config.backup_sweeps > 0


def empty_transitions(config: HedgerConfig) -> StoredTransitions:
    """``StoredTransitions`` of zeros for the config's capacity (no slot present)."""
    cap = config.capacity
    return StoredTransitions(reward=jnp.zeros((cap,), jnp.float32),
                             next_obs=jnp.zeros((config.state_dim, cap), jnp.float32),
                             terminated=jnp.zeros((cap,), bool),
                             present=jnp.zeros((cap,), bool))


def uses_index(config: HedgerConfig) -> bool:
    """Whether the config's neighbour search uses the grid index (else brute force)."""
    return config.index_kind == "grid"


def scale_inputs(config: HedgerConfig, state: jax.Array, action: jax.Array,
                 params: Optional[HedgerParams] = None) -> jax.Array:
    """Scaled query z = (concat(state, action) - offset) * scale: state (..., S), action
    (..., A) -> float32 (..., d). params: ``HedgerParams`` (its input_offset / input_scale),
    or None for the config's."""
    p = resolve(config, params)
    x = jnp.concatenate([jnp.asarray(state, jnp.float32), jnp.asarray(action, jnp.float32)], -1)
    offset = jnp.asarray(p.input_offset, jnp.float32)
    scale = jnp.asarray(p.input_scale, jnp.float32)
    return (x - offset) * scale


def valid_mask(memory: Memory) -> jax.Array:
    """bool (capacity,): which slots hold a point."""
    capacity = memory.values.shape[-1]
    return jnp.arange(capacity) < memory.size


def squared_distances(points: jax.Array, z: jax.Array) -> jax.Array:
    """Squared distances from z (d,) to every column of points (d, N) -> (N,).

    The sum over the d rows is unrolled: on the CPU, d fused elementwise passes beat XLA's
    reduction over a short leading axis.
    """
    d2 = (points[0] - z[0]) ** 2
    for i in range(1, points.shape[0]):
        d2 = d2 + (points[i] - z[i]) ** 2
    return d2


def select_neighbours(config: HedgerConfig, memory: Memory, z: jax.Array,
                      params: Optional[HedgerParams] = None) -> Neighbours:
    """K: the stored points within ``k_thresh`` of the scaled query z (d,) -> ``Neighbours``
    (k = ``max_neighbours``) in canonical order (``hedger_jax.canonical``).

    params: ``HedgerParams`` (its k_thresh), or None for the config's. If more than
    ``max_neighbours`` points lie within ``k_thresh``, the nearest are kept (ties to the
    lower slot). Brute force: squared distances to every valid slot, then ``lax.top_k``, then
    the threshold. With the grid index (``hedger_jax.index``) the same set, entry for entry,
    comes from the cells around the query plus the points written since the last merge.
    Shapes are checked when traced (``InvalidInputError``).
    """
    expect("z", z, (config.dim,))
    capacity = memory.values.shape[-1]
    k_thresh = resolve(config, params).k_thresh
    if uses_index(config):
        index = memory.index
        if index is None:  # e.g. a memory built by hand: index everything now (exact)
            index = _grid.build(config, memory.points, memory.size)
        # Stop-gradient inputs: the search is piecewise constant (the fit recomputes the
        # distances), and its custom-vmap loops have no autodiff rules; so grad / jvp of a
        # prediction work through the grid index as through brute force.
        idx, d2_sel, mask = _grid.select(
            config, jax.lax.stop_gradient(memory.points), memory.head,
            jax.tree_util.tree_map(jax.lax.stop_gradient, index), jax.lax.stop_gradient(z),
            k_thresh)
        return _pad_neighbours(config, idx, d2_sel, mask)
    k = min(config.max_neighbours, capacity)
    if capacity > 2 * BRUTE_BLOCK:
        # Stop-gradient inputs, as above: the fit recomputes the distances, and reverse-mode
        # autodiff has no rule for the loop's traced trip count.
        d2_sel, idx = _nearest_in_blocks(jax.lax.stop_gradient(memory.points), memory.size,
                                         jax.lax.stop_gradient(z), k)
    else:
        d2 = jnp.where(valid_mask(memory), squared_distances(memory.points, z), jnp.inf)
        neg_d2, idx = jax.lax.top_k(-d2, k)
        d2_sel = -neg_d2
    mask = d2_sel <= jnp.float32(k_thresh) ** 2
    return _pad_neighbours(config, idx, d2_sel, mask)


def _nearest_in_blocks(points: jax.Array, size: jax.Array, z: jax.Array, k: int):
    """The k nearest stored points to z (d,) among slots [0, size) of points (d, capacity),
    read ``BRUTE_BLOCK`` slots at a time up to ``size`` only, so a search costs what the
    stored points cost, not the capacity's -> (squared distances (k,) ascending, inf past
    the stored points; slots int32 (k,)). The same set as one ``lax.top_k`` over every slot:
    the running best precede each block's slots, so ties go to the lower slot either way."""
    capacity = points.shape[-1]

    def block(b, best):
        best_d2, best_idx = best
        start = jnp.minimum(b * BRUTE_BLOCK, capacity - BRUTE_BLOCK)   # the last block clamped
        slot = start + jnp.arange(BRUTE_BLOCK, dtype=jnp.int32)
        d2 = squared_distances(jax.lax.dynamic_slice_in_dim(points, start, BRUTE_BLOCK, 1), z)
        # A clamped block re-reads slots the previous one had: each slot counts once.
        d2 = jnp.where((slot < size) & (slot >= b * BRUTE_BLOCK), d2, jnp.inf)
        neg_d2, j = jax.lax.top_k(-jnp.concatenate([best_d2, d2]), k)
        return -neg_d2, jnp.concatenate([best_idx, slot])[j]

    init = (jnp.full((k,), jnp.inf, jnp.float32), jnp.zeros((k,), jnp.int32))
    return jax.lax.fori_loop(0, (size + BRUTE_BLOCK - 1) // BRUTE_BLOCK, block, init)


def _pad_neighbours(config: HedgerConfig, idx, d2_sel, mask) -> Neighbours:
    """(idx (w,), d2 (w,), mask (w,)) with w <= max_neighbours -> ``Neighbours`` padded to
    ``max_neighbours`` in canonical order (real neighbours by slot, then padding), so every
    search method gives bit-identical fits (float32 sums depend on the order of terms)."""
    k = idx.shape[-1]
    if k < config.max_neighbours:  # tiny memory: pad to the static neighbour count
        pad = config.max_neighbours - k
        idx = jnp.concatenate([idx, jnp.zeros((pad,), idx.dtype)])
        d2_sel = jnp.concatenate([d2_sel, jnp.full((pad,), jnp.inf, d2_sel.dtype)])
        mask = jnp.concatenate([mask, jnp.zeros((pad,), bool)])
    idx, d2_sel, mask = canonical_order(idx, d2_sel, mask)
    return Neighbours(indices=idx.astype(jnp.int32), sqdist=jnp.where(mask, d2_sel, 0.0),
                      mask=mask)


def add_scaled(config: HedgerConfig, memory: Memory, z: jax.Array, value: jax.Array,
               write: jax.Array = True, transition: Optional[tuple] = None) -> Memory:
    """Store one scaled point z (d,) with value () if ``write`` (bool ()) -> memory.

    transition: (reward (), next_obs (S,), terminated ()) kept beside the point when the
    memory keeps transitions; None stores the point without one (never backed up).

    Under ``"error"`` a full memory drops the point and sets ``FLAG_FULL``; under
    ``"overwrite_oldest"`` the oldest slot is replaced. A non-finite value or point is
    refused and sets ``FLAG_NONFINITE``. Stored data are never corrupted; the grid index,
    if any, notes the write.
    """
    capacity = memory.values.shape[-1]
    value = jnp.asarray(value, jnp.float32)
    write = jnp.asarray(write, bool)
    finite = jnp.isfinite(value) & jnp.all(jnp.isfinite(z))
    full = memory.size >= capacity
    if config.full_policy == "error":
        room = ~full
    else:
        room = jnp.ones((), bool)
    do = write & finite & room
    slot = memory.head
    points = memory.points.at[:, slot].set(jnp.where(do, z, memory.points[:, slot]))
    values = memory.values.at[slot].set(jnp.where(do, value, memory.values[slot]))
    head = jnp.where(do, (memory.head + 1) % capacity, memory.head)
    size = jnp.where(do, jnp.minimum(memory.size + 1, capacity), memory.size)
    flags = memory.flags
    flags = flags | jnp.where(write & ~finite, FLAG_NONFINITE, 0)
    flags = flags | jnp.where(write & finite & ~room, FLAG_FULL, 0)
    index = memory.index
    if index is not None:
        index = _grid.note_write(config, index, z, slot, do)
    stored = memory.transitions
    if stored is not None:
        stored = _write_transition(stored, slot, do, transition)
    return Memory(points, values, size.astype(jnp.int32), head.astype(jnp.int32),
                  flags.astype(jnp.int32), index, stored)


def _write_transition(stored: StoredTransitions, slot: jax.Array, do: jax.Array,
                      transition: Optional[tuple]) -> StoredTransitions:
    """``stored`` with slot's entry replaced by ``transition`` (or marked absent) if ``do``."""
    if transition is None:
        return stored._replace(present=stored.present.at[slot].set(
            jnp.where(do, False, stored.present[slot])))
    reward, next_obs, terminated = transition
    put = lambda arr, new: arr.at[..., slot].set(jnp.where(do, new, arr[..., slot]))  # noqa
    return StoredTransitions(
        reward=put(stored.reward, jnp.asarray(reward, jnp.float32)),
        next_obs=put(stored.next_obs, jnp.asarray(next_obs, jnp.float32)),
        terminated=put(stored.terminated, jnp.asarray(terminated, bool)),
        present=put(stored.present, jnp.ones((), bool)))


def add_points(config: HedgerConfig, memory: Memory, states: jax.Array, actions: jax.Array,
               values: jax.Array, params: Optional[HedgerParams] = None) -> Memory:
    """Store n points in order: states (n, S), actions (n, A), values (n,) -> memory.

    Each as ``add_scaled`` (full memory and NaN/inf handled by the flags). params:
    ``HedgerParams`` (its input scaling), or None for the config's. Jittable; shapes are
    checked when traced (``InvalidInputError``)."""
    n = jnp.shape(states)[0] if jnp.ndim(states) == 2 else -1
    expect("states", states, (n, config.state_dim))
    expect("actions", actions, (n, config.action_dim))
    expect("values", values, (n,))
    zs = scale_inputs(config, states, actions, params)
    values = to_fit_space(resolve(config, params), jnp.asarray(values, jnp.float32))

    def body(mem, item):
        z, v = item
        return add_scaled(config, mem, z, v), None

    memory, _ = jax.lax.scan(body, memory, (zs, jnp.asarray(values, jnp.float32)))
    return memory


def refresh_index(config: HedgerConfig, memory: Memory, force: bool = False) -> Memory:
    """Bring the neighbour index (if the config uses one) up to date for fast searches.

    The agent calls it after every episode (phase 1's included), so before every evaluation.
    With the brute-force search there is no index and this is the identity. With the grid
    index, the points written since the last merge (searched through a sorted list of recent
    writes, and beyond ``index_recent`` by brute force) are merged into the grid tables --
    O(capacity + cells) -- once three quarters of the recent list are used
    (``index.merge_threshold``), or always with ``force`` (static bool); a memory without an
    index is indexed from scratch by a sort. The search is exact at any time: refreshing only
    keeps it fast.
    """
    if not uses_index(config):
        return memory
    if memory.index is None:
        return memory._replace(index=_build_jit(config, memory.points, memory.size))
    return memory._replace(index=_refresh_jit(config, memory.index, memory.points,
                                              memory.head, memory.size, force=bool(force)))


# Jitted, so an eager call (a loaded checkpoint, a hand-built memory) runs one compiled
# program rather than op by op; under a trace they are inlined.
_build_jit = jax.jit(lambda config, points, size: _grid.build(config, points, size),
                     static_argnums=0)
_refresh_jit = jax.jit(lambda config, index, points, head, size, force:
                       _grid.refresh(config, index, points, head, size, force=force),
                       static_argnums=(0, 5))


def memory_check(memory: Memory) -> Memory:
    """Host-side: raise ``NonFiniteValueError`` or ``MemoryFullError`` if the memory's error
    flags are set; else return the memory unchanged. For a batch of memories (leading axes)
    any flagged member raises.
    """
    flags = np.asarray(jax.device_get(memory.flags))
    if np.any(flags & FLAG_NONFINITE):
        raise NonFiniteValueError(
            "a NaN/inf value tried to enter the HEDGER memory and was refused "
            f"(members flagged: {np.flatnonzero(np.atleast_1d(flags) & FLAG_NONFINITE).tolist()})")
    if np.any(flags & FLAG_FULL):
        raise MemoryFullError(
            "the HEDGER memory is full (capacity "
            f"{memory.values.shape[-1]}) and points were dropped; raise `capacity` or use "
            "full_policy='overwrite_oldest'")
    return memory


def stored_points(config: HedgerConfig, memory: Memory, params: Optional[HedgerParams] = None):
    """Host-side view of one memory's first ``size`` slots: (inputs float64 (n, d) unscaled,
    values float32 (n,)). params: ``HedgerParams`` (its input scaling), or None for the
    config's."""
    p = resolve(config, params)
    size = int(memory.size)
    z = np.asarray(memory.points)[:, :size].T.astype(np.float64)
    x = z / np.asarray(p.input_scale, np.float64) + np.asarray(p.input_offset, np.float64)
    return x, np.asarray(memory.values)[:size]
