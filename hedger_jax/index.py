"""An exact, jittable neighbour index for the fixed-capacity memory: a uniform grid (cell list).

Selected with ``HedgerConfig(neighbour_index="grid")`` (``"auto"`` picks it for large
capacities). It returns exactly the neighbour set of the brute-force search
(``memory.select_neighbours`` with ``neighbour_index="brute"``): the same slots within
``k_thresh`` (capped at the ``max_neighbours`` nearest), with bit-identical float32 squared
distances (same formula, same order of operations); only the order among exactly equal
distances may differ.

Design (all shapes static, so everything jits and vmaps):

* **Geometry (static, from the config).** Every dimension i of the *scaled* inputs gets a
  range [lo_i, hi_i] (``index_bounds``; default: [0, 1] for state dimensions -- the scaling of
  ``HedgerConfig.for_env`` -- and the scaled action bounds / discrete action set for action
  dimensions) cut into G_i cells of side s_i >= k_thresh (1 + 1e-3) -- about a quarter of
  that along one "contiguous" state dimension, see ``Geometry`` -- A cell coordinate is
  ``clip(floor((z_i - lo_i) / s_i), 0, G_i - 1)``. Clipping is monotone and non-expansive,
  so two points within k_thresh of each other always land in the same or adjacent cells --
  points outside the range are *clamped into the border cells, never dropped*; they only
  make those cells fuller (slower, still exact). The product of the G_i is capped
  (``_MAX_CELLS``) by coarsening the cells (s_i only grows, so exactness is unaffected).
  The cell key is the row-major linear index, the contiguous dimension fastest.
* **Build (``build``; ``memory.refresh_index``).** Slots sorted by cell key (invalid slots get
  a sentinel key and sort last), a sorted copy of the points, and ``starts`` (T + 1,): the
  first sorted position of every cell (histogram + cumulative sum). O(N log N) sort + O(T).
* **Query (``select``).** The cells around the query cell form 3^(d-1) contiguous key
  ranges (the cells along the contiguous dimension are adjacent keys), i.e. at most 3^(d-1)
  segments of the sorted arrays. One more segment holds the slots written since the last
  build (``n_new`` writes starting at slot ``h0``, ring-buffer order), scanned by brute force.
  The concatenation of the segments (M candidates) is scanned in chunks of ``index_chunk``
  by a ``lax.while_loop`` (about ceil(M / chunk) trips, so any cell occupancy is exact -- a
  full or overflowing cell just costs more trips) keeping a running top-k of the squared
  distances (``lax.top_k`` over k + chunk values per trip: it dominates the cost on CPU).
  The first trip is peeled with a smaller chunk (``_FIRST_CHUNK``), so a sparse neighbourhood
  costs one small top_k.
  With ``full_policy="overwrite_oldest"`` an indexed slot overwritten since the build is
  masked out of the index segments (it appears, with its new point, in the new-writes
  segment), so no slot is ever counted twice.
* **Staleness.** The new-writes segment grows with every write, so an index that is never
  rebuilt degrades gracefully to a (chunked) brute-force scan and stays exact. ``n_new``
  saturates at the capacity: then every slot was rewritten, every index entry is masked and
  the new-writes segment is the whole ring, each slot once.
"""
from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

#: Largest number of grid cells (size of the ``starts`` table); see ``max_cells``.
_MAX_CELLS = 1 << 22
#: Relative margin of the cell side over k_thresh (float32 round-off of cell coordinates).
_SIDE_MARGIN = 1e-3
#: Candidates read by the first (peeled) trip of the scan; later trips read ``index_chunk``.
_FIRST_CHUNK = 64
#: Subdivision of the contiguous dimension (cells of side k_thresh / _FINE along it).
_FINE = 4
#: Points merged into the index per O(N) pass of ``refresh``.
_MERGE_WINDOW = 1024
#: Largest number of cells along one dimension (keeps the coordinate round-off << margin).
_MAX_PER_DIM = 4096


class GridIndex(NamedTuple):
    """Pytree of one memory's grid index (N = capacity, d = dim, T = number of cells).

    order:   int32 (N,) memory slots sorted by cell key (positions >= ``starts[T]`` unused).
    skeys:   int32 (N,) their cell keys (T at unused positions).
    spoints: float32 (d, N) the points in sorted order (``points[:, order]``).
    starts:  int32 (T + 1,) first sorted position of each cell; ``starts[T]`` = indexed count.
    n_new:   int32 () points written since they were indexed (saturating at N): the slots
             ``(head - n_new + j) % N``, j < n_new, oldest first, are not (or not currently)
             in the index.
    """

    order: jax.Array
    skeys: jax.Array
    spoints: jax.Array
    starts: jax.Array
    n_new: jax.Array


class Geometry(NamedTuple):
    """Static grid geometry (Python floats / ints).

    ``contig`` is the dimension with stride 1: cells along it are adjacent keys, so the
    cells c - ``reach`` .. c + ``reach`` along it are one contiguous range of the sorted
    arrays. It is cut finer (side about k_thresh / ``_FINE``), which shrinks the scanned
    region along it from 3 to about 2 + 2 / _FINE cells of side k_thresh at no extra cost.
    """

    lo: Tuple[float, ...]
    inv_side: Tuple[float, ...]
    cells: Tuple[int, ...]
    strides: Tuple[int, ...]
    n_cells: int
    contig: int
    reach: int

def max_cells(capacity: int) -> int:
    """Cell budget: about 4 cells per slot (a refresh costs O(capacity + cells)), at least
    4096 and at most ``_MAX_CELLS``."""
    return int(min(_MAX_CELLS, max(1 << 12, 4 * capacity)))


def default_bounds(config) -> Tuple[Tuple[float, float], ...]:
    """Scaled range [lo, hi] of each input dimension that the grid covers.

    ``config.index_bounds`` when set; otherwise [0, 1] for state dimensions and the scaled
    action bounds (continuous) or the scaled discrete action set for action dimensions.
    Anything outside is clamped into the border cells (exact, only slower).
    """
    if getattr(config, "index_bounds", None) is not None:
        return tuple((float(a), float(b)) for a, b in config.index_bounds)
    S = config.state_dim
    bounds = [(0.0, 1.0)] * S
    off = config.input_offset[S:]
    scale = config.input_scale[S:]
    for j in range(config.action_dim):
        if config.is_discrete:
            vals = [a[j] for a in config.discrete_actions]
            lo, hi = min(vals), max(vals)
        else:
            lo, hi = config.action_low[j], config.action_high[j]
        a, b = (lo - off[j]) * scale[j], (hi - off[j]) * scale[j]
        bounds.append((min(a, b), max(a, b)))
    return tuple(bounds)


@functools.lru_cache(maxsize=None)
def geometry(config) -> Geometry:
    """The static grid of a config (cached: configs are hashable)."""
    bounds = default_bounds(config)
    d = len(bounds)
    side0 = config.k_thresh * (1.0 + _SIDE_MARGIN)
    widths = [max(hi - lo, 0.0) for lo, hi in bounds]
    # The contiguous dimension: the widest state dimension (the last one on ties).
    contig = max(range(config.state_dim), key=lambda i: (widths[i], i))
    target = [side0 / _FINE if i == contig else side0 for i in range(d)]
    cells = [max(1, min(_MAX_PER_DIM, int(math.ceil(w / t)))) for w, t in zip(widths, target)]
    limit = max_cells(config.capacity)
    while int(np.prod(cells, dtype=np.int64)) > limit:
        i = int(np.argmax(cells))
        cells[i] = max(1, cells[i] // 2)
    sides = [max(t, w / c) for t, w, c in zip(target, widths, cells)]
    # Points within k_thresh differ by at most `reach` cells along contig (side0 > k_thresh).
    reach = max(1, int(math.ceil(side0 / sides[contig] - 1e-9)))
    strides = [0] * d
    stride = 1
    for i in [contig] + [i for i in range(d - 1, -1, -1) if i != contig]:
        strides[i] = stride
        stride *= cells[i]
    return Geometry(lo=tuple(lo for lo, _ in bounds), inv_side=tuple(1.0 / s for s in sides),
                    cells=tuple(cells), strides=tuple(strides),
                    n_cells=int(np.prod(cells, dtype=np.int64)), contig=contig, reach=reach)


def cell_coords(geo: Geometry, z: jax.Array) -> jax.Array:
    """Integer cell coordinates of points z (d, ...) -> int32 (d, ...), clamped to the grid."""
    lo = jnp.asarray(geo.lo, jnp.float32).reshape((-1,) + (1,) * (z.ndim - 1))
    inv = jnp.asarray(geo.inv_side, jnp.float32).reshape(lo.shape)
    top = jnp.asarray(geo.cells, jnp.float32).reshape(lo.shape) - 1.0
    u = jnp.clip((z - lo) * inv, 0.0, top)   # clip before the cast: huge values are safe
    u = jnp.where(jnp.isnan(u), 0.0, u)
    return jnp.floor(u).astype(jnp.int32)


def cell_keys(geo: Geometry, z: jax.Array) -> jax.Array:
    """Row-major cell key of points z (d, ...) -> int32 (...)."""
    c = cell_coords(geo, z)
    key = c[0] * geo.strides[0]
    for i in range(1, c.shape[0]):
        key = key + c[i] * geo.strides[i]
    return key


def empty(config) -> GridIndex:
    """The index of an empty memory (every cell empty)."""
    geo = geometry(config)
    n = config.capacity
    return GridIndex(order=jnp.arange(n, dtype=jnp.int32),
                     skeys=jnp.full((n,), geo.n_cells, jnp.int32),
                     spoints=jnp.zeros((config.dim, n), jnp.float32),
                     starts=jnp.zeros((geo.n_cells + 1,), jnp.int32),
                     n_new=jnp.zeros((), jnp.int32))


def _excl_cumsum(x: jax.Array) -> jax.Array:
    c = jnp.cumsum(x)
    return (c - x).astype(jnp.int32)


def build(config, points: jax.Array, size: jax.Array) -> GridIndex:
    """Index the valid slots [0, size) of points (d, N) from scratch (a full sort).

    O(N log N) with a slow multi-operand sort on CPU (0.06 s at N = 1e5, 0.6 s at 1e6): used
    only for a memory without an index (e.g. built by hand or loaded); ``refresh`` merges
    new points into an existing index in O(N + T) instead.
    """
    geo = geometry(config)
    n = points.shape[-1]
    valid = jnp.arange(n) < size
    keys = jnp.where(valid, cell_keys(geo, points), geo.n_cells)
    skeys, order = jax.lax.sort((keys, jnp.arange(n, dtype=jnp.int32)), num_keys=1,
                                is_stable=True)
    counts = jnp.zeros((geo.n_cells + 1,), jnp.int32).at[skeys].add(1, mode="drop")
    return GridIndex(order=order, skeys=skeys, spoints=points[:, order],
                     starts=_excl_cumsum(counts), n_new=jnp.zeros((), jnp.int32))


def note_write(index: GridIndex, did_write: jax.Array, capacity: int) -> GridIndex:
    """Count one write (a bool ()) since the last refresh (saturating at the capacity)."""
    n_new = jnp.where(did_write, jnp.minimum(index.n_new + 1, capacity), index.n_new)
    return index._replace(n_new=n_new.astype(jnp.int32))


def _merge(config, index: GridIndex, points: jax.Array, head: jax.Array) -> GridIndex:
    """Merge the oldest min(n_new, W) unindexed slots into the index, W = ``_MERGE_WINDOW``.

    O(N + T + W log W), no sort of the N entries: kept entries move by the number of removed
    entries before them and of merged entries with a smaller key (a stable counting merge);
    entries of the merged slots that were indexed before (ring-buffer overwrites) are removed.
    """
    geo = geometry(config)
    n = points.shape[-1]
    T = geo.n_cells
    w = min(_MERGE_WINDOW, n)
    m = jnp.minimum(index.n_new, w)
    h0 = (head - index.n_new) % n
    j = jnp.arange(w, dtype=jnp.int32)
    active = j < m
    wslots = (h0 + j) % n
    wpts = points[:, wslots]
    wkeys = jnp.where(active, cell_keys(geo, wpts), T)
    new_counts = jnp.zeros((T + 1,), jnp.int32).at[wkeys].add(1)           # [T] = inactive
    new_before = _excl_cumsum(new_counts)                                    # (T + 1,)
    pos = jnp.arange(n, dtype=jnp.int32)
    if config.full_policy == "overwrite_oldest":
        # Old entries: drop unused positions and slots that are being re-merged.
        keep = (pos < index.starts[T]) & (((index.order - h0) % n) >= m)
        keep_i = keep.astype(jnp.int32)
        pos_old = jnp.where(keep, _excl_cumsum(keep_i) + new_before[index.skeys], n)
        kept_counts = jnp.zeros((T + 1,), jnp.int32).at[index.skeys].add(keep_i)
        sorted_old = False
    else:
        # No removals ("error" policy: the merged slots were empty). Every entry, used or not
        # (unused ones have key T and stay at the end), moves up by the number of merged
        # entries with a smaller key: strictly increasing positions, no cumsum over N.
        pos_old = pos + new_before[index.skeys]
        kept_counts = jnp.concatenate([jnp.diff(index.starts), jnp.zeros((1,), jnp.int32)])
        sorted_old = True
    starts = _excl_cumsum(kept_counts + new_counts)
    # New entries go after the kept ones of their cell, in window order.
    skw, perm = jax.lax.sort((wkeys, j), num_keys=1, is_stable=True)
    first = jnp.searchsorted(skw, skw, side="left").astype(jnp.int32)
    pos_new = starts[skw] + kept_counts[skw] + (j - first)
    pos_new = jnp.where(skw < T, pos_new, n + j)                  # inactive: distinct, dropped
    put_old = functools.partial(_put, sorted_=sorted_old)
    order = put_old(jnp.zeros((n,), jnp.int32), pos_old, index.order)
    order = _put(order, pos_new, wslots[perm], sorted_=True)
    skeys = put_old(jnp.full((n,), T, jnp.int32), pos_old, index.skeys)
    skeys = _put(skeys, pos_new, skw, sorted_=True)
    spoints = put_old(jnp.zeros_like(index.spoints), pos_old, index.spoints)
    spoints = _put(spoints, pos_new, wpts[:, perm], sorted_=True)
    return GridIndex(order=order, skeys=skeys, spoints=spoints, starts=starts,
                     n_new=(index.n_new - m).astype(jnp.int32))


def _put(dst: jax.Array, pos: jax.Array, src: jax.Array, sorted_: bool) -> jax.Array:
    """dst[..., pos] = src, out-of-range positions dropped (sorted_: pos strictly increasing)."""
    return dst.at[..., pos].set(src, mode="drop", indices_are_sorted=sorted_,
                                unique_indices=sorted_)


def refresh(config, index: GridIndex, points: jax.Array, head: jax.Array) -> GridIndex:
    """Bring the index up to date: merge every point written since (W at a time).

    A ``lax.while_loop`` of ceil(n_new / W) merges (one merge after a typical episode).
    """
    return jax.lax.while_loop(lambda ix: ix.n_new > 0,
                              lambda ix: _merge(config, ix, points, head), index)


def _sqdist(points: jax.Array, z: jax.Array) -> jax.Array:
    """Same formula and order as ``memory.squared_distances`` (bit-identical results)."""
    d2 = (points[0] - z[0]) ** 2
    for i in range(1, points.shape[0]):
        d2 = d2 + (points[i] - z[i]) ** 2
    return d2


@functools.lru_cache(maxsize=None)
def _row_offsets(d: int) -> np.ndarray:
    """{-1, 0, 1}^(d-1) as an int32 array (3^(d-1), d-1)."""
    return np.array(list(itertools.product((-1, 0, 1), repeat=d - 1)),
                    dtype=np.int32).reshape(3 ** (d - 1), d - 1)


def segments(config, index: GridIndex, z: jax.Array):
    """The candidate segments of query z (d,): (starts (R,), lengths (R + 1,)).

    Segments 0..R-1 are key ranges of the sorted arrays (2 reach + 1 adjacent cells along the
    contiguous dimension for each of the 3^(d-1) combinations of the other coordinates; rows
    off the grid have length 0); segment R is the n_new slots written since the last refresh.
    """
    geo = geometry(config)
    d = config.dim
    c = cell_coords(geo, z)                                          # (d,)
    others = [i for i in range(d) if i != geo.contig]
    offs = jnp.asarray(_row_offsets(d))                              # (R, d-1)
    row_c = c[jnp.asarray(others, jnp.int32)][None, :] + offs if others else offs
    cells = jnp.asarray([geo.cells[i] for i in others], jnp.int32)
    strides = jnp.asarray([geo.strides[i] for i in others], jnp.int32)
    row_ok = jnp.all((row_c >= 0) & (row_c < cells[None, :]), axis=1)
    base = jnp.sum(jnp.clip(row_c, 0, cells[None, :] - 1) * strides[None, :], axis=1)
    cc = c[geo.contig]
    last_lo = jnp.maximum(cc - geo.reach, 0)
    last_hi = jnp.minimum(cc + geo.reach, geo.cells[geo.contig] - 1)
    seg_start = index.starts[base + last_lo]
    seg_end = index.starts[base + last_hi + 1]
    seg_len = jnp.where(row_ok, seg_end - seg_start, 0)
    lengths = jnp.concatenate([seg_len, index.n_new[None]]).astype(jnp.int32)
    return seg_start.astype(jnp.int32), lengths


def select(config, points: jax.Array, head: jax.Array, index: GridIndex, z: jax.Array):
    """Exact K of query z (d,) -> (indices int32 (k,), sqdist float32 (k,), mask bool (k,)).

    Same contract as the brute-force search (k = min(max_neighbours, capacity), ascending
    squared distances, +inf where there is no candidate; the caller pads and masks).
    """
    n = points.shape[-1]
    k = min(config.max_neighbours, n)
    chunk = int(config.index_chunk)
    r2 = jnp.float32(config.k_thresh) ** 2
    ring = config.full_policy == "overwrite_oldest"
    h0 = (head - index.n_new) % n
    seg_start, lengths = segments(config, index, z)
    n_seg = seg_start.shape[0]
    ends = jnp.cumsum(lengths)
    begins = ends - lengths                                          # (R + 1,)
    total = ends[-1]
    seg_start_ext = jnp.concatenate([seg_start, jnp.zeros((1,), jnp.int32)])

    def trip(p0, best_d2, best_idx, width):
        p = p0 + jnp.arange(width, dtype=jnp.int32)                  # (width,)
        seg = jnp.sum(p[:, None] >= begins[None, 1:], axis=1)        # in [0, R]
        off = p - begins[seg]
        is_new = seg == n_seg
        pos = jnp.clip(seg_start_ext[seg] + off, 0, n - 1)
        new_slot = (h0 + off) % n
        slot = jnp.where(is_new, new_slot, index.order[pos])
        pts = jnp.where(is_new[None, :], points[:, new_slot], index.spoints[:, pos])
        d2 = _sqdist(pts, z)
        ok = (p < total) & (d2 <= r2)
        if ring:  # an indexed slot rewritten since the build lives in the new-writes segment
            stale = ((slot - h0) % n) < index.n_new
            ok = ok & (is_new | ~stale)
        neg, which = jax.lax.top_k(-jnp.concatenate([best_d2, jnp.where(ok, d2, jnp.inf)]), k)
        return p0 + width, -neg, jnp.concatenate([best_idx, slot])[which]

    carry = (jnp.zeros((), jnp.int32), jnp.full((k,), jnp.inf, jnp.float32),
             jnp.zeros((k,), jnp.int32))
    if _FIRST_CHUNK > 0:  # peeled first trip (one more copy of the trip in the program)
        carry = trip(*carry, min(_FIRST_CHUNK, chunk))
    _, best_d2, best_idx = jax.lax.while_loop(lambda c: c[0] < total,
                                              lambda c: trip(*c, chunk), carry)
    return best_idx, best_d2, best_d2 <= r2
