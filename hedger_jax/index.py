"""Exact, jittable neighbour index for HEDGER's fixed-capacity memory: multi-level uniform
grids (cell lists) plus a sorted list of the latest writes.

Used with ``HedgerConfig(neighbour_index="grid")`` (``"auto"`` picks it for large,
low-dimensional memories: ``HedgerConfig.index_kind``). Contract: ``select`` returns exactly
the neighbour set of the brute-force search (``memory.select_neighbours`` with
``neighbour_index="brute"``) -- the stored points within ``k_thresh`` of the query, at most
the ``max_neighbours`` nearest -- with bit-identical float32 squared distances (same formula,
same order of operations); only a point tied with the k-th distance may be swapped for
another at that distance. It is exact in every state of the index: ``refresh`` only keeps it
fast.

All shapes are static (N = capacity, d = dim, k = ``max_neighbours``, L = levels, R = recent
list), so everything jits and vmaps. Entry points: ``empty`` / ``build`` (a new index),
``note_write`` (one write), ``refresh`` / ``merge`` (fold the writes into the tables),
``select`` (one query).

Design, exactness arguments and the vmap constraints: docs/grid-index.md.
"""
from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from hedger_jax.fusion import computed_once
from hedger_jax.kselect import cpu_kernels, smallest_k, true_positions
from hedger_jax.loops import batch_cond

#: Largest capacity of the grid index (int32 positions with a flag at bit 30); above it
#: "auto" uses brute force and "grid" is refused.
GRID_MAX_CAPACITY = 1 << 29

#: Largest number of cells per level (the length of one level's ``starts``; ``max_cells``).
_MAX_CELLS = 1 << 22
#: Relative margin of a cell's side over its level's radius (float32 round-off of coordinates).
_SIDE_MARGIN = 1e-3
#: Queries rescanned, or (one level) selected, together under vmap (``batch_cond``'s compact).
_RESCAN_GROUP = 16
#: Queries that go on after the first trip, together under vmap (``batch_cond``'s compact).
_REST_GROUP = 16
#: Subdivision of the contiguous dimension: a row spans ~2 radii along it, not 3 cells.
_FINE = 4
#: Fewest writes merged per O(N) pass of a merge (``merge_window``).
_MERGE_WINDOW = 1024
#: Largest number of cells along one dimension (coordinate round-off stays << the margin).
_MAX_PER_DIM = 4096
#: Largest number of key buckets of the recent list (an insertion updates every bucket).
_MAX_BUCKETS = 2048
#: Largest capacity: a candidate's column plus ``_TAB_BIT`` must stay below 2^31.
_MAX_CAPACITY = GRID_MAX_CAPACITY
#: Ratio of the radii of consecutive levels.
_LEVEL_RATIO = math.sqrt(2.0)
#: A finer level is used when its rows hold this many times k points: its radius then holds k.
_LEVEL_TARGET = 3
#: Target growth per uniform dimension beyond two: the ball fills less of the rows' box.
_TARGET_GROWTH = 1.5
#: Auto levels: add one while a full uniform memory holds this many times k in its rows.
_LEVEL_ADD = 2.5


def level_target(n_uniform: int) -> float:
    """Points, in units of k, that a finer level's rows must hold for a query to use it:
    ``_LEVEL_TARGET`` times ``_TARGET_GROWTH`` per uniform dimension beyond two.

    With more uniform dimensions the radius ball fills a smaller part of the rows' box, and a
    rescan at the covering level costs more than a coarser level's extra candidates. The
    auto level count (``_LEVEL_ADD``) does not scale with it: a level that reaches the target
    only where the memory is denser than average still pays for itself."""
    return _LEVEL_TARGET * _TARGET_GROWTH ** max(int(n_uniform) - 2, 0)


def recent_length(config) -> int:
    """R, the recent list's length: ``config.index_recent``, or (None)
    2^round(log2(6 sqrt N)) clipped to [1024, 8192], at most N.

    Why it grows with N: a merge costs O(N) per level and comes every ~3R/4 writes, while a
    write costs O(R) (the sorted insertion) and every query scans the pending writes of its
    rows. The floor holds up to ~5.8e4 slots because the continuous-action search makes many
    queries per write; beyond the ceiling the scans cost more than the merges saved.
    """
    n = int(config.capacity)
    if getattr(config, "index_recent", None) is not None:
        return int(min(config.index_recent, n))
    r = 2 ** int(round(math.log2(6.0 * math.sqrt(n))))
    return int(min(max(r, 1024), 8192, n))


def merge_window(geo: "Geometry", n: int) -> int:
    """W, the writes merged per O(N) pass: ``_MERGE_WINDOW``, or R when longer (one pass per
    merge), at most the capacity n."""
    return min(max(_MERGE_WINDOW, geo.recent), n)


def merge_threshold(recent: int) -> int:
    """Pending writes from which ``refresh`` merges: 3/4 of the recent list (at least 1).

    Why 3/4: every merge pass costs O(N) whatever it merges, so the more writes a merge takes
    the cheaper each one is; the last quarter is headroom for the episode that crosses the
    threshold (writes beyond the list are still found, by a linear scan that every query pays
    until the merge).
    """
    return max(3 * recent // 4, 1)


class Level(NamedTuple):
    """Static geometry of one level (Python floats / ints).

    radius: every stored point within ``radius`` of a query is in the query's rows.
    lo, inv_side: per dimension, the grid origin and 1 / cell side (0 for a value dimension).
    bounds: per dimension, the sorted cell boundaries of a value dimension, else ().
    cells, strides: per dimension, the number of cells and the key stride (the contiguous
      dimension has stride 1); n_cells: the product of ``cells``.
    contig: the contiguous dimension. start: offset of this level's ``starts`` table.
    """

    radius: float
    lo: Tuple[float, ...]
    inv_side: Tuple[float, ...]
    bounds: Tuple[Tuple[float, ...], ...]
    cells: Tuple[int, ...]
    strides: Tuple[int, ...]
    n_cells: int
    contig: int
    start: int


class Geometry(NamedTuple):
    """Static geometry of a config's index (``geometry``).

    levels: the levels, coarsest (radius ``max_k_thresh``) first. n_starts: total length of
    the concatenated ``starts`` tables. recent: R. bucket: level-0 keys per bucket of the
    recent list's lookup table; n_buckets: its number of buckets (<= ``_MAX_BUCKETS``).
    target: ``level_target`` of the uniform dimensions.
    """

    levels: Tuple[Level, ...]
    n_starts: int
    recent: int
    bucket: int
    n_buckets: int
    target: float


class GridIndex(NamedTuple):
    """Pytree of one memory's index (L levels, N = capacity, d = dim, R = recent list).

    order:   int32 (L + 1, N) rows 0 .. L-1: the memory slots sorted by the level's cell key
             (positions >= the level's indexed count unused). Row L: the writes since the last
             merge -- columns [0, R) the first R of them sorted by level-0 key (ties in write
             order), columns [R, N) the later ones in write order.
    skeys:   int32 (L, N) the tables' cell keys (the level's n_cells at unused positions).
    spoints: float32 (L + 1, d, N) the points in the order of ``order`` (one gather serves a
             table entry and a recent write alike).
    starts:  int32 (n_starts,) per level, the first sorted position of each of its cells and,
             last, its indexed count.
    n_new:   int32 () writes since the last merge, saturating at N + 1: write j < n_new went to
             slot ``(head - n_new + j) % N``. Saturated (more writes than slots, only possible
             with ``full_policy="overwrite_oldest"``), every slot is searched by brute force
             until the next merge.
    rkeys:   int32 (R,) level-0 cell keys of the first min(n_new, R) writes, sorted; level 0's
             n_cells past the end.
    rstarts: int32 (B + 1,) number of those in key buckets below b (bucket of a key:
             key // ``Geometry.bucket``): the recent writes of a row are found by two lookups.
    """

    order: jax.Array
    skeys: jax.Array
    spoints: jax.Array
    starts: jax.Array
    n_new: jax.Array
    rkeys: jax.Array
    rstarts: jax.Array


def max_cells(capacity: int) -> int:
    """Cell budget per level: about 4 cells per slot (a merge costs O(capacity + cells)), at
    least 4096 and at most ``_MAX_CELLS``."""
    return int(min(_MAX_CELLS, max(1 << 12, 4 * capacity)))


def default_bounds(config) -> Tuple[Tuple[float, float], ...]:
    """Scaled range (lo, hi) of each of the d input dimensions that the grid covers.

    ``config.index_bounds`` when set; otherwise [0, 1] for state dimensions (the scaling of
    ``HedgerConfig.for_env``) and the scaled action bounds (continuous) or the range of the
    scaled discrete action set. Points outside are clamped into the border cells (exact,
    only slower).
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


def _value_cells(config, side0: float):
    """Per input dimension: the cell boundaries (midpoints between the scaled values) of a
    discrete action dimension whose values are far enough apart for one cell per value
    (interior cells >= side0 wide), else None (a uniform dimension). None everywhere with
    ``index_bounds``. Why: no cells are spent on the gaps between actions."""
    out = [None] * config.dim
    if not config.is_discrete or getattr(config, "index_bounds", None) is not None:
        return out
    S = config.state_dim
    for j in range(config.action_dim):
        vals = sorted({(a[j] - config.input_offset[S + j]) * config.input_scale[S + j]
                       for a in config.discrete_actions})
        if any((vals[i + 1] - vals[i - 1]) / 2.0 < side0 for i in range(1, len(vals) - 1)) \
                or any(b - a < side0 for a, b in zip(vals, vals[1:])):
            continue
        out[S + j] = tuple((a + b) / 2.0 for a, b in zip(vals, vals[1:]))
    return out


def _make_level(config, radius: float, bounds, values, start: int) -> Optional[Level]:
    """The level of radius ``radius`` over ``bounds`` ((lo, hi) per dimension) with the value
    cells ``values`` (``_value_cells``) and its ``starts`` at offset ``start``; None when even
    one cell per uniform dimension does not fit ``max_cells``.

    Uniform cells are at least radius (1 + ``_SIDE_MARGIN``) wide, so a point within the
    radius lies in the query's cell or a neighbour along every non-contiguous dimension; the
    contiguous one's cells are a ``_FINE``-th of that, and a row spans all of them within the
    radius (``level_rows``). Fitting the budget only widens cells (still exact).
    """
    d = len(bounds)
    side0 = radius * (1.0 + _SIDE_MARGIN)
    widths = [max(hi - lo, 0.0) for lo, hi in bounds]
    uniform = [i for i in range(d) if values[i] is None]
    states = [i for i in range(config.state_dim) if values[i] is None]
    contig = max(states or uniform or [0], key=lambda i: (widths[i], i))
    target = [side0 / _FINE if i == contig else side0 for i in range(d)]
    cells = [len(values[i]) + 1 if values[i] is not None
             else max(1, min(_MAX_PER_DIM, int(math.ceil(widths[i] / target[i]))))
             for i in range(d)]
    limit = max_cells(config.capacity)
    while int(np.prod(cells, dtype=np.int64)) > limit:
        coarsen = [i for i in uniform if cells[i] > 1]
        if not coarsen:
            return None
        i = max(coarsen, key=lambda i: cells[i])
        cells[i] = max(1, cells[i] // 2)
    sides = [max(t, w / c) if values[i] is None else 0.0
             for i, (t, w, c) in enumerate(zip(target, widths, cells))]
    # Keys: the contiguous dimension fastest, then the others last to first, so the rows of
    # ``_row_offsets`` ascend in key order.
    strides = [0] * d
    stride = 1
    for i in [contig] + [i for i in range(d - 1, -1, -1) if i != contig]:
        strides[i] = stride
        stride *= cells[i]
    return Level(radius=float(radius), lo=tuple(lo for lo, _ in bounds),
                 inv_side=tuple(1.0 / s if s > 0 else 0.0 for s in sides),
                 bounds=tuple(v if v is not None else () for v in values),
                 cells=tuple(cells), strides=tuple(strides),
                 n_cells=int(np.prod(cells, dtype=np.int64)), contig=contig, start=start)


def _rows_volume(level: Level, bounds) -> float:
    """Fraction of the uniform dimensions' box that a query's rows cover at a level (extent
    2 radii + one cell along the contiguous dimension, 3 cells along the others, each capped
    at the range): the share of a uniformly spread memory that the rows hold, per value cell
    of the discrete action dimensions."""
    vol = 1.0
    for i, inv in enumerate(level.inv_side):
        if not inv:
            continue
        width = max(bounds[i][1] - bounds[i][0], 1e-12)
        ext = 2 * level.radius + 1.0 / inv if i == level.contig else 3.0 / inv
        vol *= min(ext, width) / width
    return vol


@functools.lru_cache(maxsize=None)
def geometry(config) -> Geometry:
    """The static geometry of a config (cached: configs are hashable).

    Level l has radius ``max_k_thresh / sqrt(2)^l``. ``config.index_levels`` levels, or
    (None) every level down to the one covering ``config.k_thresh``, then more while a full
    memory of uniformly spread points would hold at least ``_LEVEL_ADD`` x k points in a
    query's rows at the new level. Levels stop where the cells no longer change or do not
    fit the budget. Raises ValueError for a capacity above ``_MAX_CAPACITY``.
    """
    if config.capacity > _MAX_CAPACITY:
        raise ValueError(f"capacity: the grid index holds at most {_MAX_CAPACITY} slots (int32 "
                         f"positions), got {config.capacity}; use neighbour_index='brute'")
    bounds = default_bounds(config)
    radius = config.max_k_thresh
    values = _value_cells(config, radius * (1.0 + _SIDE_MARGIN))
    if _make_level(config, radius, bounds, values, 0) is None:
        values = [None] * config.dim        # too many value cells for the budget: uniform
    n_values = int(np.prod([len(v) + 1 for v in values if v is not None] or [1]))
    target = level_target(sum(v is None for v in values))
    wanted = getattr(config, "index_levels", None)
    levels, start = [], 0
    for lv in range(wanted or 32):
        level = _make_level(config, radius / _LEVEL_RATIO ** lv, bounds, values, start)
        if level is None or (levels and level.cells == levels[-1].cells):
            break
        # Levels down to the one covering the config's own radius are always kept, so a
        # traced k_thresh up to max_k_thresh has a covering level of about its size.
        covering = level.radius >= config.k_thresh * (1.0 - 1e-9)
        if wanted is None and levels and not covering:
            expected = config.capacity / n_values * _rows_volume(level, bounds)
            if expected < _LEVEL_ADD * config.max_neighbours:
                break
        levels.append(level)
        start += level.n_cells + 1
    n0 = levels[0].n_cells
    bucket = -(-n0 // _MAX_BUCKETS)
    return Geometry(levels=tuple(levels), n_starts=start,
                    recent=recent_length(config), bucket=bucket,
                    n_buckets=-(-n0 // bucket), target=float(target))


def scanned_fraction(config) -> float:
    """Upper bound of the fraction of a uniformly spread memory (over ``default_bounds``) that
    a query reads at the level covering the config's own radius (rows out of reach are not
    yet skipped); brute force reads all of it. Small for a bandwidth small against the input
    ranges, large for a wide kernel or many dimensions, where brute force is faster:
    ``HedgerConfig.index_kind`` ("auto") compares it with ``AUTO_GRID_MAX_FRACTION``."""
    levels = geometry(config).levels
    cover = [lv for lv in levels if lv.radius >= config.k_thresh * (1.0 - 1e-9)][-1]
    return _rows_volume(cover, default_bounds(config))


# ------------------------------------------------------------------------------ cells
def _coord(levels: Tuple[Level, ...], i: int, x: jax.Array) -> jax.Array:
    """Cell coordinates along dimension i at each of ``levels`` of values x (L, ...) (or
    broadcastable) -> int32 (L, ...), clamped into the grid. The one definition of a cell:
    the tables and the query rows use it alike (bit-identical float32 arithmetic). Clamping
    is monotone and non-expansive, so points outside the range land in the border cells and
    are never lost."""
    if levels[0].bounds[i]:                       # a value dimension: the same at every level
        c = jnp.zeros(jnp.shape(x), jnp.int32)
        for edge in levels[0].bounds[i]:
            c = c + (x >= jnp.float32(edge)).astype(jnp.int32)
        return c
    shape = (len(levels),) + (1,) * (jnp.ndim(x) - 1)
    inv = jnp.asarray([lv.inv_side[i] for lv in levels], jnp.float32).reshape(shape)
    top = jnp.asarray([lv.cells[i] - 1 for lv in levels], jnp.float32).reshape(shape)
    u = jnp.clip((x - jnp.float32(levels[0].lo[i])) * inv, 0.0, top)   # clip before the cast:
    return jnp.floor(jnp.where(jnp.isnan(u), 0.0, u)).astype(jnp.int32)  # huge values are safe


def cell_keys(level: Level, z: jax.Array) -> jax.Array:
    """Cell key of points z (d, ...) at a level (coordinates times strides) -> int32 (...)."""
    key = _coord((level,), 0, z[0][None]) * level.strides[0]
    for i in range(1, z.shape[0]):
        key = key + _coord((level,), i, z[i][None]) * level.strides[i]
    return key[0]


def paired_dims(geo: Geometry) -> Tuple[bool, ...]:
    """Per non-contiguous dimension (in dimension order): whether a query's rows take two
    offsets along it instead of three. True for a value dimension whose interior cells are
    wider than twice level 0's radius (with margin): then at most one of the two cells beside
    the query's can hold a point within the radius (``level_rows``), at every level."""
    lv = geo.levels[0]
    out = []
    for i in range(len(lv.cells)):
        if i == lv.contig:
            continue
        b = lv.bounds[i]
        wide = all(hi - lo > 2.0 * lv.radius * (1.0 + 2 * _SIDE_MARGIN)
                   for lo, hi in zip(b, b[1:]))
        out.append(bool(b) and wide)
    return tuple(out)


@functools.lru_cache(maxsize=None)
def _row_offsets(paired: Tuple[bool, ...]) -> np.ndarray:
    """The rows' offsets along the non-contiguous dimensions: the product of {-1, 0, 1} per
    dimension, or {0, 1} where ``paired`` (shifted by the query's lower-or-upper choice) ->
    int32 (rows, d-1), in ascending key order."""
    sets = [(0, 1) if p else (-1, 0, 1) for p in paired]
    return np.array(list(itertools.product(*sets)), dtype=np.int32).reshape(-1, len(paired))


def n_rows(geo: Geometry) -> int:
    """Rows a query scans per level: 3 per non-contiguous dimension, 2 per paired one."""
    return int(np.prod([2 if p else 3 for p in paired_dims(geo)], dtype=np.int64))


def _stacked(geo: Geometry, name: str, i: int) -> np.ndarray:
    """Per level, field ``name`` of dimension i: numpy (L,)."""
    return np.asarray([getattr(lv, name)[i] for lv in geo.levels])


def level_rows(geo: Geometry, z: jax.Array):
    """The rows of query z (d,) at every level: (first key, last key, live), each
    (L, rows), rows = ``n_rows(geo)``, in ascending key order.

    Row r covers the cells at the r-th combination of offsets {-1, 0, 1} from the query's
    cell along the non-contiguous dimensions ({0, 1}, shifted down by one where the cell
    below lies within the radius, along a ``paired_dims`` dimension) and, along the
    contiguous one, every cell that can hold points within the level's radius. A row is dead
    when it is off the grid or all its cells are farther than the radius from the query: dead
    rows hold no candidates, so leaving them out changes no candidate's position. The radius
    used carries half the side margin (round-off of z +- radius). All levels at once.
    """
    d = z.shape[0]
    L = len(geo.levels)
    contig = geo.levels[0].contig
    radius = jnp.asarray([lv.radius * (1.0 + 0.5 * _SIDE_MARGIN) for lv in geo.levels],
                         jnp.float32)[:, None]                              # (L, 1)
    paired = paired_dims(geo)
    offs = jnp.asarray(_row_offsets(paired))                                 # (rows, d-1)
    base = jnp.zeros((L, offs.shape[0]), jnp.int32)
    gap2 = jnp.zeros((L, offs.shape[0]), jnp.float32)
    live = jnp.ones((L, offs.shape[0]), bool)

    for col, i in enumerate(j for j in range(d) if j != contig):
        cells = jnp.asarray(_stacked(geo, "cells", i), jnp.int32)[:, None]
        rc = _coord(geo.levels, i, jnp.broadcast_to(z[i], (L, 1)))          # (L, 1)
        b = geo.levels[0].bounds[i]
        if paired[col]:
            # Rows (c - 1, c) where the cell below lies within the level's radius, else
            # (c, c + 1): cells wider than two radii are never both within it.
            below = jnp.asarray((-np.inf,) + tuple(b), jnp.float32)[jnp.clip(rc, 0, len(b))]
            rc = rc - (z[i] - below <= radius).astype(jnp.int32)
        rc = rc + offs[None, :, col]
        live = live & (rc >= 0) & (rc < cells)
        if b:
            edges = jnp.asarray((-np.inf,) + tuple(b) + (np.inf,), jnp.float32)
            cc = jnp.clip(rc, 0, len(b))
            lo, hi = edges[cc], edges[cc + 1]
        else:
            # Border cells reach to infinity: they hold the clamped points.
            side = jnp.asarray(1.0 / _stacked(geo, "inv_side", i), jnp.float32)[:, None]
            lo = jnp.float32(geo.levels[0].lo[i]) + rc.astype(jnp.float32) * side
            lo, hi = jnp.where(rc <= 0, -jnp.inf, lo), jnp.where(rc >= cells - 1, jnp.inf,
                                                                  lo + side)
        gap = jnp.maximum(jnp.maximum(lo - z[i], z[i] - hi), 0.0)
        gap2 = gap2 + gap * gap
        strides = jnp.asarray(_stacked(geo, "strides", i), jnp.int32)[:, None]
        base = base + jnp.clip(rc, 0, cells - 1) * strides
    live = live & (gap2 <= radius * radius)
    first = base + _coord(geo.levels, contig, z[contig] - radius)
    last = base + _coord(geo.levels, contig, z[contig] + radius)
    return first, last, live


# ------------------------------------------------------------------------------ build
def empty(config) -> GridIndex:
    """The index of an empty memory (every cell empty, no recent writes)."""
    geo = geometry(config)
    n, L = config.capacity, len(geo.levels)
    skeys = jnp.stack([jnp.full((n,), lv.n_cells, jnp.int32) for lv in geo.levels])
    return GridIndex(order=jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (L + 1, n)),
                     skeys=skeys, spoints=jnp.zeros((L + 1, config.dim, n), jnp.float32),
                     starts=jnp.zeros((geo.n_starts,), jnp.int32),
                     n_new=jnp.zeros((), jnp.int32),
                     rkeys=jnp.full((geo.recent,), geo.levels[0].n_cells, jnp.int32),
                     rstarts=jnp.zeros((geo.n_buckets + 1,), jnp.int32))


def _excl_cumsum(x: jax.Array) -> jax.Array:
    """Exclusive prefix sum of counts -> int32."""
    return (jnp.cumsum(x) - x).astype(jnp.int32)


def build(config, points: jax.Array, size: jax.Array) -> GridIndex:
    """Index the valid slots [0, size) of points (d, N) from scratch -> GridIndex with an
    empty recent list: per level, a stable sort by cell key (ties in slot order).

    O(N log N), and the sort is slow on the CPU: for a memory without an index and for merges
    of many windows; ``refresh`` merges a few episodes' writes in O(N + cells) instead.
    """
    geo = geometry(config)
    n = points.shape[-1]
    valid = jnp.arange(n) < size
    fresh = empty(config)
    order, skeys, spoints, starts = [], [], [], []
    for level in geo.levels:
        keys = jnp.where(valid, cell_keys(level, points), level.n_cells)
        sk, od = jax.lax.sort((keys, jnp.arange(n, dtype=jnp.int32)), num_keys=1,
                              is_stable=True)
        counts = jnp.zeros((level.n_cells + 1,), jnp.int32).at[sk].add(1, mode="drop")
        order.append(od)
        skeys.append(sk)
        spoints.append(points[:, od])
        starts.append(_excl_cumsum(counts))
    return fresh._replace(order=jnp.stack(order + [fresh.order[-1]]), skeys=jnp.stack(skeys),
                          spoints=jnp.stack(spoints + [fresh.spoints[-1]]),
                          starts=jnp.concatenate(starts))


def note_write(config, index: GridIndex, z: jax.Array, slot: jax.Array,
               did_write: jax.Array) -> GridIndex:
    """Record the write of point z (d,) to ``slot`` (int32 ()) when ``did_write`` (bool ())
    -> index. The first R writes since the merge are inserted in level-0 key order into the
    recent columns (``_insert_recent``, O(R)); writes R .. N-1 are appended in write order
    (O(1)); past N writes the index is saturated (``n_new`` = N + 1)."""
    geo = geometry(config)
    R = geo.recent
    n = config.capacity
    L = len(geo.levels)
    n_new = index.n_new
    order, spoints, rkeys, rstarts = index.order, index.spoints, index.rkeys, index.rstarts
    # Row L is written only through static slices or a one-column scatter that drops
    # non-appends, never read back in the same step: XLA then updates it in place, not by copy.
    if R:
        key = computed_once(cell_keys(geo.levels[0], z))
        ins = computed_once(did_write & (n_new < R))
        rkeys, order, spoints = _insert_recent(L, rkeys, order, spoints, key, slot, z, n_new,
                                               ins)
        b = jnp.arange(geo.n_buckets + 1, dtype=jnp.int32)
        rstarts = rstarts + (ins & (b > key // geo.bucket)).astype(jnp.int32)
    # Writes R .. N-1 since the merge: appended in write order (one column).
    col = jnp.where(did_write & (n_new >= R) & (n_new < n), n_new, n)   # n: dropped
    order = order.at[L, col].set(slot, mode="drop")
    spoints = spoints.at[L, :, col].set(z, mode="drop")
    n_new = jnp.where(did_write, jnp.minimum(n_new + 1, n + 1), n_new)
    return index._replace(order=order, spoints=spoints, n_new=n_new.astype(jnp.int32),
                          rkeys=rkeys, rstarts=rstarts)


def _insert_by_shift(L: int, rkeys, order, spoints, key, slot, z, count, ins):
    """``_insert_recent`` by O(R) passes: every recent column pos < j <= count takes column
    j - 1 (static slices and selects: one form for any batch). Columns above ``count`` (not
    live) are left as they are, as ``_insert_by_blocks`` leaves them, so vmapped and single
    runs give bit-identical memories."""
    R = rkeys.shape[-1]
    pos = jnp.sum((rkeys <= key).astype(jnp.int32))
    j = jnp.arange(R, dtype=jnp.int32)

    def shift(a, x):                 # a (..., R): insert x at pos, shift the rest right
        # a[j - 1] by a pad: XLA's CPU code copies a concatenation of slices by a slow memmove.
        right = jax.lax.pad(a[..., :-1], jnp.zeros((), a.dtype),
                            [(0, 0, 0)] * (a.ndim - 1) + [(1, 0, 0)])
        return jnp.where(ins & (j <= count),
                         jnp.where(j < pos, a, jnp.where(j == pos, x, right)), a)

    rkeys = shift(rkeys, key)
    order = order.at[L, :R].set(shift(order[L, :R], slot))
    spoints = spoints.at[L, :, :R].set(shift(spoints[L, :, :R], z[:, None]))
    return rkeys, order, spoints


#: Columns moved per step of ``_insert_by_blocks``.
_INSERT_BLOCK = 16


def _insert_by_blocks(L: int, rkeys, order, spoints, key, slot, z, count, ins):
    """``_insert_recent`` moving only the live columns pos .. count - 1 one right, in blocks
    of ``_INSERT_BLOCK`` from the top down, in place: a loop of ~(count - pos) / 16 steps
    (pos by a binary search) instead of O(R) passes. For a single write; columns above
    ``count`` (not live) are left as they are. rkeys, order and spoints may carry leading
    axes of size 1 (a vmap of one member, ``_insert_recent_fn``) and are updated as they
    are: squeezing them would copy the loop's results back into the batched arrays."""
    lead = rkeys.ndim - 1                        # leading singleton axes
    ones = (1,) * lead
    zeros = (jnp.int32(0),) * lead
    flat_keys = rkeys.reshape(rkeys.shape[lead:])
    R = flat_keys.shape[-1]
    pos = jnp.int32(0)                           # entries <= key (rkeys ascending)
    step = 1 << (R.bit_length() - 1)
    while step:
        cand = jnp.minimum(pos + step, R)
        pos = jnp.where(flat_keys[cand - 1] <= key, cand, pos)
        step >>= 1
    B = min(_INSERT_BLOCK, R)
    d = spoints.shape[-2]
    lane = jnp.arange(B, dtype=jnp.int32)

    def step(c):
        top, rkeys, order, spoints = c
        s = jnp.maximum(top - B, 0)              # block [s, s + B); columns >= top are done
        j = s + lane
        below = jnp.maximum(s - 1, 0)            # column s - 1 (unused when s == 0: pos >= 0)

        def moved(win, prev, x):                 # win (..., B), prev (..., 1), x (..., 1)
            right = jnp.concatenate([prev, win[..., :-1]], axis=-1)
            new = jnp.where(j > pos, right, jnp.where(j == pos, x, win))
            return jnp.where(j < top, new, win)  # a clamped first block overlaps a done one

        zero, row = jnp.int32(0), jnp.int32(L)
        rkeys = jax.lax.dynamic_update_slice(
            rkeys, moved(jax.lax.dynamic_slice(rkeys, zeros + (s,), ones + (B,)),
                         jax.lax.dynamic_slice(rkeys, zeros + (below,), ones + (1,)),
                         key.reshape(ones + (1,))), zeros + (s,))
        o_win = jax.lax.dynamic_slice(order, zeros + (row, s), ones + (1, B))
        o_prev = jax.lax.dynamic_slice(order, zeros + (row, below), ones + (1, 1))
        order = jax.lax.dynamic_update_slice(
            order, moved(o_win, o_prev, slot.reshape(ones + (1, 1))), zeros + (row, s))
        p_win = jax.lax.dynamic_slice(spoints, zeros + (row, zero, s), ones + (1, d, B))
        p_prev = jax.lax.dynamic_slice(spoints, zeros + (row, zero, below), ones + (1, d, 1))
        spoints = jax.lax.dynamic_update_slice(
            spoints, moved(p_win, p_prev, z.reshape(ones + (1, d, 1))), zeros + (row, zero, s))
        return s, rkeys, order, spoints

    top = jnp.where(ins, jnp.minimum(count, R - 1) + 1, pos)    # not inserting: no step
    _, rkeys, order, spoints = jax.lax.while_loop(lambda c: c[0] > pos, step,
                                                  (top, rkeys, order, spoints))
    return rkeys, order, spoints


@functools.lru_cache(maxsize=None)
def _insert_recent_fn(L: int):
    """``_insert_recent`` as a ``custom_vmap``: unbatched or a vmap of one member, the block
    loop on the arrays as they are; a batch of members, the shift passes."""
    @custom_vmap
    def insert(rkeys, order, spoints, key, slot, z, count, ins):
        return _insert_by_blocks(L, rkeys, order, spoints, key, slot, z, count, ins)

    @insert.def_vmap
    def insert_vmap(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)
                for a, b in zip(args, in_batched)]
        if axis_size == 1:               # one seed: its own loop, on the arrays as they are
            small = [a[0] for a in args[3:]]                  # key, slot, z, count, ins
            return _insert_by_blocks(L, *args[:3], *small), (True, True, True)
        # A batched loop would run as long as the member with the most columns to move.
        out = jax.vmap(functools.partial(_insert_by_shift, L))(*args)
        return out, (True, True, True)

    return insert


def _insert_recent(L: int, rkeys, order, spoints, key, slot, z, count, ins):
    """Insert a write (key (), slot (), point z (d,)) into the recent list (keys rkeys (R,),
    ascending; row L of order (L + 1, N) and spoints (L + 1, d, N)) after the entries whose
    key is <= key (equal keys stay in write order), shifting the later ones one column
    right, when ``ins`` (count: live entries before the insertion, < R when ``ins``).
    Returns (rkeys, order, spoints). On the CPU through ``_insert_recent_fn``."""
    args = (rkeys, order, spoints, key, slot, z, count, ins)
    if cpu_kernels():
        return _insert_recent_fn(L)(*args)
    return _insert_by_shift(L, *args)


def _put(dst: jax.Array, pos: jax.Array, src: jax.Array, sorted_: bool) -> jax.Array:
    """dst[..., pos] = src, out-of-range positions dropped (sorted_: pos strictly increasing)."""
    return dst.at[..., pos].set(src, mode="drop", indices_are_sorted=sorted_,
                                unique_indices=sorted_)


def _merge_level(config, level: Level, order, skeys, spoints, starts, wslots, wpts, active,
                 h0, m):
    """Merge a window of writes (slots wslots (W,), points wpts (d, W), ``active`` (W,)) into
    one level's order, skeys (N,), spoints (d, N), starts (n_cells + 1,) -> the same four.
    Ring buffer: the entries already indexed for the window's m slots (from h0) are removed.

    A stable counting merge in O(N + cells + W log W), no sort of the N entries: a kept entry
    moves by the removed entries before it and the merged entries with a smaller key.
    """
    n = order.shape[-1]
    T = level.n_cells
    w = wslots.shape[0]
    j = jnp.arange(w, dtype=jnp.int32)
    wkeys = jnp.where(active, cell_keys(level, wpts), T)
    new_counts = jnp.zeros((T + 1,), jnp.int32).at[wkeys].add(1)            # [T] = inactive
    new_before = _excl_cumsum(new_counts)                                      # (T + 1,)
    pos = jnp.arange(n, dtype=jnp.int32)
    if config.full_policy == "overwrite_oldest":
        # Old entries: drop unused positions and slots that are being re-merged.
        keep = (pos < starts[T]) & (((order - h0) % n) >= m)
        keep_i = keep.astype(jnp.int32)
        pos_old = jnp.where(keep, _excl_cumsum(keep_i) + new_before[skeys], n)
        kept_counts = jnp.zeros((T + 1,), jnp.int32).at[skeys].add(keep_i)
        new_starts = _excl_cumsum(kept_counts + new_counts)
        sorted_old = False
    else:
        # No removals (the merged slots were empty): every entry, unused ones (key T) too,
        # moves up by the merged entries with a smaller key -- increasing, no prefix sum.
        pos_old = pos + new_before[skeys]
        kept_counts = jnp.concatenate([jnp.diff(starts), jnp.zeros((1,), jnp.int32)])
        new_starts = starts + new_before
        sorted_old = True
    # New entries go after the kept ones of their cell, in window order.
    skw, perm = jax.lax.sort((wkeys, j), num_keys=1, is_stable=True)
    first = jnp.searchsorted(skw, skw, side="left").astype(jnp.int32)
    pos_new = new_starts[skw] + kept_counts[skw] + (j - first)
    pos_new = jnp.where(skw < T, pos_new, n + j)                  # inactive: distinct, dropped
    put_old = functools.partial(_put, sorted_=sorted_old)
    order = _put(put_old(jnp.zeros((n,), jnp.int32), pos_old, order), pos_new, wslots[perm],
                 sorted_=True)
    skeys = _put(put_old(jnp.full((n,), T, jnp.int32), pos_old, skeys), pos_new, skw,
                 sorted_=True)
    spoints = _put(put_old(jnp.zeros_like(spoints), pos_old, spoints), pos_new, wpts[:, perm],
                   sorted_=True)
    return order, skeys, spoints, new_starts


def _merge_window(config, index: GridIndex, points: jax.Array, head: jax.Array,
                  todo: jax.Array):
    """Merge the oldest min(todo, W) of the last ``todo`` writes (points (d, N), head ()) into
    every level's tables -> (index with updated tables, todo - merged)."""
    geo = geometry(config)
    n = points.shape[-1]
    w = merge_window(geo, n)
    m = jnp.minimum(todo, w)
    h0 = (head - todo) % n
    j = jnp.arange(w, dtype=jnp.int32)
    active = j < m
    wslots = (h0 + j) % n
    wpts = points[:, wslots]
    order, skeys, spoints, starts = index.order, index.skeys, index.spoints, []
    for lv, level in enumerate(geo.levels):
        s = slice(level.start, level.start + level.n_cells + 1)
        o, k, p, st = _merge_level(config, level, order[lv], skeys[lv], spoints[lv],
                                   index.starts[s], wslots, wpts, active, h0, m)
        order, skeys, spoints = order.at[lv].set(o), skeys.at[lv].set(k), spoints.at[lv].set(p)
        starts.append(st)
    index = index._replace(order=order, skeys=skeys, spoints=spoints,
                           starts=jnp.concatenate(starts))
    return index, todo - m


#: Above this many windows of pending writes, ``merge`` rebuilds the tables by one sort.
_MAX_MERGE_WINDOWS = 8


def merge(config, index: GridIndex, points: jax.Array, head: jax.Array,
          size: jax.Array) -> GridIndex:
    """Fold every write since the last merge into the tables and empty the recent list ->
    index: a ``lax.while_loop`` of window merges, or, beyond ``_MAX_MERGE_WINDOWS`` windows,
    a rebuild of the valid slots [0, size) (``build``). points (d, N), head (), size ()."""
    n = points.shape[-1]
    todo = jnp.minimum(index.n_new, n)             # once saturated every slot is rewritten

    def windows(ix):
        ix, _ = jax.lax.while_loop(lambda c: c[1] > 0,
                                   lambda c: _merge_window(config, c[0], points, head, c[1]),
                                   (ix, todo))
        return ix

    big = todo > _MAX_MERGE_WINDOWS * merge_window(geometry(config), n)
    tables = batch_cond(big, lambda ix: build(config, points, size), windows, index)
    fresh = empty(config)
    return tables._replace(n_new=fresh.n_new, rkeys=fresh.rkeys, rstarts=fresh.rstarts)


def refresh(config, index: GridIndex, points: jax.Array, head: jax.Array, size: jax.Array,
            force: bool = False) -> GridIndex:
    """``merge`` when at least ``merge_threshold`` writes are pending (any, without a recent
    list), or always with ``force`` (static bool) -> index. The search is exact either way;
    merging only keeps it fast. Under vmap the merge runs only when some member needs it
    (``loops.batch_cond``)."""
    geo = geometry(config)
    if force:
        return merge(config, index, points, head, size)
    need = index.n_new >= merge_threshold(geo.recent)
    return batch_cond(need, lambda ix: merge(config, ix, points, head, size), lambda ix: ix,
                      index)


# ------------------------------------------------------------------------------ query
def _table_segments(geo: Geometry, index: GridIndex, first, last, live):
    """Every level's table segments of the query's rows (first/last/live: ``level_rows``)
    -> (positions, lengths), each int32 (L, rows); dead rows have length 0."""
    starts = jnp.asarray([lv.start for lv in geo.levels], jnp.int32)[:, None]
    s0 = index.starts[starts + first]
    return s0, jnp.where(live, index.starts[starts + last + 1] - s0, 0)


def covering_level(geo: Geometry, k_thresh) -> jax.Array:
    """The finest level whose radius covers ``k_thresh`` (float or traced ()) -> int32 ():
    every stored point within k_thresh of a query lies in the query's rows at that level.
    Level 0 covers the largest radius the config allows (``HedgerConfig.max_k_thresh``)."""
    radii = jnp.asarray([lv.radius for lv in geo.levels], jnp.float32)
    return jnp.maximum(jnp.sum((radii >= k_thresh).astype(jnp.int32)) - 1, 0)


def level_segments(geo: Geometry, index: GridIndex, first, last, live, k: int, k_thresh):
    """The levels a query searches -> (cover (), level (), positions (L, rows), lengths
    (L, rows)). ``cover``: ``covering_level``. ``level``: the finest level finer than cover
    whose rows hold >= ceil(geo.target * k) indexed points, else cover. positions, lengths:
    every level's table segments of the query's rows. first/last/live: ``level_rows``."""
    s0, length = _table_segments(geo, index, first, last, live)
    cover = covering_level(geo, k_thresh)
    counts = jnp.sum(length, axis=1)
    lv = cover
    for i in range(1, len(geo.levels)):
        lv = jnp.where((i > cover) & (counts[i] >= int(math.ceil(geo.target * k))), i, lv)
    return cover, lv, s0, length


def _recent_segments(geo: Geometry, index: GridIndex, first, last, live):
    """The recent-list entries of the level-0 rows (first/last/live (rows,)) -> (list
    positions, lengths), each (rows,).

    Whole key buckets are taken: a superset of the rows, exact since every candidate's
    distance is tested (and level 0's rows hold every point within any level's radius, so
    they serve every level). Where a bucket spans two rows, a row's segment starts after the
    previous live row's end, so no entry is a candidate twice (rows and list ascend in key).
    """
    a = index.rstarts[first // geo.bucket]
    b = jnp.where(live, index.rstarts[last // geo.bucket + 1], 0)
    done = jnp.concatenate([jnp.zeros((1,), b.dtype), jax.lax.cummax(b)[:-1]])
    a = jnp.maximum(a, done)
    return a, jnp.where(live, jnp.maximum(b - a, 0), 0)


def _segments(n_new, R: int, tab_start, tab_len, rec_start, rec_len):
    """The candidate sequence's layout: one segment per row (its table part, then its recent
    part) and one for the writes beyond the first R since the merge. Returns (table (rows + 1,
    4) int32: per segment its begin in the sequence, table start, table length, recent start;
    sub_begin, sub_delta, sub_len, sub_col (2 (rows + 1),): per sub-segment its begin, its
    column shift's change from the previous one (``_candidate_columns``), its length and first
    column; total (): the sequence's length)."""
    zero = jnp.zeros((1,), jnp.int32)
    tab_len = jnp.concatenate([tab_len, zero]).astype(jnp.int32)
    over_len = jnp.maximum(n_new - R, 0)
    lengths = tab_len + jnp.concatenate([rec_len, over_len[None]]).astype(jnp.int32)
    ends = jnp.cumsum(lengths)
    begins = ends - lengths
    t_start = jnp.concatenate([tab_start, zero]).astype(jnp.int32)
    r_start = jnp.concatenate([rec_start, jnp.full((1,), R, jnp.int32)]).astype(jnp.int32)
    table = jnp.stack([begins, t_start, tab_len, r_start], 1)
    # A candidate's column is its position plus its sub-segment's shift.
    sub_begin = jnp.stack([begins, begins + tab_len], 1).reshape(-1)
    shift = jnp.stack([t_start - begins, r_start - begins - tab_len], 1).reshape(-1)
    sub_delta = shift - jnp.concatenate([zero, shift[:-1]])
    sub_len = jnp.stack([tab_len, lengths - tab_len], 1).reshape(-1)
    sub_col = jnp.stack([t_start, r_start], 1).reshape(-1)
    return table, sub_begin, sub_delta, sub_len, sub_col, ends[-1]


def _append(best, n_best, d2, slot, ok):
    """The kept (squared distances (k,), slots (k,)) whose first ``n_best`` are finite, with
    the accepted candidates (``ok`` (w,)) of (d2, slot) (w,) after them, as many as fit.
    Gathered, not scattered (XLA's CPU scatter is a loop of single updates): entry
    n_best + r takes the r-th accepted candidate."""
    k, width = best[0].shape[0], d2.shape[0]
    r = jnp.arange(k, dtype=jnp.int32) - n_best                    # (k,)
    src = true_positions(ok, r)
    new = (r >= 0) & (src < width)
    src = jnp.minimum(src, width - 1)
    return jnp.where(new, d2[src], best[0]), jnp.where(new, slot[src], best[1])


def _scan(config, geo: Geometry, index: GridIndex, head, z, lv, tab_start, tab_len,
          rec_start, rec_len):
    """The k nearest candidates of query z (d,) within level ``lv``'s radius -> (slots int32
    (k,), squared distances float32 (k,)), in no particular order, +inf where fewer. The
    candidate sequence (``_segments``) is read in trips of a ``lax.while_loop`` that keeps
    the k nearest so far, so any occupancy is exact; a full cell only costs more trips."""
    L, n, chunk = len(geo.levels), index.order.shape[-1], chunk_width(config)
    k = min(config.max_neighbours, n)
    # Only candidates within the level's radius can be part of an accepted answer.
    r2 = jnp.asarray([lvl.radius for lvl in geo.levels], jnp.float32)[lv] ** 2
    n_new = jnp.minimum(index.n_new, n)                        # saturated: ``select``'s brute
    table, sub_begin, sub_delta, sub_len, sub_col, total = _segments(
        n_new, geo.recent, tab_start, tab_len, rec_start, rec_len)
    if config.full_policy == "overwrite_oldest":
        h0 = jax.lax.rem(head - n_new + n, n)

    def candidates(p, columns):
        """Candidates at sequence positions p (w,): (slots, squared distances, whether each
        is a live candidate within the level's radius), each (w,)."""
        col, in_tab = columns(p, table, sub_begin, sub_delta)
        row, col = _candidate_cells(lv, L, n, col, in_tab)
        slot = index.order[row, col]
        d2 = _sqdist(_candidate_points(index.spoints, row, col), z)
        ok = (p < total) & (d2 <= r2)
        if config.full_policy == "overwrite_oldest":
            # A table entry whose slot was written since the merge is stale: its new point is
            # among the recent writes.
            ok = ok & ~(in_tab & (jax.lax.rem(slot - h0 + n, n) < n_new))
        return slot, d2, ok

    # The windowed first trip (``_first_trip``) flags no stale entries: not for a ring buffer.
    by_segments = L > 1 and config.full_policy != "overwrite_oldest" and n >= _WINDOW

    def trip(p0, best_d2, best_idx, width, fresh=False):
        p = p0 + jnp.arange(width, dtype=jnp.int32)                  # (width,)
        if fresh and by_segments:
            d2, ok = _first_trip(width)(index.spoints, z, lv, table, sub_begin, sub_delta,
                                        sub_len, sub_col, total, r2)
            slot = p
        else:
            slot, d2, ok = candidates(p, _candidate_columns)
        if L > 1:
            # Keep sequence positions (unique per query) and turn only the final k into slots,
            # rather than gathering every candidate's slot; the selection is the same.
            slot = p
        # Only candidates nearer than the current k-th (+inf while fewer than k are kept) can
        # enter (a tie loses to the kept entry before it), so later trips select few values.
        ok = ok & (d2 < jnp.max(best_d2))

        # ``smallest_k`` is sort-free on the CPU, so the trip loop stays one kernel.
        def top(best):
            return smallest_k(jnp.concatenate([best[0], jnp.where(ok, d2, jnp.inf)]),
                              jnp.concatenate([best[1], slot]), k)

        if L > 1:                     # rows of ~3k+ candidates: the k nearest must be chosen
            if fresh:   # nothing kept yet: select among the new candidates only
                return (p0 + width,) + smallest_k(jnp.where(ok, d2, jnp.inf), slot, k)
            return (p0 + width,) + top((best_d2, best_idx))
        # One level: the kept finite entries are a prefix (a selection leaves all k finite)
        # and the new ones usually fit after them; only overflowing queries select.
        n_best = jnp.sum(jnp.isfinite(best_d2).astype(jnp.int32))
        over = n_best + jnp.sum(ok.astype(jnp.int32)) > k
        return (p0 + width,) + batch_cond(
            over, top, lambda best: _append(best, n_best, d2, slot, ok), (best_d2, best_idx),
            compact=_RESCAN_GROUP)

    carry = (jnp.zeros((), jnp.int32), jnp.full((k,), jnp.inf, jnp.float32),
             jnp.zeros((k,), jnp.int32))
    rest = lambda c: jax.lax.while_loop(lambda c: c[0] < total,  # noqa: E731
                                        lambda c: trip(*c, chunk), c)
    if L == 1:
        # One level (small memories, few candidates per row): one loop, one copy of the trip.
        _, best_d2, best_idx = rest(carry)
        return best_idx, best_d2
    # Several levels: one wide first trip covers most queries' candidates; only the queries
    # with more go on, so a vmapped batch does not run its slowest query's trips for all.
    carry = trip(*carry, first_trips(config) * chunk, fresh=True)
    _, best_d2, best_idx = batch_cond(carry[0] < total, rest, lambda c: c, carry,
                                      compact=_REST_GROUP)
    best_idx = candidates(best_idx, _candidate_columns)[0]            # positions -> slots
    return best_idx, best_d2


def _candidate_cells(lv, L: int, n: int, col, in_tab):
    """(row, column) of candidates in the (L + 1, ...) index arrays: level lv's table or
    (row L) the recent list; col, in_tab (w,) -> two int32 (w,). Straight 2-D gathers:
    ``index.order[lv]`` with a traced lv would copy the level's N entries."""
    return jnp.where(in_tab, lv, L), jnp.clip(col, 0, n - 1)


def _candidate_points(spoints, row, col) -> jax.Array:
    """The candidates' points: spoints (L + 1, d, N), row, col (w,) -> (d, w)."""
    return jnp.stack([spoints[row, i, col] for i in range(spoints.shape[1])])


#: Columns one step of ``_first_trip_by_segments`` reads (one vector load per coordinate).
_WINDOW = 16


def _first_trip_by_count(spoints, z, lv, table, sub_begin, sub_delta, sub_len, sub_col, total,
                         r2, width: int):
    """The first trip's squared distances and live flags, (width,) each, candidate by
    candidate: every position's column from the sub-segment begins, then a gather of its
    point (``_scan``'s ``candidates``)."""
    del sub_len, sub_col
    L, n = spoints.shape[0] - 1, spoints.shape[-1]
    p = jnp.arange(width, dtype=jnp.int32)
    col, in_tab = _candidate_columns(p, table, sub_begin, sub_delta)
    row, col = _candidate_cells(lv, L, n, col, in_tab)
    d2 = _sqdist(_candidate_points(spoints, row, col), z)
    return d2, (p < total) & (d2 <= r2)


def _first_trip_by_segments(spoints, z, lv, sub_begin, sub_len, sub_col, r2, width: int):
    """``_first_trip_by_count`` for one query, segment by segment: each sub-segment (a row's
    table part, then its recent part; ``_scan``) is read in windows of ``_WINDOW`` contiguous
    columns (``dynamic_slice``: vector loads) whose distances are written at the
    sub-segment's positions, up to the trip's width. The same distances (same formula, same
    points); positions beyond the candidates stay +inf, so they are not live.

    A window that would run past the arrays' end starts earlier (``dynamic_slice`` clamps)
    and its lanes are shifted by the same amount; lanes outside the sub-segment keep the
    values already written, so a window's tail never overwrites the next sub-segment's
    positions (sub-segments are written in position order, each only its own)."""
    L, n = spoints.shape[0] - 1, spoints.shape[-1]
    dim = spoints.shape[1]
    lane = jnp.arange(_WINDOW, dtype=jnp.int32)
    # Table parts (even sub-segments) are in level lv's row, recent parts in row L.
    odd = jax.lax.broadcasted_iota(jnp.int32, sub_begin.shape, 0) % 2 == 1
    rows = jnp.where(odd, L, lv)
    # Positions [0, width) at [_WINDOW, _WINDOW + width): room for a shifted window's lanes
    # on both sides.
    buf = jnp.full((_WINDOW + width + _WINDOW,), jnp.inf, jnp.float32)

    def segment(s, buf):
        begin, row, col0 = sub_begin[s], rows[s], sub_col[s]
        stop = jnp.minimum(sub_len[s], width - begin)      # columns of it inside the trip

        def window(c):
            off, buf = c
            col = col0 + off
            start = jnp.clip(col, 0, n - _WINDOW)
            pts = jax.lax.dynamic_slice(spoints, (row, 0, start), (1, dim, _WINDOW))[0]
            rel = start + lane - col                       # lane's column - col
            keep = (rel >= 0) & (off + rel < stop)
            at = _WINDOW + begin + off - (col - start)
            old = jax.lax.dynamic_slice(buf, (at,), (_WINDOW,))
            new = jnp.where(keep, _sqdist(pts, z), old)
            return off + _WINDOW, jax.lax.dynamic_update_slice(buf, new, (at,))

        return jax.lax.while_loop(lambda c: c[0] < stop, window,
                                  (jnp.zeros((), jnp.int32), buf))[1]

    buf = jax.lax.fori_loop(0, sub_begin.shape[0], segment, buf)
    d2 = buf[_WINDOW:_WINDOW + width]
    return d2, d2 <= r2


@functools.lru_cache(maxsize=None)
def _first_trip(width: int):
    """The first trip of a multi-level scan as a ``custom_vmap``: (spoints, z, lv, table,
    sub_begin, sub_delta, sub_len, sub_col, total, r2) -> (squared distances, live), (width,)
    each, at positions 0 .. width - 1 of the query's candidate sequence. Same values either
    way: one query reads contiguous windows (``_first_trip_by_segments``); a vmapped batch
    gathers candidate by candidate (``_first_trip_by_count``), since a batch's slices with
    per-member starts would be gathers too."""

    @custom_vmap
    def first(spoints, z, lv, table, sub_begin, sub_delta, sub_len, sub_col, total, r2):
        return _first_trip_by_segments(spoints, z, lv, sub_begin, sub_len, sub_col, r2, width)

    @first.def_vmap
    def first_vmap(axis_size, in_batched, *args):
        axes = tuple(0 if b else None for b in in_batched)
        out = jax.vmap(functools.partial(_first_trip_by_count, width=width), in_axes=axes)(*args)
        return out, (True, True)

    return first


#: Table-part flag of ``_columns_by_count``'s sum; every column (< N + scan width) is below it.
_TAB_BIT = 1 << 30


def _columns_by_count(p, table, sub_begin, sub_delta):
    """The column (in the level's or the recent list's row of the index arrays) and table flag
    of the candidates at positions p (width,) of a query's candidate sequence -> (int32
    (width,), bool (width,)). sub_begin, sub_delta (2 segments,): every sub-segment's first
    position and the change of the position-to-column shift there (``_scan``).

    The column is p plus the sum of the shift changes at the sub-segment begins <= p (they
    telescope to the shift of p's sub-segment, empty ones included); p is in a table part iff
    an odd number of begins are <= p. One sum gives both: adding +``_TAB_BIT`` at every table
    part's begin and -``_TAB_BIT`` at every recent part's begin (the begins <= p are a
    prefix, as they ascend) sets the bit exactly for a table part."""
    del table
    even = jax.lax.broadcasted_iota(jnp.int32, sub_delta.shape, sub_delta.ndim - 1) % 2 == 0
    # Materialised once: XLA would recompute them inside every element of the reduction.
    delta = computed_once(sub_delta + jnp.where(even, _TAB_BIT, -_TAB_BIT))
    sub_begin = computed_once(sub_begin)
    acc = p + jnp.sum(jnp.where(p[:, None] >= sub_begin[None, :], delta[None, :], 0), axis=1)
    return acc & (_TAB_BIT - 1), acc >= _TAB_BIT


#: The candidates' columns (``_columns_by_count``).
_candidate_columns = _columns_by_count


#: Widest default scan step (``chunk_width``).
_CHUNK = 64
#: Granularity of ``chunk_width``'s narrowed steps.
_CHUNK_STEP = 16


def _full_memory_candidates(config) -> float:
    """m: the mean count of a one-level query's rows (before rows out of reach are skipped)
    in a full memory of uniformly spread points over ``default_bounds``."""
    geo = geometry(config)
    bounds = default_bounds(config)
    n_values = int(np.prod([len(b) + 1 for b in geo.levels[0].bounds if b] or [1]))
    return config.capacity / n_values * _rows_volume(geo.levels[0], bounds)


def chunk_width(config) -> int:
    """Candidates per trip of the grid scan: ``config.index_chunk``, or (None) ``_CHUNK``,
    narrowed for a one-level grid to the multiple of ``_CHUNK_STEP`` at or above
    m + 4 sqrt(m) (m: ``_full_memory_candidates``), about the most any query meets in a
    full uniform memory. Why: a vmapped one-level scan makes as many trips as its fullest
    query needs, and a trip costs its width whatever it holds. Denser data stays exact, in
    more trips."""
    if getattr(config, "index_chunk", None) is not None:
        return int(config.index_chunk)
    if len(geometry(config).levels) > 1:
        return _CHUNK
    m = _full_memory_candidates(config)
    width = _CHUNK_STEP * int(math.ceil((m + 4.0 * math.sqrt(m)) / _CHUNK_STEP))
    return int(min(max(width, _CHUNK_STEP), _CHUNK))


def first_trips(config) -> int:
    """Width, in chunks of ``chunk_width``, of the first trip of a multi-level scan, which
    every query of a vmapped batch makes: twice the candidates a chosen finer level's rows
    hold (``level_target`` x k), so that few queries go on."""
    k = min(config.max_neighbours, config.capacity)
    return max(1, int(math.ceil(2 * geometry(config).target * k / chunk_width(config))))


def _sqdist(points: jax.Array, z: jax.Array) -> jax.Array:
    """Squared distances from z (d,) to points (d, ...) -> (...): the formula and order of
    ``memory.squared_distances``, so the results are bit-identical."""
    d2 = (points[0] - z[0]) ** 2
    for i in range(1, points.shape[0]):
        d2 = d2 + (points[i] - z[i]) ** 2
    return d2


def select(config, points: jax.Array, head: jax.Array, index: GridIndex, z: jax.Array,
           k_thresh=None):
    """K of query z (d,) -> (slots int32 (k,), squared distances float32 (k,), mask bool
    (k,)), k = min(max_neighbours, N); points (d, N) and head () are the memory's.

    ``k_thresh``: float or traced (); default the config's; at most
    ``HedgerConfig.max_k_thresh``, the radius level 0 is built for. Brute force's set (module
    doc), +inf and mask False where there is no neighbour, in no particular order: the
    caller pads and puts K in canonical order.
    """
    geo = geometry(config)
    n = points.shape[-1]
    k = min(config.max_neighbours, n)
    k_thresh = jnp.float32(config.k_thresh if k_thresh is None else k_thresh)
    r2 = k_thresh ** 2
    z = computed_once(z)
    first, last, live = level_rows(geo, z)
    rows = computed_once(jnp.stack([first, last, live.astype(jnp.int32)]))
    first, last, live = rows[0], rows[1], rows[2] != 0
    if geo.recent:
        rec_start, rec_len = _recent_segments(geo, index, first[0], last[0], live[0])
    else:
        rec_start = rec_len = jnp.zeros(first.shape[1:], jnp.int32)
    cover, lv, seg_start, seg_len = level_segments(geo, index, first, last, live, k, k_thresh)
    if len(geo.levels) == 1:
        found = _scan(config, geo, index, head, z, jnp.zeros((), jnp.int32), seg_start[0],
                      seg_len[0], rec_start, rec_len)
    else:
        # A finer level's answer stands only if it found k neighbours within its radius (then
        # nothing outside its rows is nearer); else the covering level is scanned.
        found = _scan(config, geo, index, head, z, lv, seg_start[lv], seg_len[lv], rec_start,
                      rec_len)
        ok = (lv == cover) | jnp.all(jnp.isfinite(found[1]))

        def rescan(_):
            return _scan(config, geo, index, head, z, cover, seg_start[cover], seg_len[cover],
                         rec_start, rec_len)

        # A branch, not a loop: XLA would hoist a loop's invariant rescan and always run it.
        found = batch_cond(~ok, rescan, lambda c: c, found, compact=_RESCAN_GROUP)
    if config.full_policy == "overwrite_oldest":
        # Saturated (more writes since the merge than slots, so every slot is valid): brute
        # force; the sort-free selection over all N only for the small one-level memories.
        def brute(_):
            d2, idx = smallest_k(_sqdist(points, z), jnp.arange(n, dtype=jnp.int32), k,
                                 kernel_form=len(geo.levels) == 1)
            return idx, d2

        found = batch_cond(index.n_new > n, brute, lambda c: c, found)
    best_idx, best_d2 = found
    return best_idx, best_d2, best_d2 <= r2
