"""An exact, jittable neighbour index for the fixed-capacity memory: multi-level uniform grids
(cell lists) plus a sorted list of the latest writes.

Selected with ``HedgerConfig(neighbour_index="grid")`` (``"auto"`` picks it for large
capacities). It returns exactly the neighbour set of the brute-force search
(``memory.select_neighbours`` with ``neighbour_index="brute"``): the stored points within
``k_thresh`` of the query, at most the ``max_neighbours`` nearest, with bit-identical float32
squared distances (same formula, same order of operations).

Design (all shapes static, so everything jits and vmaps; N = capacity, d = dim, k =
``max_neighbours``):

* **Levels.** Level l guarantees to find every point within ``radius_l = k_thresh / r^l``
  (r = sqrt 2) of the query: each dimension is cut into cells of side >= radius_l (1 + 1e-3),
  so the points within radius_l lie in the query's cell or a neighbour along every dimension;
  one "contiguous" state dimension (the widest) is cut 4x finer and is the fastest-varying
  part of a cell's key, so the cells along it form contiguous key ranges ("rows"): a query
  scans at most 3^(d-1) rows per level (2 instead of 3 along a discrete action dimension
  whose values lie more than two radii apart: ``paired_dims``). Rows whose cells are all
  farther than radius_l from the query (e.g. the cells of another discrete action) are
  skipped. Level 0 (radius ``k_thresh``) answers every query; finer levels exist for large
  capacities (``index_levels``) and make the cost independent of the density: a query uses
  the finest level whose rows hold at least ``level_target`` x k points (3k; 4.5k with three
  uniform dimensions, e.g. continuous actions; one lookup of the cell tables per level),
  keeps the k nearest, and accepts them if the k-th lies within that level's radius (then no
  point outside the scanned rows can be nearer); otherwise it rescans at level 0 (rare).
* **Cells.** A uniform dimension i gets a range [lo_i, hi_i] (``index_bounds``; default
  [0, 1] for state dimensions -- the scaling of ``HedgerConfig.for_env`` -- and the scaled
  action bounds for continuous actions); a cell coordinate is
  ``clip(floor((z_i - lo_i) / s_i), 0, G_i - 1)``: clipping is monotone and non-expansive, so
  points outside the range are *clamped into the border cells, never dropped*; they only make
  those cells fuller (slower, still exact). A discrete action dimension whose scaled values
  are at least ``k_thresh`` (1 + 1e-3) apart gets one cell per value (boundaries at the
  midpoints), so the cell tables do not spend cells on the gaps between actions. The number of
  cells per level is capped (``max_cells``) by coarsening (sides only grow: still exact).
* **Tables.** Per level: the memory slots sorted by cell key, a copy of their points in that
  order, their keys, and ``starts``: the first sorted position of every cell. Build: a sort.
* **Recent writes.** Points written since the last merge are not in the tables. The first
  R of them (``recent_length``: ``index_recent``, or 1,024-8,192 growing with the capacity)
  are kept in a list sorted by level-0 key (an O(R) insertion per write; with loop kernels,
  ``hedger_jax.runtime``, a loop moving only the entries after the new one); a query finds the
  parts of its level-0 rows in that list by binary search. Writes beyond R are scanned by
  brute force (exact, slower). ``refresh`` merges the writes into the tables -- O(N + cells)
  per level, so only once 3R / 4 have accumulated (``merge_threshold``: a few episodes) or
  when forced.
* **Scan.** The query's candidates are the concatenation of its table rows, its recent-list
  rows and the brute-force writes; they are scanned in chunks (``chunk_width``) by a
  ``lax.while_loop`` keeping the k nearest so far (``kselect.smallest_k``: ``lax.top_k``,
  or a sort-free selection that loop kernels can hold; with one level, a query whose
  candidates all fit one step of at most k takes them as they are, and candidates that fit
  the kept entries are appended without a selection), so any occupancy is exact -- a full or
  overflowing cell just costs more trips. A candidate's column in the index arrays follows
  from its position in the sequence (``_candidate_columns``: a compare-and-count over the
  segment starts, or a binary search for some vmapped batch sizes, whichever XLA's CPU
  backend runs faster). With several levels the first trip is
  ``first_trips`` chunks wide and only the queries with more candidates go on (under vmap,
  16 at a time), so a batch does not run its slowest query's trips for every query.
* **Ring buffer.** With ``full_policy="overwrite_oldest"`` a slot written since the last merge
  is masked out of the tables (its new point is in the recent list or the brute-force writes),
  and a recent-list entry is masked once its slot was written again, so no slot is ever
  counted twice. ``n_new`` (writes since the merge) saturates at N + R: then every slot was
  rewritten and the last N writes are all scanned by brute force, each slot once.
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

from hedger_jax.config import GRID_MAX_CAPACITY
from hedger_jax.fusion import computed_once
from hedger_jax.kselect import cpu_kernels, smallest_k, true_positions
from hedger_jax.loops import batch_cond

#: Largest number of grid cells per level (size of a ``starts`` table); see ``max_cells``.
_MAX_CELLS = 1 << 22
#: Relative margin of the cell side over the level radius (float32 round-off of coordinates).
_SIDE_MARGIN = 1e-3
#: Queries rescanned together under vmap (``loops.batch_cond``'s ``compact``).
_RESCAN_GROUP = 16
#: Queries that go on scanning after ``first_trips`` together under vmap (``compact``).
_REST_GROUP = 16
#: Subdivision of the contiguous dimension (cells of side radius / _FINE along it).
_FINE = 4
#: Points merged into the tables per O(N) pass of ``refresh``.
_MERGE_WINDOW = 1024
#: Largest number of cells along one dimension (keeps the coordinate round-off << margin).
_MAX_PER_DIM = 4096
#: Largest number of key buckets of the recent list's lookup table (an insertion costs
#: O(buckets)).
_MAX_BUCKETS = 2048
#: Largest capacity of the grid index: a candidate's column plus ``_TAB_BIT`` (the flag of
#: ``_columns_by_count``'s single sum) must stay below 2^31, with room for the scan's width.
_MAX_CAPACITY = GRID_MAX_CAPACITY
#: Ratio of the radii of consecutive levels.
_LEVEL_RATIO = math.sqrt(2.0)
#: A finer level is used for a query when its rows hold at least this many times k points
#: (then the k nearest lie within its radius with overwhelming probability for any smooth
#: density: the radius ball fills about half of the rows' box in two dimensions; measured on
#: uniform data at 3e5 and 1e6 points: 0 and 0.02 % of queries rescan at level 0).
_LEVEL_TARGET = 3
#: With more than two uniform (not one-cell-per-value) dimensions the targets grow by this
#: factor per extra dimension (``level_target``): the radius ball fills a smaller part of the
#: rows' box (3 dimensions: ~0.21 of it instead of ~0.47), so at 3k a finer level's k nearest
#: often lay outside its radius and the query was searched again at level 0. Measured
#: (continuous mountain car, action_scale 0.1, 2e5 uniform points in 3e5 slots): at 3k, 9.8 %
#: of queries were rescanned; training at 4k / 5k / 6k (with ``loops``' small-batch groups)
#: 2.17 / 2.08 / 1.69x faster than at 3k, 4.5k within 3 % of 4k -- a coarser level (2.8x the
#: candidates) costs more than a rare rescan.
_TARGET_GROWTH = 1.5
#: The auto level count adds a level while a full memory of uniformly spread points would
#: hold at least this many times k points in a query's rows at that level. (2 gave mountain
#: car 6 levels at 1e6 slots; 5 were faster both to train, paired 1.14x with the merges every
#: level costs, and to query, 1.05x for 4096 batched queries; 300k keeps 4: 3 traded 1.05x
#: training for 0.97x queries. Measured, 2-core CPU.)
_LEVEL_ADD = 2.5


def level_target(n_uniform: int) -> float:
    """Points (in units of k) that a finer level's rows must hold for a query to use that
    level: ``_LEVEL_TARGET``, times ``_TARGET_GROWTH`` per uniform dimension beyond two.
    The auto level count (``_LEVEL_ADD``) does not scale with it: continuous mountain car at
    1e5 slots, a level whose rows reach the target only where the memory is denser than
    average, kept 1.08x faster training than the old code; dropping it, 0.78x (paired)."""
    return _LEVEL_TARGET * _TARGET_GROWTH ** max(int(n_uniform) - 2, 0)


def recent_length(config) -> int:
    """R, the recent list's length: ``config.index_recent``, or (None) from the capacity N:
    1,024 up to ~5.8e4 slots, 2,048 up to ~2.3e5, 4,096 up to ~9.3e5, 8,192 above
    (2^round(log2(6 sqrt N)), clipped to [1024, 8192]), at most N.

    Why it grows: a merge costs O(N) per level and merges happen every ~3R/4 writes, while a
    write costs O(R) (the sorted insertion) and every query scans the pending writes of its
    rows. Training, mountain car, paired, serial codegen (2-core CPU): at 1e6 slots R = 8,192
    was 1.08x faster than 4,096 discrete (0.98x continuous) and 16,384 0.94x of 8,192
    (earlier 2,048 / 4,096 were 1.27x / 1.37x faster than 1,024); at 3e5 4,096 was 1.10x / 1.05x faster than 2,048
    (discrete / continuous); at 1e5 2,048 1.03x / 1.00x against 1,024; at 5e4 2,048 was 1.08x
    discrete but 0.81x continuous (its greedy search makes many queries per write), so 1,024
    is kept up to ~5.8e4.
    """
    n = int(config.capacity)
    if getattr(config, "index_recent", None) is not None:
        return int(min(config.index_recent, n))
    r = 2 ** int(round(math.log2(6.0 * math.sqrt(n))))
    return int(min(max(r, 1024), 8192, n))


def merge_window(geo: "Geometry", n: int) -> int:
    """Writes merged per O(N) pass: ``_MERGE_WINDOW``, or the recent list's length when longer
    (one pass per merge), at most the capacity n."""
    return min(max(_MERGE_WINDOW, geo.recent), n)


def merge_threshold(recent: int) -> int:
    """Pending writes from which ``refresh`` merges: 3/4 of the recent list (at least 1).

    Every merge pass costs O(N) whatever the number of points it merges (up to
    ``merge_window``), and refreshes happen between episodes, so the more writes a merge takes
    the cheaper each one is: at 3/4 of a 1,024-entry list a merge takes ~770-970 writes of
    200-step episodes instead of ~510-710 at one half (training paired 1.08x at 3e5 slots,
    1.13x at 1e6, neutral at 2e4; measured). The last quarter is the headroom for the episode
    that crosses the threshold: writes beyond the list (an episode longer than R/4 steps
    after it) are still found, by a linear scan of them, but cost every query until the merge.
    """
    return max(3 * recent // 4, 1)


class Level(NamedTuple):
    """Static geometry of one level (Python floats / ints).

    radius: every stored point within ``radius`` of a query is in the query's rows.
    lo, inv_side: per dimension, the grid origin and 1 / cell side (0 for a value dimension).
    bounds: per dimension, the sorted cell boundaries of a value dimension, else ().
    cells, strides: cells per dimension and the key stride of each (the contiguous dimension
      has stride 1); n_cells: their product.
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
    """levels: the levels, coarsest (radius k_thresh) first; n_starts: total length of the
    concatenated ``starts`` tables; recent: R, the length of the recent-write list; bucket:
    level-0 keys per bucket of the recent list's lookup table, n_buckets: its number of
    buckets (at most ``_MAX_BUCKETS``); target: ``level_target`` of the uniform dimensions."""

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


def _value_cells(config, side0: float):
    """Per input dimension: the cell boundaries of a discrete action dimension whose scaled
    values are far enough apart for one cell per value (interior cells >= side0 wide), else
    None (a uniform dimension)."""
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
    """Volume of a query's rows at a level (uniform dimensions only), for the auto level count."""
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
    """The static levels of a config (cached: configs are hashable).

    ``config.index_levels`` levels, or (None) as many as are useful for the capacity: a finer
    level is added while a memory full of uniformly spread points would hold at least
    ``_LEVEL_ADD`` x ``max_neighbours`` points in a query's rows at that level (at least one).
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
        # Levels down to the one covering the config's own radius are always kept: a traced
        # k_thresh between it and max_k_thresh then has a covering level of its size.
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
    """The fraction of a memory of uniformly spread points (over ``default_bounds``) that a
    query's rows cover at the level covering the config's own radius, before rows out of
    reach are skipped: an upper bound of how
    much of the memory a level-0 grid search reads (tested), where brute force reads all of
    it. Small for a bandwidth that is small against the input ranges
    (mountain car and the corridor: 0.001-0.013); large for a wide kernel or many dimensions
    (d = 4 with bandwidth 0.1: 0.065; d = 8: 0.07), where brute force was 2-10x faster
    (measured); ``HedgerConfig``'s "auto" index uses it."""
    levels = geometry(config).levels
    cover = [lv for lv in levels if lv.radius >= config.k_thresh * (1.0 - 1e-9)][-1]
    return _rows_volume(cover, default_bounds(config))


# ------------------------------------------------------------------------------ cells
def _coord(levels: Tuple[Level, ...], i: int, x: jax.Array) -> jax.Array:
    """Cell coordinates along dimension i at each of ``levels`` of values x (L, ...) (or
    broadcastable) -> int32 (L, ...), clamped into the grid. The one definition of a cell:
    the index tables and the query rows use it alike (bit-identical float32 arithmetic)."""
    if levels[0].bounds[i]:                       # a value dimension: the same at every level
        c = jnp.zeros(jnp.shape(x), jnp.int32)
        for edge in levels[0].bounds[i]:
            c = c + (x >= jnp.float32(edge)).astype(jnp.int32)
        return c
    shape = (len(levels),) + (1,) * (jnp.ndim(x) - 1)
    inv = jnp.asarray([lv.inv_side[i] for lv in levels], jnp.float32).reshape(shape)
    top = jnp.asarray([lv.cells[i] - 1 for lv in levels], jnp.float32).reshape(shape)
    u = jnp.clip((x - jnp.float32(levels[0].lo[i])) * inv, 0.0, top)   # clip, then cast:
    return jnp.floor(jnp.where(jnp.isnan(u), 0.0, u)).astype(jnp.int32)  # huge values are safe


def cell_keys(level: Level, z: jax.Array) -> jax.Array:
    """Row-major cell key of points z (d, ...) at a level -> int32 (...)."""
    key = _coord((level,), 0, z[0][None]) * level.strides[0]
    for i in range(1, z.shape[0]):
        key = key + _coord((level,), i, z[i][None]) * level.strides[i]
    return key[0]


def paired_dims(geo: Geometry) -> Tuple[bool, ...]:
    """Per non-contiguous dimension (in dimension order): whether a query's rows take two
    offsets along it instead of three -- a value dimension (one cell per discrete action
    value) whose interior cells are wider than twice level 0's radius (with margin), so at
    most one of the two cells beside the query's can hold a point within the radius
    (``level_rows``)."""
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
    (L, ``n_rows(geo)``), in ascending key order.

    Row r covers the cells with the r-th combination of offsets {-1, 0, 1} from the query's
    cell along the non-contiguous dimensions -- {0, 1} shifted by -1 where the cell below lies
    within the level's radius, along a ``paired_dims`` dimension -- and, along the contiguous
    one, every cell that holds points within the level's radius. A row is not live when it is
    off the grid, or all of its cells are farther than the radius from the query. All levels
    at once (a handful of operations whatever their number).

    Paired value dimensions (e.g. mountain car's three discrete actions: 6 rows, not 9) leave
    out a row that could never be live, so a query does a third less row work: paired
    against three offsets, bit-identical (dead rows hold no candidates, so every candidate
    keeps its position), 2-core CPU: batched selection 1.20x at 1e3 slots, 1.12x at 1e4;
    predictions 1.13x at 3e5, 1.08x at 1e4; discrete training 1.21x at 2e4, 1.08x at 3e5.
    """
    d = z.shape[0]
    L = len(geo.levels)
    contig = geo.levels[0].contig
    radius = jnp.asarray([lv.radius * (1.0 + 0.5 * _SIDE_MARGIN) for lv in geo.levels],
                         jnp.float32)[:, None]                              # (L, 1)
    paired = paired_dims(geo)
    offs = jnp.asarray(_row_offsets(paired))                                 # (R, d-1)
    base = jnp.zeros((L, offs.shape[0]), jnp.int32)
    gap2 = jnp.zeros((L, offs.shape[0]), jnp.float32)
    live = jnp.ones((L, offs.shape[0]), bool)

    for col, i in enumerate(j for j in range(d) if j != contig):
        cells = jnp.asarray(_stacked(geo, "cells", i), jnp.int32)[:, None]
        rc = _coord(geo.levels, i, jnp.broadcast_to(z[i], (L, 1)))          # (L, 1)
        b = geo.levels[0].bounds[i]
        if paired[col]:
            # Rows (c - 1, c) where the cell below lies within the level's radius, else
            # (c, c + 1): both are never within it (cells wider than two radii).
            below = jnp.asarray((-np.inf,) + tuple(b), jnp.float32)[jnp.clip(rc, 0, len(b))]
            rc = rc - (z[i] - below <= radius).astype(jnp.int32)
        rc = rc + offs[None, :, col]
        live = live & (rc >= 0) & (rc < cells)
        if b:
            edges = jnp.asarray((-np.inf,) + tuple(b) + (np.inf,), jnp.float32)
            cc = jnp.clip(rc, 0, len(b))
            lo, hi = edges[cc], edges[cc + 1]
        else:
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
    """Index the valid slots [0, size) of points (d, N) from scratch (a sort per level).

    O(N log N) with a slow multi-operand sort on CPU: used for a memory without an index
    (e.g. built by hand or loaded) and after very many writes; ``refresh`` merges a few
    episodes' points in O(N + cells) instead.
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
    """Record one write (bool ``did_write``) of point z (d,) to ``slot``: the first R since the
    last merge are inserted in level-0 key order into the recent columns (``_insert_recent``),
    later ones appended after them (O(1)); past N writes the index is saturated."""
    geo = geometry(config)
    R = geo.recent
    n = config.capacity
    L = len(geo.levels)
    n_new = index.n_new
    order, spoints, rkeys, rstarts = index.order, index.spoints, index.rkeys, index.rstarts
    # Row L is only touched in its first R columns (an insertion: static slices, written back
    # in place) or one column (an append: a scatter that drops the write when not appending,
    # so the old value is never read back). Reading a column that an earlier update of the
    # same step wrote made XLA copy the whole (L + 1, ...) arrays at every write (measured:
    # 5 ms per write at capacity 300,000), and a window with a traced start became a gather
    # and scatter of R columns per write under vmap.
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
    live) are left as they are, as ``_insert_by_blocks`` leaves them: vmapped seeds (this
    form) and single runs (that one) give bit-identical memories."""
    R = rkeys.shape[-1]
    pos = jnp.sum((rkeys <= key).astype(jnp.int32))
    j = jnp.arange(R, dtype=jnp.int32)

    def shift(a, x):                 # a (..., R): insert x at pos, shift the rest right
        # a[j - 1] by a pad, not a concatenation of slices: XLA's CPU code copied that with
        # memmove, which ran slowly enough to take 11 % of a discrete training step at 2e4
        # slots (AMD EPYC; profiled). Paired: training 1.16-1.27x at 2e4, 1.40x at 3e5.
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
    """``_insert_recent`` moving only the live columns pos .. count - 1 (one right), in blocks
    of ``_INSERT_BLOCK`` from the top down, in place: a loop of ~(count - pos) / 16 steps
    instead of O(R) passes over the recent columns (and XLA's copies of them), pos found by
    a binary search. For a single write (the training step); columns above ``count`` (not
    live) are left as they are. rkeys, order and spoints may carry leading axes of size 1 (a
    vmap of one member, ``_insert_recent_fn``), updated in place as they are: squeezed, the
    loop's results were copied back into the batched arrays at every write (~26 us per
    training step at 2e4 slots)."""
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
        # Batched writes (vmapped seeds): the O(R) passes, one form for every member (a loop
        # would run until the member with the most columns to move is done, with gathers).
        out = jax.vmap(functools.partial(_insert_by_shift, L))(*args)
        return out, (True, True, True)

    return insert


def _insert_recent(L: int, rkeys, order, spoints, key, slot, z, count, ins):
    """Insert a write (key (), slot (), point z (d,)) into the recent list (keys rkeys (R,),
    ascending; row L of order (L + 1, N) and spoints (L + 1, d, N)) after the entries whose
    key is <= key (so equal keys stay in write order), shifting the later ones one column
    right, when ``ins`` (count: live entries before the insertion, < R when ``ins``).
    Returns (rkeys, order, spoints)."""
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
    """Merge the window's points (slots wslots (W,), points wpts (d, W), ``active`` (W,)) into one
    level's tables; ring buffer: entries of the window's slots (indexed before) are removed.

    O(N + T + W log W), no sort of the N entries: kept entries move by the number of removed
    entries before them and of merged entries with a smaller key (a stable counting merge).
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
        # No removals ("error" policy: the merged slots were empty). Every entry, used or not
        # (unused ones have key T and stay at the end), moves up by the number of merged
        # entries with a smaller key: strictly increasing positions, no prefix sum over N.
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
    """Merge the oldest min(todo, W) of the last ``todo`` writes into every level's tables.
    Returns (index with updated tables, todo - merged)."""
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


#: A merge of more writes than this many windows rebuilds the tables (one sort) instead.
_MAX_MERGE_WINDOWS = 8


def merge(config, index: GridIndex, points: jax.Array, head: jax.Array,
          size: jax.Array) -> GridIndex:
    """Merge every write since the last merge into the tables and empty the recent list: a
    ``lax.while_loop`` of ceil(writes / W) window merges, or, for more than
    ``_MAX_MERGE_WINDOWS`` windows (or a saturated index), a rebuild of the valid slots
    [0, size) from scratch."""
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
    """Merge the writes since the last merge into the tables when worthwhile: when at least
    ``merge_threshold`` writes are pending (three quarters of the recent list; anything
    pending without a recent list), or always
    with ``force``. The search is exact either way; merging only keeps it fast. Under
    ``vmap`` the merge runs only when some member needs it (``loops.batch_cond``)."""
    geo = geometry(config)
    if force:
        return merge(config, index, points, head, size)
    need = index.n_new >= merge_threshold(geo.recent)
    return batch_cond(need, lambda ix: merge(config, ix, points, head, size), lambda ix: ix,
                      index)


# ------------------------------------------------------------------------------ query
def _table_segments(geo: Geometry, index: GridIndex, first, last, live):
    """Every level's table segments of the query's rows: (positions, lengths), each (L, R).
    first/last/live: ``level_rows``."""
    starts = jnp.asarray([lv.start for lv in geo.levels], jnp.int32)[:, None]
    s0 = index.starts[starts + first]
    return s0, jnp.where(live, index.starts[starts + last + 1] - s0, 0)


def covering_level(geo: Geometry, k_thresh) -> jax.Array:
    """The finest level whose radius covers ``k_thresh`` (int32 ()): every stored point within
    k_thresh of a query lies in the query's rows at that level. Level 0 covers the largest
    radius the config allows (``HedgerConfig.max_k_thresh``)."""
    radii = jnp.asarray([lv.radius for lv in geo.levels], jnp.float32)
    return jnp.maximum(jnp.sum((radii >= k_thresh).astype(jnp.int32)) - 1, 0)


def level_segments(geo: Geometry, index: GridIndex, first, last, live, k: int, k_thresh):
    """The levels a query searches: -> (cover (), level (), positions (L, R), lengths (L, R)).
    ``cover`` is ``covering_level``; ``level`` the finest level at or below it whose rows hold
    >= geo.target * k indexed points, else ``cover``; positions and lengths every level's table
    segments of the query's rows. first/last/live: ``level_rows``."""
    s0, length = _table_segments(geo, index, first, last, live)
    cover = covering_level(geo, k_thresh)
    counts = jnp.sum(length, axis=1)
    lv = cover
    for i in range(1, len(geo.levels)):
        lv = jnp.where((i > cover) & (counts[i] >= int(math.ceil(geo.target * k))), i, lv)
    return cover, lv, s0, length


def _recent_segments(geo: Geometry, index: GridIndex, first, last, live):
    """The recent-list entries in the level-0 rows (first/last/live (R,)): (list positions,
    lengths). Whole key buckets are taken (a superset of the rows: exact, as every
    candidate's distance is tested). Where a bucket spans two rows (buckets of more keys than
    the contiguous dimension has cells, e.g. 4 dimensions), a row's segment starts after the
    previous live row's end, so no entry is a candidate twice (it was: a slot counted twice
    in K). The rows' keys ascend with the row number (``level_rows``), and so do the list's."""
    a = index.rstarts[first // geo.bucket]
    b = jnp.where(live, index.rstarts[last // geo.bucket + 1], 0)
    done = jnp.concatenate([jnp.zeros((1,), b.dtype), jax.lax.cummax(b)[:-1]])
    a = jnp.maximum(a, done)
    return a, jnp.where(live, jnp.maximum(b - a, 0), 0)


def _scan(config, geo: Geometry, index: GridIndex, head, z, lv, tab_start, tab_len,
          rec_start, rec_len):
    """Running top-k over the candidates: per row, its table segment at level ``lv`` then its
    recent writes; last, the writes since the merge beyond the first R. Every candidate comes
    from the same (level or recent row, column) gather. -> (best slots (k,), best squared
    distances (k,)), ascending with several levels, else unordered; with one level and
    ``order`` (a function of (slots, squared distances) of any width), each branch's answer
    goes through it (``select_orders``)."""
    L = len(geo.levels)
    n = index.order.shape[-1]
    R = geo.recent
    k = min(config.max_neighbours, n)
    chunk = chunk_width(config)
    # Only candidates within the level's radius can be an accepted answer (``select``); the
    # fewer finite entries, the cheaper XLA's top_k.
    r2 = jnp.asarray([lvl.radius for lvl in geo.levels], jnp.float32)[lv] ** 2
    n_new = jnp.minimum(index.n_new, n)                        # not saturated here
    zero = jnp.zeros((1,), jnp.int32)
    # One segment per row (table part, then recent part) and one for the later writes; per
    # segment: (begin in the candidate sequence, table start, table length, recent start).
    tab_len = jnp.concatenate([tab_len, zero]).astype(jnp.int32)
    over_len = jnp.maximum(n_new - R, 0)
    lengths = tab_len + jnp.concatenate([rec_len, over_len[None]]).astype(jnp.int32)
    ends = jnp.cumsum(lengths)
    begins = ends - lengths
    total = ends[-1]
    t_start = jnp.concatenate([tab_start, zero]).astype(jnp.int32)
    r_start = jnp.concatenate([rec_start, jnp.full((1,), R, jnp.int32)]).astype(jnp.int32)
    table = jnp.stack([begins, t_start, tab_len, r_start], 1)
    # Sub-segments: per segment its table part, then its recent part; a candidate's column is
    # its position plus its sub-segment's shift (``_candidate_columns``).
    sub_begin = jnp.stack([begins, begins + tab_len], 1).reshape(-1)
    shift = jnp.stack([t_start - begins, r_start - begins - tab_len], 1).reshape(-1)
    sub_delta = shift - jnp.concatenate([zero, shift[:-1]])
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
            # A table entry whose slot was written since the merge is stale (its new point is
            # among the recent writes).
            ok = ok & ~(in_tab & (jax.lax.rem(slot - h0 + n, n) < n_new))
        return slot, d2, ok

    # The first trip of a multi-level scan by ``_first_trip``: one query's by segment windows,
    # a vmapped batch's by the column count (same values).
    by_segments = L > 1 and config.full_policy != "overwrite_oldest" and n >= _WINDOW
    sub_len = jnp.stack([tab_len, lengths - tab_len], 1).reshape(-1)
    sub_col = jnp.stack([t_start, r_start], 1).reshape(-1)

    def trip(p0, best_d2, best_idx, width, fresh=False):
        p = p0 + jnp.arange(width, dtype=jnp.int32)                  # (width,)
        if fresh and by_segments:
            d2, ok = _first_trip(width)(index.spoints, z, lv, table, sub_begin, sub_delta,
                                        sub_len, sub_col, total, r2)
            slot = p
        else:
            slot, d2, ok = candidates(p, _candidate_columns)
        if L > 1:
            # Several levels: the kept candidates are carried as sequence positions (unique per
            # query, free), and only the k kept at the end become slots, instead of gathering
            # the slot of every candidate (192 per query in the first trip). Same selection
            # (payloads do not order it), same slots. Paired, bit-identical, 2-core CPU:
            # batched predictions 1.05x at 3e5 slots, selection 1.11x at 1e6; training
            # discrete 1.06x at 3e5, 1.03x at 1e6, continuous 0.95-1.03x at 3e5.
            slot = p
        # Only candidates nearer than the current k-th can enter (an equal one would lose to
        # the earlier entry anyway): later trips hand top_k few finite values (it is cheap on
        # those, ~1 us per row, and ~40 ns per finite value in random order).
        # (The k-th nearest so far is the largest kept distance: +inf while fewer than k.)
        ok = ok & (d2 < jnp.max(best_d2))

        # ``smallest_k``: with loop kernels (``hedger_jax.runtime``), single queries and
        # vmapped batches below 64 select without ``top_k``, so the training loops stay
        # single kernels with several levels too (training at 1e5 / 3e5 / 1e6 slots paired
        # 1.42x / 1.31x / 1.17x discrete, 1.16x / 1.34x continuous at 1e5 / 3e5; it was
        # 0.93x at 3e5 before LLVM's unroll threshold was lowered, so top_k was kept then).
        def top(best):
            return smallest_k(jnp.concatenate([best[0], jnp.where(ok, d2, jnp.inf)]),
                              jnp.concatenate([best[1], slot]), k)

        if L > 1:                     # rows of ~3k+ candidates: the k nearest must be chosen
            if fresh:   # nothing kept yet: the k nearest of the new candidates only (k fewer
                #             values: batched selection 1.14-1.19x at 1e5-1e6, measured;
                #             packing the candidates within the radius into half the width
                #             first was slower)
                # (Cutting the candidates beyond the smallest of a few shrinking radii that
                # held k before the selection, a gain for XLA's top_k in big batches, slowed
                # the sort-free form: 0.97x discrete, 0.85x continuous at 3e5, paired.)
                return (p0 + width,) + smallest_k(jnp.where(ok, d2, jnp.inf), slot, k)
            return (p0 + width,) + top((best_d2, best_idx))
        # One level (small memories): usually every candidate within the radius fits in the
        # k kept entries, whose finite ones are a prefix; then the new ones are appended
        # after them (unsorted: ``select``'s caller puts K in canonical order) and XLA's
        # top_k (a third of a batched query's cost at 1e4 slots, measured) runs only for the
        # queries that overflow, 16 at a time under vmap.
        n_best = jnp.sum(jnp.isfinite(best_d2).astype(jnp.int32))

        def append(best):
            # Gathered, not scattered: output entry n_best + r takes the r-th accepted
            # candidate (``kselect.true_positions``: through ok's bits packed in words; a
            # prefix count of ok and a binary search over it was slower: training at 2e4
            # slots 1.09-1.19x discrete, 1.28x continuous; batched selection 1.09x at 1e4,
            # 1.49x at 2e4, paired, bit-identical). XLA's CPU scatter was a loop of single
            # updates: training 1.03x, batched selection 1.03-1.05x (paired, bit-identical).
            r = jnp.arange(k, dtype=jnp.int32) - n_best                    # (k,)
            src = true_positions(ok, r)
            new = (r >= 0) & (src < width)
            src = jnp.minimum(src, width - 1)
            return jnp.where(new, d2[src], best[0]), jnp.where(new, slot[src], best[1])

        over = n_best + jnp.sum(ok.astype(jnp.int32)) > k
        return (p0 + width,) + batch_cond(over, top, append, (best_d2, best_idx),
                                          compact=_RESCAN_GROUP)

    carry = (jnp.zeros((), jnp.int32), jnp.full((k,), jnp.inf, jnp.float32),
             jnp.zeros((k,), jnp.int32))
    if L == 1:
        # One level (small memories): rows hold few candidates (1e4 uniform points: at most
        # 43, one trip); one loop (one copy of the trip in the program: compile time).
        _, best_d2, best_idx = jax.lax.while_loop(lambda c: c[0] < total,
                                                  lambda c: trip(*c, chunk), carry)
        return best_idx, best_d2
    # Several levels: two stages. A query's rows at its level hold about geo.target k to
    # twice that many candidates, so the first stage is one wide trip (``first_trips`` chunks:
    # one top_k instead of several, batched selection 1.2x at 3e5 and 1e6, measured), then
    # only the queries with more candidates go on, ``_REST_GROUP`` at a time under vmap
    # (``loops.batch_cond``'s ``compact``): a vmapped while loop runs as many trips as the
    # query with the most candidates needs, for every query of the batch (3e5 slots, 4096
    # uniform queries: mean 2.8 trips of 64, max 6). Same candidates in the same order:
    # bit-identical results.
    carry = trip(*carry, first_trips(config) * chunk, fresh=True)

    def rest(c):
        return jax.lax.while_loop(lambda c: c[0] < total, lambda c: trip(*c, chunk), c)

    _, best_d2, best_idx = batch_cond(carry[0] < total, rest, lambda c: c, carry,
                                      compact=_REST_GROUP)
    best_idx = candidates(best_idx, _candidate_columns)[0]            # positions -> slots
    return best_idx, best_d2


def _candidate_cells(lv, L: int, n: int, col, in_tab):
    """(row, column) of candidates in the (L + 1, ...) index arrays: level lv's table or
    (row L) the recent list. Straight 2-D gathers from those arrays (``index.order[lv]`` with
    a traced lv would be a copy of the level's N entries)."""
    return jnp.where(in_tab, lv, L), jnp.clip(col, 0, n - 1)


def _candidate_points(spoints, row, col) -> jax.Array:
    """The candidates' points: spoints (L + 1, d, N), row, col (w,) -> (d, w)."""
    return jnp.stack([spoints[row, i, col] for i in range(spoints.shape[1])])


#: Columns one step of ``_first_trip_by_segments`` reads from a segment (one vector load
#: per coordinate).
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
    sub-segment's positions, up to the trip's width. The same distances (the same formula on
    the same points); positions beyond the candidates stay +inf, so they are not live.

    A window that would run past the arrays' end starts earlier (``dynamic_slice`` clamps)
    and its lanes are shifted by the same amount; lanes outside the sub-segment keep the
    values already written (a window's tail must not overwrite the next sub-segment's
    positions: sub-segments are written in position order, and each writes only its own)."""
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
    """The first trip of a multi-level scan: (spoints, z, lv, table, sub_begin, sub_delta,
    sub_len, sub_col, total, r2) -> (squared distances, live), (width,) each, at positions
    0 .. width - 1 of the query's candidate sequence. One query: ``_first_trip_by_segments``;
    under ``vmap``: ``_first_trip_by_count``, whose gathers XLA's CPU backend emits element by
    element for a batch as for one query, while a batch's slices would be gathers too (the
    segment form for a vmapped batch ran 0.47x, measured). Same values either way.

    Measured (paired, 2-core Intel Xeon, continuous mountain car at 3e5 slots, results
    identical): training 1.05x with the greedy search's grid still vmapped (its refinements
    and the replay's use the segment form), and with the grid searched action by action
    (``greedy.search_1d``) a further 1.06x."""

    @custom_vmap
    def first(spoints, z, lv, table, sub_begin, sub_delta, sub_len, sub_col, total, r2):
        return _first_trip_by_segments(spoints, z, lv, sub_begin, sub_len, sub_col, r2, width)

    @first.def_vmap
    def first_vmap(axis_size, in_batched, *args):
        axes = tuple(0 if b else None for b in in_batched)
        out = jax.vmap(functools.partial(_first_trip_by_count, width=width), in_axes=axes)(*args)
        return out, (True, True)

    return first


#: Flag bit of ``_columns_by_count``'s single sum: set for a candidate in a table part. The
#: grid index needs every column (< capacity + scan width) below it (``geometry`` checks).
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
    delta = computed_once(sub_delta + jnp.where(even, _TAB_BIT, -_TAB_BIT))
    sub_begin = computed_once(sub_begin)
    acc = p + jnp.sum(jnp.where(p[:, None] >= sub_begin[None, :], delta[None, :], 0), axis=1)
    return acc & (_TAB_BIT - 1), acc >= _TAB_BIT


#: The candidates' columns: ``_columns_by_count`` (see there).
_candidate_columns = _columns_by_count


#: Widest default scan step (``chunk_width``), and the steps' granularity.
_CHUNK = 64
_CHUNK_STEP = 16


def _full_memory_candidates(config) -> float:
    """m: the mean count of a one-level query's rows (before rows out of reach are skipped)
    in a full memory of uniformly spread points over ``default_bounds``."""
    geo = geometry(config)
    bounds = default_bounds(config)
    n_values = int(np.prod([len(b) + 1 for b in geo.levels[0].bounds if b] or [1]))
    return config.capacity / n_values * _rows_volume(geo.levels[0], bounds)


def chunk_width(config) -> int:
    """Candidates per step of the grid scan: ``config.index_chunk``, or (None) ``_CHUNK``,
    narrowed for a one-level grid whose rows hold few points even when the memory is full:
    the multiple of ``_CHUNK_STEP`` at or above m + 4 sqrt(m), m the mean count of a query's
    rows in a full memory of uniformly spread points (about the most any of 4096 uniform
    queries meets, measured: mountain car 1e3 / 1e4 slots, m + 4 sqrt(m) = 10 / 43, largest
    counts 9 / 40). A vmapped one-level scan makes as many steps as its fullest query needs,
    and a step costs its width whatever it holds: batched selection at 1e3 / 1e4 slots with
    16 / 48 instead of 64 ran 1.40x / 1.15x, predictions at 1e4 1.10x, with no change with
    several levels (paired, 2-core CPU). Denser data is still exact, in more steps."""
    if getattr(config, "index_chunk", None) is not None:
        return int(config.index_chunk)
    if len(geometry(config).levels) > 1:
        return _CHUNK
    m = _full_memory_candidates(config)
    width = _CHUNK_STEP * int(math.ceil((m + 4.0 * math.sqrt(m)) / _CHUNK_STEP))
    return int(min(max(width, _CHUNK_STEP), _CHUNK))


def first_trips(config) -> int:
    """Width, in chunks of ``chunk_width``, of the grid scan's first trip with several levels,
    made for every query of a vmapped batch before only those with more candidates go on:
    enough for twice the candidates a finer level's rows hold when that level is chosen
    (``level_target`` x k), so few queries go on (4096 uniform queries at 1e5 / 3e5 / 1e6
    uniform points: 2.1 % / 3.4 % / 0.15 %, measured; 2 or 4 chunks were slower at 3e5 and
    1e6)."""
    k = min(config.max_neighbours, config.capacity)
    return max(1, int(math.ceil(2 * geometry(config).target * k / chunk_width(config))))


def _sqdist(points: jax.Array, z: jax.Array) -> jax.Array:
    """Same formula and order as ``memory.squared_distances`` (bit-identical results)."""
    d2 = (points[0] - z[0]) ** 2
    for i in range(1, points.shape[0]):
        d2 = d2 + (points[i] - z[i]) ** 2
    return d2


def select(config, points: jax.Array, head: jax.Array, index: GridIndex, z: jax.Array,
           k_thresh=None):
    """Exact K of query z (d,) within ``k_thresh`` (default the config's; at most the radius
    the index is built for, ``HedgerConfig.max_k_thresh``) -> (indices int32 (k,), sqdist
    float32 (k,), mask bool (k,)).

    Same contract as the brute-force search (k = min(max_neighbours, capacity), +inf where
    there is no candidate; the caller pads, masks and puts K in canonical order), except the
    order: ascending squared distances with several levels, unordered with one.
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
        # A finer level than the covering one is used when its rows hold enough points, and
        # its answer kept only if it found k neighbours within its radius (then nothing
        # outside its rows is nearer); else the covering level is scanned.
        found = _scan(config, geo, index, head, z, lv, seg_start[lv], seg_len[lv], rec_start,
                      rec_len)
        ok = (lv == cover) | jnp.all(jnp.isfinite(found[1]))

        def rescan(_):
            return _scan(config, geo, index, head, z, cover, seg_start[cover], seg_len[cover],
                         rec_start, rec_len)

        # A branch, not a loop: XLA hoists loop-invariant work out of a while loop, which
        # would run the rescan always; under vmap only when some query needs it.
        found = batch_cond(~ok, rescan, lambda c: c, found, compact=_RESCAN_GROUP)
    if config.full_policy == "overwrite_oldest":
        # Saturated (more writes since the merge than slots): brute force over every slot.
        def brute(_):
            d2, idx = smallest_k(_sqdist(points, z), jnp.arange(n, dtype=jnp.int32), k,
                                 kernel_form=len(geo.levels) == 1)
            return idx, d2

        found = batch_cond(index.n_new > n, brute, lambda c: c, found)
    best_idx, best_d2 = found
    return best_idx, best_d2, best_d2 <= r2
