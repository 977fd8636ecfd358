"""The grid neighbour index returns exactly the brute-force neighbour sets.

Brute force (``neighbour_index="brute"``) is the reference. Compared per query: the multiset of
squared distances (bit-identical float32) and the set of slots, ties aside (a slot tied with
the k-th distance may be swapped for another one at the same distance).
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax import index as gi
from hedger_jax.config import HedgerConfig
from hedger_jax.memory import (add_points, add_scaled, init_memory, refresh_index,
                               select_neighbours)
from hedger_jax.prediction import predict_scaled
from hedger_jax.train import Transition, train_episode

DISCRETE = ((-1.0,), (0.0,), (1.0,))


def _cfg(kind, **kw):
    base = dict(state_dim=2, action_dim=1, capacity=2000, bandwidth=0.05,
                discrete_actions=DISCRETE, max_neighbours=16)
    base.update(kw)
    return HedgerConfig(neighbour_index=kind, **base)


def _memory(cfg, pts, refresh=True):
    """A memory holding pts (n, d) in slots [0, n), indexed from scratch."""
    n = pts.shape[0]
    p = np.zeros((cfg.dim, cfg.capacity), np.float32)
    p[:, :n] = pts.T
    m = init_memory(cfg)._replace(points=jnp.asarray(p), size=jnp.int32(n),
                                  head=jnp.int32(n % cfg.capacity))
    if cfg.index_kind == "grid":
        m = m._replace(index=None)           # hand-built: refresh indexes from scratch
        if refresh:
            m = refresh_index(cfg, m)
    return m


#: Queries per search call: a test's queries are padded (repeated) to a multiple of it, so
#: every test searching one config shares one compiled program whatever its query count.
_BATCH = 256


@functools.lru_cache(maxsize=None)
def _select_fn(cfg):
    return jax.jit(jax.vmap(lambda m, z: select_neighbours(cfg, m, z), in_axes=(None, 0)))


@functools.lru_cache(maxsize=None)
def _alone_fn(cfg):
    """Each query searched alone (``lax.map``: no vmap), one after another."""
    return jax.jit(lambda m, zs: jax.lax.map(lambda z: select_neighbours(cfg, m, z), zs))


def _padded(queries):
    q = np.asarray(queries, np.float32)
    return jnp.asarray(np.resize(q, (-(-len(q) // _BATCH) * _BATCH, q.shape[1])))


def _select(cfg, m, queries, fn=_select_fn):
    """K of each query (n, d), vmapped (or with ``fn=_alone_fn`` one by one) -> host
    ``Neighbours`` with leading axis n."""
    n = len(queries)
    out = jax.device_get(fn(cfg)(m, _padded(queries)))
    return jax.tree_util.tree_map(lambda x: x[:n], out)


def _assert_canonical(nb):
    """Batched Neighbours: real neighbours first, by ascending slot."""
    for idx, mask in zip(np.asarray(nb.indices), np.asarray(nb.mask)):
        n = int(mask.sum())
        assert mask[:n].all() and not mask[n:].any()
        assert np.all(np.diff(idx[:n]) > 0), idx[:n]


def _assert_same(cfg_b, m_b, cfg_g, m_g, queries, canonical=False):
    """Brute force and the grid find the same K (sets; ties at the k-th distance aside); with
    ``canonical``, both also in canonical order. Returns brute force's."""
    a, b = _select(cfg_b, m_b, queries), _select(cfg_g, m_g, queries)
    if canonical:
        _assert_canonical(a)
        _assert_canonical(b)
    for i in range(len(queries)):
        da = np.sort(a.sqdist[i][a.mask[i]])
        db = np.sort(b.sqdist[i][b.mask[i]])
        np.testing.assert_array_equal(da, db, err_msg=f"query {i}: squared distances differ")
        ia, ib = a.indices[i][a.mask[i]], b.indices[i][b.mask[i]]
        assert len(set(ib.tolist())) == len(ib), f"query {i}: duplicate slots {ib}"
        if len(da) and len(da) == cfg_b.max_neighbours:  # capped: ties at the k-th distance
            kth = da[-1]
            ia = ia[a.sqdist[i][a.mask[i]] < kth]
            ib = ib[b.sqdist[i][b.mask[i]] < kth]
        assert set(ia.tolist()) == set(ib.tolist()), f"query {i}: {sorted(ia)} != {sorted(ib)}"
    return a


@functools.lru_cache(maxsize=None)
def _probe_fn(cfg, scan=False):
    """jit(vmap over queries z) of what ``index.select`` decides for a query of a memory m:
    (the level it searches first, that level's table candidates in the query's rows) and,
    with ``scan``, whether that level's answer stands (the covering level, or k found
    within the finer level's radius; else it is searched again at the covering level)."""
    geo = gi.geometry(cfg)

    def probe(m, z):
        first, last, live = gi.level_rows(geo, z)
        cover, lv, start, length = gi.level_segments(geo, m.index, first, last, live,
                                                     cfg.max_neighbours, cfg.k_thresh)
        if not scan:
            return lv, jnp.sum(length[lv])
        rec = jnp.zeros_like(start[lv])
        _, d2 = gi._scan(cfg, geo, m.index, m.head, z, lv, start[lv], length[lv], rec, rec)
        # ``_scan``'s k entries are in no particular order: all finite = k found.
        return lv, jnp.sum(length[lv]), (lv == cover) | jnp.all(jnp.isfinite(d2))

    return jax.jit(jax.vmap(probe, in_axes=(None, 0)))


def _pair(**kw):
    return _cfg("brute", **kw), _cfg("grid", **kw)


def _uniform(rng, n):
    x = np.empty((n, 3), np.float32)
    x[:, :2] = rng.uniform(0, 1, (n, 2))
    x[:, 2] = rng.integers(-1, 2, n)
    return x


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="neighbour_index"):
        HedgerConfig(2, neighbour_index="kdtree")
    with pytest.raises(ValueError, match="index_chunk"):
        HedgerConfig(2, index_chunk=0)
    with pytest.raises(ValueError, match="index_bounds"):
        HedgerConfig(2, index_bounds=((0, 1), (0, 1)))
    with pytest.raises(ValueError, match="index_bounds"):
        HedgerConfig(2, index_bounds=((0, 1), (1, 0), (0, 1)))
    # auto: grid from 512 slots for d <= 4 (state dims + 1 action), from 16,384 for d >= 5.
    assert HedgerConfig(2, capacity=511).index_kind == "brute"
    assert HedgerConfig(2, capacity=512).index_kind == "grid"
    assert HedgerConfig(3, capacity=512).index_kind == "grid"
    assert HedgerConfig(4, capacity=16_383).index_kind == "brute"
    assert HedgerConfig(4, capacity=16_384).index_kind == "grid"
    # Low-dimensional inputs use the grid at any kernel width; with more dimensions, only
    # while a query's rows cover at most AUTO_GRID_MAX_FRACTION of the memory.
    from hedger_jax.config import AUTO_GRID_MAX_FRACTION
    wide = HedgerConfig(3, capacity=20_000, bandwidth=0.1)
    assert gi.scanned_fraction(wide) > AUTO_GRID_MAX_FRACTION and wide.index_kind == "grid"
    wide8 = HedgerConfig(7, capacity=20_000, bandwidth=0.1)
    assert gi.scanned_fraction(wide8) > AUTO_GRID_MAX_FRACTION and wide8.index_kind == "brute"
    narrow8 = HedgerConfig(7, capacity=20_000, bandwidth=0.01)
    assert gi.scanned_fraction(narrow8) < AUTO_GRID_MAX_FRACTION and narrow8.index_kind == "grid"
    assert HedgerConfig(2, capacity=10 ** 6).index_kind == "grid"
    assert HedgerConfig(2, capacity=10 ** 6, neighbour_index="brute").index_kind == "brute"


def _assert_level_geometry(cfg, geo):
    assert geo.levels[0].radius == pytest.approx(cfg.k_thresh)
    for lv in geo.levels:
        assert lv.n_cells == int(np.prod(lv.cells)) <= gi.max_cells(cfg.capacity)
        assert lv.strides[lv.contig] == 1
        for i, inv in enumerate(lv.inv_side):
            if lv.bounds[i]:                      # a value dimension: one cell per value
                assert inv == 0 and lv.cells[i] == len(lv.bounds[i]) + 1
            elif i != lv.contig:                  # three cells cover the radius both ways
                assert 1.0 / inv >= lv.radius
    radii = [lv.radius for lv in geo.levels]
    assert radii == sorted(radii, reverse=True)


def test_geometry_cells_at_least_the_level_radius():
    cfg = _cfg("grid")
    geo = gi.geometry(cfg)
    _assert_level_geometry(cfg, geo)
    lv = geo.levels[0]
    assert lv.cells[2] == 3 and lv.bounds[2] == (-0.5, 0.5)   # the discrete action {-1, 0, 1}
    assert lv.contig == 1 and 1.0 / lv.inv_side[1] < cfg.k_thresh  # finely cut
    # A huge grid is coarsened, never finer than the radius.
    big = HedgerConfig(5, 1, bandwidth=1e-3, neighbour_index="grid", capacity=100)
    _assert_level_geometry(big, gi.geometry(big))
    # Levels: one at small capacities, more (each finer) for large ones, or as configured.
    assert len(gi.geometry(_cfg("grid", capacity=2000)).levels) == 1
    assert len(gi.geometry(_cfg("grid", capacity=10 ** 6, bandwidth=0.015)).levels) > 2
    many = _cfg("grid", index_levels=3)
    assert len(gi.geometry(many).levels) == 3
    _assert_level_geometry(many, gi.geometry(many))
    # Actions closer together than the radius: the action dimension stays uniform.
    close = HedgerConfig(2, neighbour_index="grid", discrete_actions=((0.0,), (0.01,)))
    assert gi.geometry(close).levels[0].bounds[2] == ()


def test_uniform_random_matches_brute():
    rng = np.random.default_rng(0)
    cb, cg = _pair()
    pts = _uniform(rng, 1500)
    queries = np.concatenate([_uniform(rng, 150), pts[:50]])   # includes stored points
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    assert a.mask.sum(1).mean() > 3                            # non-trivial neighbour sets


def test_clustered_overflowing_cells_small_chunks():
    """Thousands of points (with exact duplicates) in a few cells, scanned 8 at a time (the
    one-level config of the next test)."""
    rng = np.random.default_rng(1)
    cb, cg = _pair(index_chunk=8, max_neighbours=8, index_levels=1)
    centres = _uniform(rng, 3)
    pts = np.repeat(centres, 600, axis=0) + rng.normal(0, 0.01, (1800, 3)).astype(np.float32)
    pts[:, 2] = np.round(pts[:, 2])
    pts[::7] = pts[0]                                          # many exact duplicates
    queries = np.concatenate([centres + rng.normal(0, 0.02, (3, 3)).astype(np.float32),
                              pts[:20], _uniform(rng, 20)])
    mg = _memory(cg, pts)
    starts = np.asarray(mg.index.starts)
    assert np.diff(starts).max() > 100 * cg.index_chunk // 8   # really overflowing cells
    _assert_same(cb, _memory(cb, pts), cg, mg, queries)


@pytest.mark.parametrize("levels", [1, 3])
def test_scan_rest_runs_for_the_queries_with_more_candidates_only(levels):
    """The scan's batched paths: with several levels the second stage (queries with more
    than ``first_trips`` chunks of candidates after one wide trip, gathered 16 at a time under
    vmap); with one level the top_k of the queries whose candidates overflow k (16 at a time)
    while the others append theirs. A batch of dense-cluster and sparse queries, vmapped and
    one by one, both exactly the brute-force sets."""
    rng = np.random.default_rng(11)
    cb, cg = _pair(index_chunk=8, max_neighbours=8, index_levels=levels)
    assert len(gi.geometry(cg).levels) == levels and gi.first_trips(cg) > 1
    cluster = np.repeat(_uniform(rng, 2), 400, axis=0) \
        + rng.normal(0, 0.005, (800, 3)).astype(np.float32)
    cluster[:, 2] = np.round(cluster[:, 2])
    pts = np.concatenate([cluster, _uniform(rng, 700)])
    queries = np.concatenate([cluster[::40] + 0.001, _uniform(rng, 40)])   # 20 dense, 40 not
    mb, mg = _memory(cb, pts), _memory(cg, pts)
    n_cand = np.asarray(_probe_fn(cg, scan=True)(mg, jnp.asarray(queries))[1])
    more = n_cand > gi.first_trips(cg) * cg.index_chunk
    assert 16 < more.sum() < len(queries) // 2          # several groups, not every query
    _assert_same(cb, mb, cg, mg, queries)
    batched = _select(cg, mg, queries)
    alone = _select(cg, mg, queries, fn=_alone_fn)
    for name, x, y in zip(batched._fields, alone, batched):
        np.testing.assert_array_equal(x, y, err_msg=f"{name}: one by one != vmapped")


def test_wide_user_chunk_one_level_matches_brute():
    """A wide chunk (300: ten 32-bit words of accepted-candidate bits, the last partial), with
    queries whose candidates fit in k and queries that overflow it."""
    rng = np.random.default_rng(12)
    cb, cg = _pair(index_chunk=300, max_neighbours=8, index_levels=1)
    cluster = _uniform(rng, 1)[0] + rng.normal(0, 0.01, (300, 3)).astype(np.float32)
    cluster[:, 2] = np.round(cluster[:, 2])
    pts = np.concatenate([cluster, _uniform(rng, 500)])
    queries = np.concatenate([cluster[:20], _uniform(rng, 20)])
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    counts = a.mask.sum(1)
    assert counts.max() == 8 and counts.min() < 8      # overflowing and fitting queries


def test_one_level_appends_over_several_odd_chunks_match_brute():
    """One level, a chunk of 5 (not a power of two): a query's accepted candidates are
    appended to the kept ones trip after trip (each appended entry gathered by a binary
    search over the trip's accepted counts), at offsets that are not multiples of the chunk."""
    rng = np.random.default_rng(13)
    cb, cg = _pair(index_chunk=5, max_neighbours=16, index_levels=1)
    pts = _uniform(rng, 700)
    queries = np.concatenate([_uniform(rng, 60), pts[:20]])
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    counts = a.mask.sum(1)
    assert (counts > 2 * 5).sum() > 10 and (counts < 16).sum() > 60   # most fit in k   # several trips, no overflow


def _segment_inputs(rng, n_rows, recent, offset=0):
    """A random candidate sequence of n_rows table+recent segments plus the later-writes
    segment (some parts empty), as ``index._scan`` lays it out: (table (n_rows + 1, 4),
    sub_begin, sub_delta, total) and, independently, every position's (column, in table)."""
    tab_len = rng.integers(0, 6, n_rows + 1) * (rng.uniform(size=n_rows + 1) < 0.7)
    tab_len[-1] = 0
    rec_len = rng.integers(0, 4, n_rows + 1) * (rng.uniform(size=n_rows + 1) < 0.5)
    tab_start = rng.integers(0, 1000, n_rows + 1) + offset      # offset: columns near the top
    tab_start[-1] = 0
    rec_start = rng.integers(0, recent, n_rows + 1)
    rec_start[-1] = recent
    lengths = tab_len + rec_len
    begins = np.cumsum(lengths) - lengths
    cols, in_tab = [], []
    for s in range(n_rows + 1):
        cols += [tab_start[s] + j for j in range(tab_len[s])]
        cols += [rec_start[s] + j for j in range(rec_len[s])]
        in_tab += [True] * tab_len[s] + [False] * rec_len[s]
    table = np.stack([begins, tab_start, tab_len, rec_start], 1).astype(np.int32)
    sub_begin = np.stack([begins, begins + tab_len], 1).reshape(-1)
    shift = np.stack([tab_start - begins, rec_start - begins - tab_len], 1).reshape(-1)
    sub_delta = shift - np.concatenate([[0], shift[:-1]])
    return ((table, sub_begin.astype(np.int32), sub_delta.astype(np.int32)),
            np.asarray(cols, np.int64), np.asarray(in_tab, bool))


@pytest.mark.parametrize("batch", [None, 3, 12, 16, 300])
def test_candidate_columns_match_the_expanded_segments(batch):
    """Mapping a candidate position to its (column, table part), alone and vmapped, against
    the segments written out one position at a time (empty table, recent and whole
    segments)."""
    rng = np.random.default_rng(21)
    n = 1 if batch is None else batch
    cases = [_segment_inputs(rng, 9, 64) for _ in range(n)]
    width = 16
    p = np.arange(width, dtype=np.int32) + 3
    for impl in (gi._candidate_columns,):
        args = [np.stack([c[0][i] for c in cases]) for i in range(3)]
        if batch is None:
            col, tab = jax.jit(impl)(jnp.asarray(p), *(jnp.asarray(a[0]) for a in args))
            col, tab = np.asarray(col)[None], np.asarray(tab)[None]
        else:
            col, tab = jax.jit(jax.vmap(impl, in_axes=(None, 0, 0, 0)))(
                jnp.asarray(p), *(jnp.asarray(a) for a in args))
            col, tab = np.asarray(col), np.asarray(tab)
        for i, (_, want_col, want_tab) in enumerate(cases):
            m = min(width, max(len(want_col) - 3, 0))
            np.testing.assert_array_equal(col[i, :m], want_col[3:3 + m], err_msg=str(impl))
            np.testing.assert_array_equal(tab[i, :m], want_tab[3:3 + m], err_msg=str(impl))


def test_candidate_columns_near_the_largest_capacity():
    """Table columns just below the grid's largest capacity (the count's single sum carries a
    table flag at bit 30) map exactly, single and vmapped; a larger capacity is refused with a
    clear error, and "auto" picks brute force there."""
    rng = np.random.default_rng(22)
    top = gi._MAX_CAPACITY - 1000
    p = jnp.arange(24, dtype=jnp.int32)
    for _ in range(4):
        (table, sub_begin, sub_delta), want_col, want_tab = _segment_inputs(rng, 9, 64, top)
        args = (jnp.asarray(table), jnp.asarray(sub_begin), jnp.asarray(sub_delta))
        single = jax.jit(gi._columns_by_count)(p, *args)
        batched = jax.jit(jax.vmap(gi._columns_by_count, (None, 0, 0, 0)))(
            p, *(a[None] for a in args))
        m = min(24, len(want_col))
        for col, tab in (single, (batched[0][0], batched[1][0])):
            np.testing.assert_array_equal(np.asarray(col)[:m], want_col[:m])
            np.testing.assert_array_equal(np.asarray(tab)[:m], want_tab[:m])
        assert int(np.max(want_col, initial=0)) > (1 << 28) or not want_tab.any()
    big = dict(state_dim=2, action_dim=1, capacity=gi._MAX_CAPACITY + 1)
    with pytest.raises(ValueError, match="at most"):
        HedgerConfig(**big, neighbour_index="grid")
    with pytest.raises(ValueError, match="at most"):              # the index's own check
        gi.geometry(HedgerConfig(**big, neighbour_index="brute"))
    assert HedgerConfig(**big).index_kind == "brute"           # "auto" falls back


@pytest.mark.full   # ~15 s; the other grid-against-brute tests cover the small batches
def test_big_and_small_query_batches_match_brute_and_each_other():
    """A vmapped batch of 128 queries and the same queries in batches of 4 (``lax.map``)
    over a three-level grid: both equal brute force, and bit for bit each other."""
    rng = np.random.default_rng(23)
    kw = dict(capacity=20_000, bandwidth=0.05, max_neighbours=16, index_levels=3)
    cb, cg = _pair(**kw)
    pts = _uniform(rng, 20_000)
    mg = _memory(cg, pts)
    queries = np.concatenate([_uniform(rng, 108), pts[:20]])
    a = _assert_same(cb, _memory(cb, pts), cg, mg, queries)
    assert a.mask.sum(1).mean() > 12
    q = jnp.asarray(queries)
    f = jax.vmap(lambda z: select_neighbours(cg, mg, z))
    big = jax.jit(f)(q)
    small = jax.jit(lambda qq: jax.lax.map(f, qq.reshape(-1, 4, 3)))(q)   # batches of 4
    for x, y in zip(big, small):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y).reshape(np.shape(x)))


def test_chunk_width_fits_a_full_uniform_memory_and_stays_exact_beyond():
    """``index.chunk_width``: the config's ``index_chunk`` when set; 64 with several levels;
    for a small one-level grid a multiple of 16 that holds every query's rows in a full
    memory of uniform points (so a vmapped scan makes one step), and clustered points beyond
    it are found exactly in more steps."""
    assert gi.chunk_width(_cfg("grid", index_chunk=24)) == 24
    assert gi.chunk_width(_cfg("grid", capacity=200_000)) == 64
    rng = np.random.default_rng(29)
    for cap in (200, 800):                                      # 16 and 48 wide
        cb, cg = _pair(capacity=cap, index_levels=1)
        width = gi.chunk_width(cg)
        geo = gi.geometry(cg)
        assert len(geo.levels) == 1 and width % 16 == 0 and 16 <= width < 64
        pts = _uniform(rng, cap)
        mg = _memory(cg, pts)
        counts = np.asarray(_probe_fn(cg)(mg, jnp.asarray(_uniform(rng, 4096)))[1])
        assert counts.max() <= width < 2 * counts.max()
        clustered = pts.copy()
        clustered[: cap // 4, :2] = 0.5 + 0.01 * clustered[: cap // 4, :2]   # > width per row
        queries = np.concatenate([clustered[:30] + 0.002, _uniform(rng, 70)])
        a = _assert_same(cb, _memory(cb, clustered), cg, _memory(cg, clustered), queries)
        assert a.mask.sum(1).max() == cg.max_neighbours


def test_cell_borders_and_threshold_distance():
    """Points on cell borders and at exactly k_thresh (in float32) from the query."""
    cb, cg = _pair()
    lv = gi.geometry(cg).levels[0]
    side = np.float32(1.0 / lv.inv_side[0])
    fine = np.float32(1.0 / lv.inv_side[1])                   # dim 1 is the finely cut one
    assert lv.contig == 1 and fine < side
    r = np.float32(cg.k_thresh)
    xs, vs = np.meshgrid((np.arange(0, 8, dtype=np.float32) * side).astype(np.float32),
                         (np.arange(0, 8, dtype=np.float32) * fine).astype(np.float32))
    border = np.stack([xs.ravel(), vs.ravel(), np.zeros(xs.size, np.float32)], 1)
    q = border[:40].copy()
    ring = np.concatenate([q + np.array([r, 0, 0], np.float32), q - np.array([0, r, 0], np.float32),
                           q + np.array([np.nextafter(r, 0), 0, 0], np.float32),
                           q + np.array([0, np.nextafter(r, 1), 0], np.float32)])
    pts = np.concatenate([border, ring, q + 0.5 * side])
    queries = np.concatenate([q, border + np.float32(1e-7), border - np.float32(1e-7)])
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    assert a.mask.sum() > len(queries)


@pytest.mark.parametrize("discrete", [False, True])
def test_every_level_rows_hold_every_point_within_its_radius(discrete):
    """``level_rows`` checked directly, without brute force: for queries anywhere (uniform,
    on cell corners of the coarsest and finest level and one float32 step off them, on and
    beyond the bounds) and points on, just inside and halfway inside each level's sphere in
    400 directions, every point whose float32 squared distance the scan accepts (<= the
    level's radius squared, ``index._sqdist``'s formula) has a cell key in a live row of that
    level."""
    rng = np.random.default_rng(11)
    kw = dict(capacity=300_000, bandwidth=0.015, neighbour_index="grid", index_levels=3)
    cfg = (HedgerConfig(2, 1, discrete_actions=DISCRETE, **kw) if discrete else
           HedgerConfig(2, 1, action_low=(-0.1,), action_high=(0.1,), **kw))
    geo = gi.geometry(cfg)
    b = np.array(gi.default_bounds(cfg))
    # Queries: uniform, on cell corners of level 0 and 2 (and one float32 step off them),
    # near and beyond the bounds.
    q = rng.uniform(b[:, 0], b[:, 1], (60, 3))
    for lv in (geo.levels[0], geo.levels[-1]):
        side = np.array([1.0 / s if s else 1.0 for s in lv.inv_side])
        c = np.floor(rng.uniform(2, 8, (20, 3))) * side + np.array(lv.lo)
        q = np.concatenate([q, c, np.nextafter(c.astype(np.float32), np.float32(9)),
                            np.nextafter(c.astype(np.float32), np.float32(-9))])
    q = np.concatenate([q, [b[:, 0] - 0.01, b[:, 1] + 0.005, b[:, 0]]])
    if discrete:
        q[:, 2] = rng.choice([-1.0, 0.0, 1.0], len(q))
    q = q.astype(np.float32)
    first, last, live = map(np.asarray, jax.jit(jax.vmap(lambda z: gi.level_rows(geo, z)))(
        jnp.asarray(q)))
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for li, lv in enumerate(geo.levels):
        r32 = np.float32(lv.radius)
        pts = np.concatenate([(q[:, None] + s * lv.radius * dirs[None]).astype(np.float32)
                              for s in (1.0, 1.0 - 6e-8, 0.5)], 1)          # (Q, P, 3)
        d2 = (pts[..., 0] - q[:, None, 0]) ** 2
        for j in (1, 2):
            d2 = d2 + (pts[..., j] - q[:, None, j]) ** 2               # index._sqdist, float32
        keys = np.asarray(gi.cell_keys(lv, jnp.asarray(pts.reshape(-1, 3).T))).reshape(d2.shape)
        rows = live[:, li][:, None, :]
        hit = ((keys[..., None] >= first[:, li][:, None, :])
               & (keys[..., None] <= last[:, li][:, None, :]) & rows).any(-1)
        missed = (d2 <= r32 * r32) & ~hit
        assert not missed.any(), (li, q[np.nonzero(missed)[0][:3]], pts[missed][:3])


def test_out_of_range_points_are_clamped_not_dropped():
    rng = np.random.default_rng(2)
    cb, cg = _pair()
    pts = _uniform(rng, 400)
    far = np.array([[-5, -5, 0], [7, 0.5, 1], [0.5, 40, -1], [1e6, 1e6, 1e6], [-1e6, 0, 3],
                    [1.02, 0.5, 0], [-0.03, 0.2, 1]], np.float32)
    far_cloud = np.repeat(far, 5, 0) + rng.normal(0, 0.01, (35, 3)).astype(np.float32)
    pts = np.concatenate([pts, far, far_cloud])
    queries = np.concatenate([far, far + 0.02, _uniform(rng, 50),
                              np.array([[0.5, 0.5, 0.4], [0.5, 0.5, -2.5]], np.float32)])
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    assert a.mask[: len(far)].sum(1).min() >= 1                # far points found themselves


def test_tiny_and_empty_memories():
    cb, cg = _pair(capacity=5, max_neighbours=8)
    for n in (0, 1, 5):
        pts = _uniform(np.random.default_rng(n), n)
        q = _uniform(np.random.default_rng(9), 10)
        if n:
            q = np.concatenate([q, pts])
        _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), q)


def _run_writes(policy, capacity, n_writes, refresh_every, seed, **kw):
    """Write points one by one through add_scaled; refresh at chosen steps; compare often.
    -> (the grid memory, the writes pending (``n_new``) after each block of writes)."""
    rng = np.random.default_rng(seed)
    cb, cg = _pair(**{**dict(capacity=capacity, full_policy=policy, max_neighbours=8,
                             bandwidth=0.08), **kw})
    pts = _uniform(rng, n_writes)
    pts[::5, :2] = pts[::5, :2] * 0.1                          # a dense corner
    vals = rng.normal(size=n_writes).astype(np.float32)

    @jax.jit
    def write_block(mb, mg, zs, vs, writes):
        def body(c, x):
            mb, mg = c
            z, v, w = x
            return (add_scaled(cb, mb, z, v, w), add_scaled(cg, mg, z, v, w)), None
        return jax.lax.scan(body, (mb, mg), (zs, vs, writes))[0]

    refresh = functools.partial(refresh_index, cg, force=True)        # jitted inside
    mb, mg = init_memory(cb), init_memory(cg)
    done, pending = 0, []
    width = max(refresh_every)          # every block padded with skipped writes: one compile
    for step, block in enumerate(refresh_every):
        writes = np.zeros(width, bool)
        writes[:block] = rng.uniform(size=block) > 0.1         # some writes are skipped
        zs, vs = np.zeros((width, 3), np.float32), np.zeros(width, np.float32)
        zs[:block], vs[:block] = pts[done:done + block], vals[done:done + block]
        mb, mg = write_block(mb, mg, jnp.asarray(zs), jnp.asarray(vs), jnp.asarray(writes))
        done += block
        pending.append(int(mg.index.n_new))
        q = np.concatenate([_uniform(rng, 24), pts[max(0, done - 8):done]])
        _assert_same(cb, mb, cg, mg, q, canonical=True)        # stale index: still exact
        if step % 3 != 2:                                      # sometimes no refresh at all
            mg = refresh(mg)
            assert int(mg.index.n_new) == 0
            _assert_same(cb, mb, cg, mg, q, canonical=True)
    np.testing.assert_array_equal(np.asarray(mb.points), np.asarray(mg.points))
    return mg, pending


def test_incremental_writes_error_policy():
    mg, _ = _run_writes("error", 600, 900, [50, 200, 3, 120, 527], seed=3)
    assert int(mg.size) == 600                                 # filled up, then dropped


def test_incremental_writes_ring_buffer_wraps_and_saturates():
    """Ring buffer: overwritten indexed slots must not appear twice; more writes than the
    capacity between refreshes (n_new saturates) and merges bigger than the merge window."""
    blocks = [150, 90, 400, 30, 700, 60, 1500, 5]
    mg, pending = _run_writes("overwrite_oldest", 300, sum(blocks), blocks, seed=4)
    assert int(mg.size) == 300
    window = gi.merge_window(gi.geometry(_cfg("grid", capacity=300)), 300)
    assert max(pending) == 301 > window, pending     # saturated: more than one window merged


@functools.lru_cache(maxsize=None)
def _value_and_grads_fn(cfg):
    """jit(vmap over queries z) of a prediction -> ((value, known), (d value / d z,
    d value / d stored values))."""
    def value(mem, z, values):
        p = predict_scaled(cfg, mem._replace(values=values), z)
        return p.value, p.known

    grad = jax.value_and_grad(value, argnums=(1, 2), has_aux=True)
    return jax.jit(jax.vmap(lambda m, z: grad(m, z, m.values), in_axes=(None, 0)))


# One level in the full suite: the gradient passes the grid search the same way at any
# level count (its inputs are stop_gradient), and test_training_matches_brute compares
# one-level predictions (the replay's) with brute force's.
@pytest.mark.parametrize("levels", [pytest.param(1, marks=pytest.mark.full), 3])
def test_predictions_and_gradients_through_the_grid_match_brute(levels):
    """Predictions (value, known) through the grid index (one level and several) equal brute
    force's; so does jax.grad of a prediction w.r.t. the query and the stored values (it
    works through the grid index), which w.r.t. the values is the local fit's equivalent
    kernel, whose weights sum to 1 (an intercept reproduces constants). Gradients are
    compared at the first 12 queries (near stored points), values at all."""
    rng = np.random.default_rng(8)
    cb, cg = _pair(max_neighbours=16, bandwidth=0.06, index_levels=levels)
    pts = _uniform(rng, 1500)
    vals = jnp.asarray(rng.normal(size=cb.capacity).astype(np.float32))
    mb, mg = (_memory(c, pts)._replace(values=vals) for c in (cb, cg))
    near = pts[:12] + rng.normal(0, 0.01, (12, 3)).astype(np.float32) * np.float32([1, 1, 0])
    q = jnp.asarray(np.concatenate([near, _uniform(rng, 64), pts[12:28]]))
    (vb, kb), (gz_b, gv_b) = _value_and_grads_fn(cb)(mb, q)
    (vg, kg), (gz_g, gv_g) = _value_and_grads_fn(cg)(mg, q)
    np.testing.assert_array_equal(np.asarray(kb), np.asarray(kg))
    np.testing.assert_allclose(np.asarray(vb), np.asarray(vg), rtol=1e-5, atol=1e-6)
    known = np.asarray(kb)[:12]
    assert known.sum() >= 8
    gz_b, gv_b, gz_g, gv_g = (np.asarray(g)[:12] for g in (gz_b, gv_b, gz_g, gv_g))
    np.testing.assert_allclose(gz_g, gz_b, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(gv_g, gv_b, rtol=1e-4, atol=1e-6)
    assert np.all(np.abs(gz_g[known, :2]).sum(1) > 0)
    np.testing.assert_allclose(gv_g[known].sum(1), 1.0, atol=1e-4)


def test_training_matches_brute():
    """An episode's replay (train_episode) over the grid index stores brute force's values,
    and leaves its writes pending in the recent list."""
    rng = np.random.default_rng(5)
    cb, cg = _pair(max_neighbours=16, bandwidth=0.06)
    pts = _uniform(rng, 1200)
    vals = jnp.asarray(rng.normal(size=cb.capacity).astype(np.float32))
    mb, mg = (_memory(c, pts)._replace(values=vals) for c in (cb, cg))
    T = 40
    ep = Transition(obs=jnp.asarray(rng.uniform(0, 1, (T, 2)), jnp.float32),
                    action=jnp.asarray(rng.integers(-1, 2, (T, 1)), jnp.float32),
                    reward=jnp.asarray(rng.uniform(0, 1, T), jnp.float32),
                    next_obs=jnp.asarray(rng.uniform(0, 1, (T, 2)), jnp.float32),
                    terminated=jnp.zeros((T,), bool), valid=jnp.ones((T,), bool))
    tb, _ = jax.jit(lambda m, e: train_episode(cb, m, e))(mb, ep)
    tg, _ = jax.jit(lambda m, e: train_episode(cg, m, e))(mg, ep)
    np.testing.assert_allclose(np.asarray(tb.values), np.asarray(tg.values), rtol=1e-4, atol=1e-6)
    assert int(tg.index.n_new) == T


def test_vmap_over_memories():
    rng = np.random.default_rng(6)
    cb, cg = _pair(capacity=500)
    mems_b, mems_g = [], []
    for s in range(3):
        pts = _uniform(rng, 300 + 50 * s)
        mems_b.append(_memory(cb, pts))
        mems_g.append(_memory(cg, pts))
    stack = lambda ms: jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ms)  # noqa: E731
    q = jnp.asarray(_uniform(rng, 20))
    f = lambda cfg: jax.jit(jax.vmap(jax.vmap(  # noqa: E731
        lambda m, z: select_neighbours(cfg, m, z), (None, 0)), (0, None)))
    a, b = f(cb)(stack(mems_b), q), f(cg)(stack(mems_g), q)
    np.testing.assert_array_equal(np.sort(np.where(a.mask, a.sqdist, -1), -1),
                                  np.sort(np.where(b.mask, b.sqdist, -1), -1))
    # refresh_index under vmap: indexing from scratch gives each member's own index; a lazy
    # refresh with nothing pending leaves it as it is.
    refresh = jax.vmap(functools.partial(refresh_index, cg))
    built = refresh(stack(mems_g)._replace(index=None)).index
    lazy = refresh(stack(mems_g)).index
    for name, want, x, y in zip(built._fields, stack(mems_g).index, built, lazy):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(want), err_msg=f"built {name}")
        np.testing.assert_array_equal(np.asarray(y), np.asarray(want), err_msg=f"lazy {name}")


def _beyond_the_patch():
    """32 queries at growing distances (0.005 to 0.08) outside the patch [0.3, 0.38]^2 of
    the next test, on two sides."""
    d = np.linspace(0.005, 0.08, 16, dtype=np.float32)
    mid, zero = np.full_like(d, 0.34), np.zeros_like(d)
    return np.concatenate([np.stack([mid, 0.38 + d, zero], 1),
                           np.stack([0.38 + d, mid, zero + 1], 1)])


def test_multi_level_dense_and_sparse_queries_match_brute():
    """Finer levels answer dense neighbourhoods; a sparse query or one whose k-th neighbour
    lies outside the finer level's radius falls back to level 0; all exact. (The
    three-level config of ``test_scan_rest_runs_for_the_queries_with_more_candidates_only``.)"""
    rng = np.random.default_rng(7)
    cb, cg = _pair(index_chunk=8, max_neighbours=8, index_levels=3)
    dense = _uniform(rng, 1500)
    dense[:, :2] = 0.3 + 0.08 * dense[:, :2]                  # a dense patch
    sparse = _uniform(rng, 300)
    pts = np.concatenate([dense, sparse])
    queries = np.concatenate([dense[:40] + 0.003, sparse[:40], _uniform(rng, 40),
                              _beyond_the_patch()])
    mg = _memory(cg, pts)
    _assert_same(cb, _memory(cb, pts), cg, mg, queries)
    assert len(gi.geometry(cg).levels) == 3
    chosen, _, accepted = map(np.asarray, _probe_fn(cg, scan=True)(mg, jnp.asarray(queries)))
    assert chosen[:40].min() >= 2 and (chosen[40:80] == 0).mean() > 0.5
    assert not accepted[-32:].all()             # beyond the patch: rescanned at level 0


@pytest.mark.parametrize("bandwidth, paired", [(0.2, True), (0.28, False)])
def test_off_grid_discrete_actions_are_still_found(bandwidth, paired):
    """One cell per discrete action value; a stored point or a query with an action between
    the values (the low-level API allows it) is still exact (cells adjacent in the action
    dimension are scanned when near enough): with cells wider than two radii (k_thresh 0.43,
    spacing 1), where a query's rows take the cell below or the one above (``paired_dims``),
    and narrower (k_thresh 0.60), where they take both."""
    rng = np.random.default_rng(8)
    cb, cg = _pair(bandwidth=bandwidth)
    geo = gi.geometry(cg)
    assert geo.levels[0].bounds[2] == (-0.5, 0.5)
    assert gi.paired_dims(geo) == (False, paired) and gi.n_rows(geo) == (6 if paired else 9)
    rows = jax.eval_shape(functools.partial(gi.level_rows, geo), jnp.zeros(3, jnp.float32))
    assert rows[0].shape == (len(geo.levels), gi.n_rows(geo))
    pts = _uniform(rng, 800)
    pts[::4, 2] = rng.choice([-0.55, -0.45, 0.45, 0.52, 0.3], size=len(pts[::4]))
    queries = np.concatenate([pts[:30], _uniform(rng, 30)])
    queries[::3, 2] = rng.choice([-0.5, 0.49, 0.51, 0.2], size=len(queries[::3]))
    a = _assert_same(cb, _memory(cb, pts), cg, _memory(cg, pts), queries)
    assert a.mask.sum() > len(queries)


@functools.lru_cache(maxsize=None)
def _write_fn(cfg):
    @jax.jit
    def go(m, zs, vs, writes):
        return jax.lax.scan(lambda m, x: (add_scaled(cfg, m, *x), None), m, (zs, vs, writes))[0]
    return go


def _write_all(cfg, pts, vals, width=400):
    """Write pts (n, 3) one by one from an empty memory (padded to width skipped writes: one
    compilation per config)."""
    n = len(pts)
    zs, vs = np.zeros((width, 3), np.float32), np.zeros(width, np.float32)
    zs[:n], vs[:n] = pts, vals
    return _write_fn(cfg)(init_memory(cfg), jnp.asarray(zs), jnp.asarray(vs),
                          jnp.asarray(np.arange(width) < n))


def _written(cfg, pts):
    """The brute-force memory that writing pts (n, 3) one by one leaves, built by hand: the
    first ``capacity`` points ("error"), or point i in slot i % capacity, the last write
    winning (ring buffer)."""
    cap = cfg.capacity
    if cfg.full_policy == "error" or len(pts) <= cap:
        return _memory(cfg, pts[:cap])
    n = len(pts)
    kept = np.empty((cap, pts.shape[1]), np.float32)
    kept[np.arange(n - cap, n) % cap] = pts[n - cap:]     # the last capacity writes
    return _memory(cfg, kept)


def _short_recent_pair(policy="error"):
    """A small memory with a recent list of 16 (merged from 12 pending writes)."""
    return _pair(capacity=120, full_policy=policy, index_recent=16, max_neighbours=8,
                 bandwidth=0.08)


def test_recent_list_overflow_and_saturation_stay_exact():
    """More writes since the last merge than the recent list holds (appended after it), and in
    a ring buffer more than the capacity (saturated: brute force), all without a refresh."""
    rng = np.random.default_rng(9)
    for policy, n_writes in (("error", 150), ("overwrite_oldest", 150), ("overwrite_oldest", 400)):
        cb, cg = _short_recent_pair(policy)
        pts = _uniform(rng, n_writes)
        vals = rng.normal(size=n_writes).astype(np.float32)
        mb, mg = _written(cb, pts), _write_all(cg, pts, vals)
        np.testing.assert_array_equal(np.asarray(mg.points), np.asarray(mb.points))
        assert int(mg.size) == int(mb.size)
        assert int(mg.index.n_new) == min(n_writes, 120 if policy == "error" else 121)
        q = np.concatenate([_uniform(rng, 30), pts[-10:]])
        _assert_same(cb, mb, cg, mg, q)
        merged = refresh_index(cg, mg)                    # >= 3R/4 pending: merges
        assert int(merged.index.n_new) == 0
        _assert_same(cb, mb, cg, merged, q)


def test_refresh_merges_lazily_and_force_always():
    """``refresh_index`` merges from 3/4 of the recent list pending (12 of 16), or always with
    ``force``; exact either way."""
    rng = np.random.default_rng(10)
    cb, cg = _short_recent_pair()
    assert gi.merge_threshold(16) == 12 and gi.merge_threshold(64) == 48
    pts = _uniform(rng, 12)
    zero = np.zeros(12, np.float32)
    mg = _write_all(cg, pts[:10], zero[:10])
    lazy = refresh_index(cg, mg)                              # 10 < 3/4 of 16: nothing to do
    assert int(lazy.index.n_new) == 10
    forced = refresh_index(cg, mg, force=True)
    assert int(forced.index.n_new) == 0
    assert int(refresh_index(cg, _write_all(cg, pts[:11], zero[:11])).index.n_new) == 11
    assert int(refresh_index(cg, _write_all(cg, pts, zero)).index.n_new) == 0     # 12: merged
    mb = _written(cb, pts[:10])
    q = np.concatenate([_uniform(rng, 20), pts[:10] + 0.01])
    for m in (lazy, forced):
        assert _assert_same(cb, mb, cg, m, q).mask.sum() >= 10


def test_scanned_fraction_bounds_what_a_query_reads():
    """index.scanned_fraction (the auto index's guard) is an upper bound of the share of a
    uniformly filled memory in a query's live level-0 rows (measured here by counting the
    table entries of those rows), and it orders a narrow and a wide kernel as the counts do."""
    rng = np.random.default_rng(0)
    shares = {}
    for bw in (0.015, 0.1):
        cfg = HedgerConfig(3, capacity=20_000, bandwidth=bw, neighbour_index="grid")
        b = np.array(gi.default_bounds(cfg))
        pts = rng.uniform(b[:, 0], b[:, 1], (20_000, 4)).astype(np.float32)
        index = jax.jit(functools.partial(gi.build, cfg))(jnp.asarray(pts.T), jnp.int32(20_000))
        geo = gi.geometry(cfg)
        lo, hi = b[:, 0] + 0.3 * (b[:, 1] - b[:, 0]), b[:, 1] - 0.3 * (b[:, 1] - b[:, 0])
        queries = jnp.asarray(rng.uniform(lo, hi, (200, 4)).astype(np.float32))

        def count(starts, z):
            first, last, live = gi.level_rows(geo, z)
            return jnp.sum(jnp.where(live[0], starts[last[0] + 1] - starts[first[0]], 0))

        counts = jax.jit(jax.vmap(count, (None, 0)))(index.starts, queries)
        shares[bw] = float(np.mean(np.asarray(counts))) / 20_000
        assert 0 < shares[bw] <= gi.scanned_fraction(cfg)
    assert shares[0.1] > 10 * shares[0.015]


def test_recent_length_grows_with_the_capacity_and_follows_the_config():
    auto = {n: gi.recent_length(_cfg("grid", capacity=n))
            for n in (500, 20_000, 50_000, 100_000, 300_000, 1_000_000, 4_000_000)}
    assert auto == {500: 500, 20_000: 1024, 50_000: 1024, 100_000: 2048, 300_000: 4096,
                    1_000_000: 8192, 4_000_000: 8192}
    assert gi.recent_length(_cfg("grid", capacity=1_000_000, index_recent=256)) == 256
    assert gi.recent_length(_cfg("grid", capacity=100, index_recent=256)) == 100
    assert gi.geometry(_cfg("grid", capacity=300_000)).recent == 4096
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="index_recent"):
            _cfg("grid", index_recent=bad)


# The ring buffer's one-pass merge in the full suite: its removal of re-merged slots is the
# merge of the ring-buffer tests above (windows of 300 and 120 writes).
@pytest.mark.parametrize("policy", ["error",
                                    pytest.param("overwrite_oldest", marks=pytest.mark.full)])
def test_a_recent_list_longer_than_the_merge_window_merges_in_one_pass_exactly(policy):
    """R > _MERGE_WINDOW: the window is R (``index.merge_window``), so 3R/4 pending writes are
    merged by one pass; the tables then answer as brute force does."""
    rng = np.random.default_rng(12)
    R = 2 * gi._MERGE_WINDOW
    cb, cg = _pair(capacity=4 * gi._MERGE_WINDOW, full_policy=policy, index_recent=R,
                   max_neighbours=8, bandwidth=0.03)
    assert gi.merge_window(gi.geometry(cg), cg.capacity) == R
    n = gi.merge_threshold(R) + 5
    pts, vals = _uniform(rng, n), rng.normal(size=n).astype(np.float32)
    mg = _write_all(cg, pts, vals, width=n)
    merged = refresh_index(cg, mg)
    assert int(mg.index.n_new) == n and int(merged.index.n_new) == 0
    q = np.concatenate([_uniform(rng, 40), pts[-10:], pts[:10]])
    _assert_same(cb, _memory(cb, pts), cg, merged, q)     # the n writes filled slots [0, n)


def test_level_target_grows_with_the_uniform_dimensions():
    """A finer level is used when its rows hold ``level_target`` x k points: 3k with two
    uniform dimensions (discrete actions get one cell per value), 1.5 times more per extra
    uniform dimension (the radius ball fills less of the rows' box); the first wide trip of
    the scan is sized from it."""
    assert gi.level_target(1) == gi.level_target(2) == 3
    assert gi.level_target(3) == 4.5 and gi.level_target(4) == 6.75
    disc = _cfg("grid", capacity=10 ** 5, bandwidth=0.015)
    cont = HedgerConfig(2, 1, action_low=(-1.0,), action_high=(1.0,), capacity=10 ** 5,
                        bandwidth=0.015, max_neighbours=16, neighbour_index="grid")
    assert gi.geometry(disc).target == 3 and gi.geometry(cont).target == 4.5
    assert gi.first_trips(disc) * gi.chunk_width(disc) >= 2 * 3 * 16
    assert gi.first_trips(cont) * gi.chunk_width(cont) >= 2 * 4.5 * 16


#: Continuous actions, three levels, a narrow chunk and a short recent list: the config of
#: the tests that query as the greedy search does (one compiled search for all of them).
_CONTINUOUS = dict(action_low=(-0.2,), action_high=(0.2,), capacity=6000, bandwidth=0.05,
                   max_neighbours=8, index_levels=3, index_chunk=16, index_recent=16)


def _continuous_pair(**kw):
    kw = {**_CONTINUOUS, **kw}
    return (HedgerConfig(2, 1, neighbour_index="brute", **kw),
            HedgerConfig(2, 1, neighbour_index="grid", **kw))


def test_continuous_levels_small_batches_of_candidate_actions_match_brute():
    """Three uniform dimensions (continuous actions) with several levels, queried as the
    greedy search does: 11 candidate actions per state, vmapped, on uniform points plus a
    dense cluster. Some queries choose a finer level whose k nearest are not all within its
    radius (searched again at level 0); every set is exactly brute force's."""
    rng = np.random.default_rng(5)
    cb, cg = _continuous_pair()
    pts = np.concatenate([rng.uniform([0, 0, -0.2], [1, 1, 0.2], (5000, 3)),
                          rng.normal([0.5, 0.5, 0.0], 0.01, (800, 3))]).astype(np.float32)
    mb, mg = _memory(cb, pts), _memory(cg, pts)
    states = np.concatenate([rng.uniform(0, 1, (14, 2)), [[0.5, 0.5], [0.505, 0.49]]])
    acts = np.linspace(-0.2, 0.2, 11)
    q = np.concatenate([np.repeat(states, 11, 0), np.tile(acts, len(states))[:, None]],
                       1).astype(np.float32)
    geo = gi.geometry(cg)
    lv = np.asarray(_probe_fn(cg)(mg, jnp.asarray(q))[0])
    radius = np.array([x.radius for x in geo.levels])[lv]
    d2 = np.sum((pts[None].astype(np.float64) - q[:, None]) ** 2, -1)
    rescanned = (lv > 0) & (np.sum(d2 <= radius[:, None] ** 2, 1) < 8)
    assert np.all(np.bincount(lv, minlength=3) > 10) and rescanned.sum() > 5
    _assert_same(cb, mb, cg, mg, q)
    per_state = jax.jit(jax.vmap(jax.vmap(lambda m, z: select_neighbours(cg, m, z),
                                          (None, 0)), (None, 0)))(
        mg, jnp.asarray(q.reshape(len(states), 11, 3)))
    flat = _select(cg, mg, q)
    np.testing.assert_array_equal(np.asarray(per_state.indices).reshape(-1, 8), flat.indices)
    np.testing.assert_array_equal(np.asarray(per_state.mask).reshape(-1, 8), flat.mask)


def test_recent_buckets_spanning_two_rows_give_each_write_once():
    """Four dimensions (the corridor's geometry): a key bucket of the recent list spans more
    keys than a row, so two rows can share one. Every recent write must be a candidate once:
    K has no repeated slot and is brute force's (a repeated slot was counted twice in the fit,
    seen in the Figure 5 experiment)."""
    kw = dict(action_low=(-1.0,), action_high=(1.0,), capacity=12000, bandwidth=0.05,
              input_offset=(-0.785, -1.0, 0.0, 0.0), input_scale=(0.637, 0.5, 0.0091, 1.0))
    cb = HedgerConfig(3, 1, neighbour_index="brute", **kw)
    cg = HedgerConfig(3, 1, neighbour_index="grid", **kw)
    geo = gi.geometry(cg)
    lv = geo.levels[0]
    assert geo.bucket > 1 and geo.bucket * 2 > lv.cells[lv.contig]     # buckets span rows
    rng = np.random.default_rng(9)
    first = np.asarray(jax.jit(functools.partial(gi.level_rows, geo))(
        jnp.asarray([0.5, 0.5, 0.5, 0.5], jnp.float32))[0])
    assert np.all(np.diff(first[0]) > 0)                    # rows in ascending key order
    s = rng.normal([0.0, 1.0, 50.0], [0.1, 0.2, 10.0], (600, 3)).astype(np.float32)
    a = rng.uniform(-1, 1, (600, 1)).astype(np.float32)
    mb, mg = (jax.jit(functools.partial(add_points, c))(init_memory(c), s, a,
                                                         np.zeros(600, np.float32))
              for c in (cb, cg))
    assert int(mg.index.n_new) == 600                       # all in the recent list
    q = np.concatenate([s[:150] + rng.normal(0, 0.02, (150, 3)).astype(np.float32),
                        rng.uniform(-1, 1, (150, 1)).astype(np.float32)], 1)
    z = jnp.asarray((q - np.asarray(cg.input_offset, np.float32))
                    * np.asarray(cg.input_scale, np.float32))
    got = _select(cg, mg, z)
    for i in range(len(q)):
        real = got.indices[i][got.mask[i]]
        assert len(set(real.tolist())) == len(real), f"query {i}: repeated slot {np.sort(real)}"
    a_ = _assert_same(cb, mb, cg, mg, np.asarray(z))
    assert a_.mask.sum(1).mean() > 3


def _insert_reference(rkeys, order, spoints, L, key, slot, z, count, ins):
    """NumPy: the sorted insertion of one write into the recent list (after equal keys), the
    live columns 0 .. count shifted; columns above count and rows other than L untouched."""
    rkeys, order, spoints = rkeys.copy(), order.copy(), spoints.copy()
    if ins:
        pos = int(np.searchsorted(rkeys[:count], key, side="right"))
        rkeys[:count + 1] = np.insert(rkeys[:count], pos, key)
        order[L, :count + 1] = np.insert(order[L, :count], pos, slot)
        spoints[L, :, :count + 1] = np.insert(spoints[L, :, :count], pos, z, axis=1)
    return rkeys, order, spoints


@pytest.mark.parametrize("R, L, d", [(1, 0, 2), (7, 1, 3), (16, 0, 3), (33, 2, 1), (1024, 1, 3)])
def test_recent_insertion_by_blocks_matches_numpy(R, L, d):
    """The loop-kernel form of the recent list's sorted insertion (moves only the live
    columns, 16 per step, top down; finds the place by a binary search) against NumPy's
    insert: duplicate keys (a new write goes after equal ones), an empty and an almost full
    list, a write that is not inserted."""
    rng = np.random.default_rng(R + 10 * L)
    N = 3 * R + 5
    fn = jax.jit(functools.partial(gi._insert_by_blocks, L))
    counts = sorted({0, R - 1, *rng.integers(0, R, 6).tolist()})
    for trial, count in enumerate(counts * 2):
        sentinel = 99
        rkeys = np.full(R, sentinel, np.int32)
        rkeys[:count] = np.sort(rng.integers(0, 12, count))
        order = rng.integers(0, N, (L + 1, N)).astype(np.int32)
        spoints = rng.normal(size=(L + 1, d, N)).astype(np.float32)
        key = np.int32(rng.integers(0, 12) if trial % 3 else (rkeys[0] if count else 0))
        slot = np.int32(rng.integers(0, N))
        z = rng.normal(size=d).astype(np.float32)
        ins = bool(trial != 3)
        got = fn(rkeys, order, spoints, key, slot, z, np.int32(count), np.bool_(ins))
        want = _insert_reference(rkeys, order, spoints, L, key, slot, z, count, ins)
        for g, w, name in zip(got, want, ("rkeys", "order", "spoints")):
            np.testing.assert_array_equal(np.asarray(g), w, err_msg=f"{name}, count {count}")


def test_recent_insertion_vmapped_uses_the_shift_form_and_agrees(monkeypatch):
    """Under vmap (seeds) the insertion takes the O(R) shift form (one form for every member):
    the same arrays, bit for bit -- columns above the live ones untouched, as the loop form
    leaves them -- as each member's own loop-kernel insertion; a vmap of one member takes the
    loop."""
    calls = []
    shift = gi._insert_by_shift
    monkeypatch.setattr(gi, "_insert_by_shift", lambda *a: calls.append(1) or shift(*a))
    rng = np.random.default_rng(3)
    S, R, L, d, N = 5, 40, 1, 3, 90
    counts = np.array([0, 3, 17, 39, 20], np.int32)
    rkeys = np.full((S, R), 50, np.int32)
    for s, c in enumerate(counts):
        rkeys[s, :c] = np.sort(rng.integers(0, 9, c))
    order = rng.integers(0, N, (S, L + 1, N)).astype(np.int32)
    spoints = rng.normal(size=(S, L + 1, d, N)).astype(np.float32)
    keys = rng.integers(0, 9, S).astype(np.int32)
    slots = rng.integers(0, N, S).astype(np.int32)
    zs = rng.normal(size=(S, d)).astype(np.float32)
    ins = np.array([True, True, False, True, True])
    got = jax.jit(jax.vmap(gi._insert_recent_fn(L)))(rkeys, order, spoints, keys, slots, zs,
                                                      counts, ins)
    assert calls, "the vmapped insertion did not take the shift form"
    for s in range(S):
        want = _insert_reference(rkeys[s], order[s], spoints[s], L, keys[s], slots[s], zs[s],
                                 int(counts[s]), bool(ins[s]))
        own = jax.jit(functools.partial(gi._insert_by_blocks, L))(
            rkeys[s], order[s], spoints[s], keys[s], slots[s], zs[s], counts[s], ins[s])
        for g, w, o in zip(got, want, own):
            np.testing.assert_array_equal(np.asarray(g[s]), w)
            np.testing.assert_array_equal(np.asarray(g[s]), np.asarray(o))
    # One member (a sweep of one seed): its own loop, not the shift form.
    calls.clear()
    blocks = []
    by_blocks = gi._insert_by_blocks
    monkeypatch.setattr(gi, "_insert_by_blocks", lambda *a: blocks.append(1) or by_blocks(*a))
    one = jax.jit(jax.vmap(gi._insert_recent_fn(L)))(*(x[3:4] for x in (
        rkeys, order, spoints, keys, slots, zs, counts, ins)))
    assert blocks and not calls
    want = _insert_reference(rkeys[3], order[3], spoints[3], L, keys[3], slots[3], zs[3],
                             int(counts[3]), True)
    for g, w in zip(one, want):
        np.testing.assert_array_equal(np.asarray(g[0]), w)


def test_writes_with_the_loop_kernel_insertion_stay_exact(monkeypatch):
    """With loop kernels on, single writes use ``_insert_by_blocks``: the grid index still
    returns brute force's neighbours through a ring buffer, skipped writes, merges, a
    recent list that overflows (appends after it) and a saturated index (the config of
    ``_short_recent_pair``: its searches are compiled once)."""
    calls = []
    blocks = gi._insert_by_blocks
    monkeypatch.setattr(gi, "cpu_kernels", lambda: True)
    monkeypatch.setattr(gi, "_insert_by_blocks", lambda *a: calls.append(1) or blocks(*a))
    sizes = [60, 36, 160, 12, 200, 12]
    mg, pending = _run_writes("overwrite_oldest", 120, sum(sizes), sizes, seed=14,
                              index_recent=16)
    assert calls and int(mg.size) == 120
    assert any(16 < n <= 120 for n in pending), pending      # beyond the recent list
    assert max(pending) == 121, pending                       # saturated


@pytest.mark.parametrize("policy, full", [("error", False), ("error", True),
                                          ("overwrite_oldest", False)])
def test_one_query_at_a_time_matches_the_batch_and_brute(policy, full):
    """A query searched alone reads its first trip by contiguous windows
    (``index._first_trip_by_segments``; a vmapped batch counts columns instead): the same
    neighbour sets, bit for bit, as the batch, and brute force's. Several levels, a dense
    cluster and points in the grid's last cells, queried there and at uniform spots; either
    writes pending beyond the recent list (a recent part and the part after it), or a full,
    merged memory, whose last cells' segments end at the arrays' last column (windows that
    would run past it start earlier). Both hold the same points (the error-policy cases
    search with the programs of ``test_continuous_levels_...``). (With ``overwrite_oldest``
    every trip counts columns: the stale-slot test needs each candidate's slot.)"""
    rng = np.random.default_rng(11)
    cb, cg = _continuous_pair(full_policy=policy)
    assert len(gi.geometry(cg).levels) == 3
    n_late = 40
    corner = rng.uniform([0.98, 0.98, 0.19], [1.0, 1.0, 0.2], (60, 3))
    n_uniform = cg.capacity - n_late - 300 - len(corner)
    pts = np.concatenate([rng.uniform([0, 0, -0.2], [1, 1, 0.2], (n_uniform, 3)),
                          rng.normal([0.5, 0.5, 0.0], 0.01, (300, 3)), corner]
                         ).astype(np.float32)
    late = rng.uniform([0, 0, -0.2], [1, 1, 0.2], (n_late, 3)).astype(np.float32)
    mb = _memory(cb, np.concatenate([pts, late]))
    if full:                                         # every point indexed
        mg = _memory(cg, np.concatenate([pts, late]))
    else:                                            # the late writes pending
        writes, vals = jnp.ones(n_late, bool), jnp.zeros(n_late, jnp.float32)
        mg = _write_fn(cg)(_memory(cg, pts), jnp.asarray(late), vals, writes)
    np.testing.assert_array_equal(np.asarray(mg.points), np.asarray(mb.points))
    assert int(mg.size) == cg.capacity
    assert int(mg.index.n_new) == (0 if full else n_late)   # 16 in the recent list, 24 after
    q = np.concatenate([corner[:30] + 0.001, pts[n_uniform:n_uniform + 30], late[:20],
                        rng.uniform([0, 0, -0.2], [1, 1, 0.2], (40, 3))]).astype(np.float32)
    alone = _select(cg, mg, q, fn=_alone_fn)
    batch = _select(cg, mg, q)
    for name, a, b in zip(batch._fields, alone, batch):
        np.testing.assert_array_equal(a, b, err_msg=f"{name}: alone != batch")
    _assert_same(cb, mb, cg, mg, q)


# 60,000 slots (every level at full resolution) in the full suite: at 3,000 the same seven
# levels' radii are searched, the finest two with a coarsened contiguous dimension.
@pytest.mark.parametrize("capacity", [3000, pytest.param(60_000, marks=pytest.mark.full)])
def test_a_traced_radius_below_the_bound_gives_brute_forces_sets(capacity):
    """With ``max_bandwidth`` above ``bandwidth`` the index keeps a level for every radius
    between them; a query with a traced k_thresh in that range is answered from the finest
    level that covers it (or a finer one whose rows hold enough points): exactly brute
    force's K at that radius, for radii at, between and above the levels'."""
    from hedger_jax.params import HedgerParams

    rng = np.random.default_rng(31)
    cb, cg = _pair(capacity=capacity, bandwidth=0.01, max_bandwidth=0.08, max_neighbours=16)
    geo = gi.geometry(cg)
    radii = [lv.radius for lv in geo.levels]
    assert radii[0] == pytest.approx(cg.max_k_thresh)
    assert min(radii) <= cg.k_thresh * (1 + 1e-9) and len(radii) >= 6
    n = capacity // 2
    pts = _uniform(rng, n)
    pts[: n // 4, :2] = 0.3 + 0.02 * rng.standard_normal((n // 4, 2))     # a dense cluster
    mb, mg = _memory(cb, pts), _memory(cg, pts)
    queries = jnp.asarray(np.concatenate([_uniform(rng, 40), pts[:20] + 0.001]))
    def sel(cfg):
        return jax.jit(jax.vmap(lambda m, z, p: select_neighbours(cfg, m, z, p),
                                in_axes=(None, 0, None)))

    sel_b, sel_g = sel(cb), sel(cg)
    for h in (0.01, 0.013, 0.02, 0.0317, 0.05, 0.08):
        params = HedgerParams.create(cg, bandwidth=h)
        a = jax.device_get(sel_b(mb, queries, params))
        b = jax.device_get(sel_g(mg, queries, params))
        for i in range(queries.shape[0]):
            da, db = np.sort(a.sqdist[i][a.mask[i]]), np.sort(b.sqdist[i][b.mask[i]])
            np.testing.assert_array_equal(da, db, err_msg=f"h={h} query {i}")
        assert np.asarray(a.mask).sum() > 0
    assert int(gi.covering_level(geo, jnp.float32(radii[-1]))) == len(radii) - 1
    assert int(gi.covering_level(geo, jnp.float32(radii[0]))) == 0
    assert int(gi.covering_level(geo, jnp.float32(radii[2] * 0.99))) == 2
