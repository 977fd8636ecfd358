"""The fixed-capacity Memory pytree: init, bulk insert, flags, full policies, masking."""
import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, MemoryFullError, NonFiniteValueError, add_points,  # noqa: E402
                        init_memory, memory_check, predict_detailed)
from hedger_np_ref import f32, replace_fields  # noqa: E402

FLAG_FULL = 1
FLAG_NONFINITE = 2

CFG = HedgerConfig(2, 1, capacity=8, bandwidth=0.1)
CFG_RING = HedgerConfig(2, 1, capacity=4, bandwidth=0.1, full_policy="overwrite_oldest")
CFG_MASK = HedgerConfig(1, 1, capacity=16, bandwidth=0.1, max_neighbours=8)

_add_jit = jax.jit(functools.partial(add_points, CFG))
_pd_mask = jax.jit(functools.partial(predict_detailed, CFG_MASK))


def _data(n, seed=0, dim_s=2, dim_a=1):
    rng = np.random.default_rng(seed)
    return (f32(rng.uniform(0, 1, (n, dim_s))), f32(rng.uniform(-1, 1, (n, dim_a))),
            f32(rng.standard_normal(n)))


def _np(mem):
    return {k: np.asarray(getattr(mem, k)) for k in ("points", "values", "size", "head", "flags")}


def test_init_memory_shapes_and_dtypes():
    """An empty memory: zeroed (d, capacity) points and (capacity,) values, size = head =
    flags = 0, no index with brute force; a pytree whose leaves are exactly those arrays."""
    m = init_memory(CFG)
    assert m.points.shape == (3, 8) and m.points.dtype == jnp.float32
    assert m.values.shape == (8,) and m.values.dtype == jnp.float32
    assert not np.any(np.asarray(m.points)) and not np.any(np.asarray(m.values))
    for f in ("size", "head", "flags"):
        x = getattr(m, f)
        assert x.shape == () and x.dtype == jnp.int32 and int(x) == 0
    assert m.index is None and CFG.index_kind == "brute"
    leaves = jax.tree_util.tree_leaves(m)
    assert len(leaves) == 5
    assert all(x is y for x, y in zip(leaves, (m.points, m.values, m.size, m.head, m.flags)))


def test_add_points_stores_columns_and_counts():
    s, a, v = _data(5)
    m = add_points(CFG, init_memory(CFG), s, a, v)
    np.testing.assert_array_equal(np.asarray(m.points)[:, :5], np.concatenate([s, a], 1).T)
    np.testing.assert_array_equal(np.asarray(m.values)[:5], v)
    assert int(m.size) == 5 and int(m.head) == 5 and int(m.flags) == 0
    s2, a2, v2 = _data(2, seed=1)
    m2 = add_points(CFG, m, s2, a2, v2)
    assert int(m2.size) == 7 and int(m2.head) == 7 and int(m2.flags) == 0
    np.testing.assert_array_equal(np.asarray(m2.points)[:, :5], np.asarray(m.points)[:, :5])
    np.testing.assert_array_equal(np.asarray(m2.points)[:, 5:7], np.concatenate([s2, a2], 1).T)
    np.testing.assert_array_equal(np.asarray(m2.values)[5:7], v2)
    memory_check(m2)  # clean memory: no exception


def test_add_points_jitted_equals_unjitted():
    s, a, v = _data(3, seed=4)
    m0 = add_points(CFG, init_memory(CFG), s[:1], a[:1], v[:1])
    mj = _add_jit(m0, s, a, v)
    mu = add_points(CFG, m0, s, a, v)
    for k, x in _np(mj).items():
        np.testing.assert_array_equal(x, _np(mu)[k], err_msg=k)


def test_full_memory_error_policy_keeps_data_and_flags():
    s, a, v = _data(8, seed=2)
    m = add_points(CFG, init_memory(CFG), s, a, v)
    assert int(m.size) == 8 and int(m.flags) == 0
    memory_check(m)  # exactly full is not an error
    before = _np(m)
    s2, a2, v2 = _data(3, seed=3)
    m2 = add_points(CFG, m, s2, a2, v2)
    after = _np(m2)
    np.testing.assert_array_equal(after["points"], before["points"])
    np.testing.assert_array_equal(after["values"], before["values"])
    assert int(m2.size) == 8
    assert int(m2.flags) & FLAG_FULL
    with pytest.raises(MemoryFullError):
        memory_check(m2)
    # also under jit
    m3 = _add_jit(m, s2, a2, v2)
    np.testing.assert_array_equal(np.asarray(m3.points), before["points"])
    np.testing.assert_array_equal(np.asarray(m3.values), before["values"])
    assert int(m3.flags) & FLAG_FULL


def test_partial_overflow_keeps_existing_data():
    s, a, v = _data(6, seed=5)
    m = add_points(CFG, init_memory(CFG), s, a, v)
    s2, a2, v2 = _data(4, seed=6)
    m2 = add_points(CFG, m, s2, a2, v2)
    np.testing.assert_array_equal(np.asarray(m2.points)[:, :6], np.asarray(m.points)[:, :6])
    np.testing.assert_array_equal(np.asarray(m2.values)[:6], v)
    assert 6 <= int(m2.size) <= 8
    assert int(m2.flags) & FLAG_FULL
    with pytest.raises(MemoryFullError):
        memory_check(m2)


def test_nonfinite_value_sets_flag():
    s, a, v = _data(3, seed=7)
    v = v.copy()
    v[1] = np.nan
    m = add_points(CFG, init_memory(CFG), s, a, v)
    assert int(m.flags) & FLAG_NONFINITE
    assert not int(m.flags) & FLAG_FULL
    with pytest.raises(NonFiniteValueError):
        memory_check(m)
    v[1] = np.inf
    m = _add_jit(init_memory(CFG), s, a, v)
    assert int(m.flags) & FLAG_NONFINITE


def test_overwrite_oldest_is_a_ring_buffer():
    s, a, v = _data(6, seed=8)
    m = add_points(CFG_RING, init_memory(CFG_RING), s[:4], a[:4], v[:4])
    assert int(m.size) == 4 and int(m.head) % 4 == 0
    m = add_points(CFG_RING, m, s[4:5], a[4:5], v[4:5])
    m = add_points(CFG_RING, m, s[5:6], a[5:6], v[5:6])
    assert int(m.size) == 4 and int(m.head) == 2 and int(m.flags) == 0
    memory_check(m)
    z = np.concatenate([s, a], 1)
    expect_order = [4, 5, 2, 3]
    np.testing.assert_array_equal(np.asarray(m.points), z[expect_order].T)
    np.testing.assert_array_equal(np.asarray(m.values), v[expect_order])


def test_overwrite_oldest_bulk_insert_wraps():
    s, a, v = _data(7, seed=9)
    m = add_points(CFG_RING, init_memory(CFG_RING), s[:3], a[:3], v[:3])
    m = add_points(CFG_RING, m, s[3:7], a[3:7], v[3:7])  # 3 + 4 = 7 > 4
    z = np.concatenate([s, a], 1)
    expect_order = [4, 5, 6, 3]
    assert int(m.size) == 4 and int(m.head) == 3 and int(m.flags) == 0
    np.testing.assert_array_equal(np.asarray(m.points), z[expect_order].T)
    np.testing.assert_array_equal(np.asarray(m.values), v[expect_order])


def test_empty_slots_never_become_neighbours():
    cfg = CFG_MASK
    m = init_memory(cfg)
    zq = np.array([0.0, 0.0], np.float32)  # the origin: where zero-initialised slots sit
    p0 = _pd_mask(m, jnp.asarray(zq[:1]), jnp.asarray(zq[1:]))
    assert int(p0.n_neighbours) == 0 and not bool(p0.known)
    assert float(p0.value) == cfg.default_value and not np.any(np.asarray(p0.mask))
    # five real points near the origin
    pts = f32([[0.01, 0.0], [-0.01, 0.01], [0.0, -0.01], [0.02, 0.02], [-0.02, -0.015]])
    m = add_points(cfg, m, pts[:, :1], pts[:, 1:], f32(np.full(5, 3.0)))
    p = _pd_mask(m, jnp.asarray(zq[:1]), jnp.asarray(zq[1:]))
    mask = np.asarray(p.mask)
    assert int(p.n_neighbours) == 5 and int(mask.sum()) == 5
    assert set(np.asarray(p.indices)[mask].tolist()) == {0, 1, 2, 3, 4}
    assert bool(p.known) and float(p.value) == pytest.approx(3.0, rel=1e-5)
    # garbage beyond `size` (slots 5..9 right on the query with a wild value) is ignored
    pts2 = f32(np.zeros((5, 2)))
    m2 = add_points(cfg, m, pts2[:, :1], pts2[:, 1:], f32(np.full(5, -1000.0)))
    m2 = replace_fields(m2, size=jnp.int32(5), head=jnp.int32(5))
    p2 = _pd_mask(m2, jnp.asarray(zq[:1]), jnp.asarray(zq[1:]))
    mask2 = np.asarray(p2.mask)
    assert int(p2.n_neighbours) == 5
    assert set(np.asarray(p2.indices)[mask2].tolist()) == {0, 1, 2, 3, 4}
    assert float(p2.value) == pytest.approx(3.0, rel=1e-5)


def test_prediction_arrays_have_max_neighbours_entries_even_when_capacity_is_smaller():
    """The API: indices/weights/mask are (max_neighbours,) whatever the capacity."""
    cfg = HedgerConfig(1, 1, capacity=6, bandwidth=0.1, max_neighbours=10)
    pts = f32([[0.01, 0.0], [-0.01, 0.01], [0.0, -0.01], [0.02, 0.02], [-0.02, -0.015]])
    m = add_points(cfg, init_memory(cfg), pts[:, :1], pts[:, 1:], f32(np.full(5, 3.0)))
    p = jax.jit(functools.partial(predict_detailed, cfg))(m, jnp.zeros((1,), jnp.float32),
                                                           jnp.zeros((1,), jnp.float32))
    assert bool(p.known) and int(p.n_neighbours) == 5
    assert float(p.value) == pytest.approx(3.0, rel=1e-5)
    mask = np.asarray(p.mask)
    assert set(np.asarray(p.indices)[mask].tolist()) == {0, 1, 2, 3, 4}
    assert p.indices.shape == p.weights.shape == p.mask.shape == (10,)


@pytest.mark.parametrize("kind", ["brute", "grid"])
def test_neighbours_come_in_canonical_order_by_slot(kind):
    """K is reported as the real neighbours by ascending slot, then the padding, with each
    slot's own squared distance (a float64 NumPy brute force gives the set)."""
    cfg = HedgerConfig(2, 1, capacity=64, bandwidth=0.1, max_neighbours=8,
                       neighbour_index=kind)
    rng = np.random.default_rng(3)
    s, a, v = _data(60, seed=3)
    m = add_points(cfg, init_memory(cfg), s, a, v)
    from hedger_jax.memory import refresh_index, select_neighbours
    m = refresh_index(cfg, m)
    pts = np.asarray(m.points, np.float64)[:, :60]
    select = jax.jit(functools.partial(select_neighbours, cfg))
    for q in rng.uniform([0, 0, -1], [1, 1, 1], (20, 3)).astype(np.float32):
        nb = select(m, jnp.asarray(q))
        mask, idx, d2 = (np.asarray(x) for x in (nb.mask, nb.indices, nb.sqdist))
        n = int(mask.sum())
        assert mask[:n].all() and not mask[n:].any()        # real neighbours first
        assert np.all(np.diff(idx[:n]) > 0)                 # by ascending slot
        ref = np.sum((pts - q.astype(np.float64)[:, None]) ** 2, axis=0)
        within = np.flatnonzero(ref <= cfg.k_thresh ** 2)
        expect = within[np.argsort(ref[within], kind="stable")][:8]
        assert set(idx[:n].tolist()) == set(expect.tolist())
        np.testing.assert_allclose(d2[:n], ref[idx[:n]], rtol=1e-5, atol=1e-7)


def _lattice_memory(cfg, n, rng):
    """A memory of cfg holding n points on a 1/64 lattice in [0, 1]^3 (exact float32 squared
    distances, so many ties) with values of a smooth function, its other slots empty."""
    from hedger_jax.memory import init_memory as _init
    pts = np.zeros((3, cfg.capacity), np.float32)
    pts[:, :n] = rng.integers(0, 65, (3, n)) / np.float32(64)
    vals = np.zeros(cfg.capacity, np.float32)
    vals[:n] = np.sin(3 * pts[0, :n]) + pts[1, :n] - pts[2, :n] ** 2
    return _init(cfg)._replace(points=jnp.asarray(pts), values=jnp.asarray(vals),
                               size=jnp.int32(n), head=jnp.int32(n % cfg.capacity))


def test_brute_force_in_blocks_finds_the_nearest_stored_points():
    """A brute-force memory larger than two blocks is read block by block up to its stored
    points (``_nearest_in_blocks``): K equals a float64 NumPy brute force's (the nearest
    ``max_neighbours`` within the threshold, ties to the lower slot) at sizes of 0, part of
    one block, exactly one, two, and three with the last block moved back over the second;
    the same under vmap over memories of different sizes; and predictions, with their
    gradients w.r.t. the query and the stored values, equal bit for bit those of a memory
    small enough for the one-pass search holding the same points."""
    from hedger_jax.memory import BRUTE_BLOCK, select_neighbours
    from hedger_jax.prediction import predict_scaled
    cap = 2 * BRUTE_BLOCK + 904
    cfg = HedgerConfig(2, 1, capacity=cap, bandwidth=0.03, max_neighbours=8,
                       neighbour_index="brute")
    rng = np.random.default_rng(11)
    select = jax.jit(jax.vmap(lambda m, z: select_neighbours(cfg, m, z), in_axes=(None, 0)))
    zs = (rng.integers(0, 65, (24, 3)) / np.float32(64)).astype(np.float32)
    zs[:4] += np.float32(1 / 128)                     # between lattice points: more ties
    mems = {}
    for n in (0, 700, BRUTE_BLOCK, 3000, cap - 300, cap):
        m = mems[n] = _lattice_memory(cfg, n, rng)
        nb = select(m, jnp.asarray(zs))
        pts = np.asarray(m.points, np.float64)[:, :n]
        for q, idx, mask in zip(zs, np.asarray(nb.indices), np.asarray(nb.mask)):
            d2 = np.sum((pts - q.astype(np.float64)[:, None]) ** 2, axis=0)
            order = np.lexsort((np.arange(n), d2))[:8]          # by distance, then slot
            expect = np.sort(order[d2[order] <= cfg.k_thresh ** 2])
            np.testing.assert_array_equal(idx[mask], expect, err_msg=f"size {n}")
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), mems[3000], mems[cap - 300])
    vsel = jax.jit(jax.vmap(lambda m: jax.vmap(lambda z: select_neighbours(cfg, m, z))(
        jnp.asarray(zs))))(both)
    for i, n in enumerate((3000, cap - 300)):
        alone = select(mems[n], jnp.asarray(zs))
        np.testing.assert_array_equal(np.asarray(vsel.indices[i])[np.asarray(alone.mask)],
                                      np.asarray(alone.indices)[np.asarray(alone.mask)])
    small = HedgerConfig(2, 1, capacity=2 * BRUTE_BLOCK, bandwidth=0.03, max_neighbours=8,
                         neighbour_index="brute")
    m_small = mems[3000]._replace(points=mems[3000].points[:, :small.capacity],
                                  values=mems[3000].values[:small.capacity])

    def value_and_grads(c, m):
        def value(z, values):
            return predict_scaled(c, m._replace(values=values), z).value
        return jax.jit(jax.vmap(jax.value_and_grad(value, argnums=(0, 1)),
                                in_axes=(0, None)))(jnp.asarray(zs), m.values)

    (v_big, (gz_big, gv_big)), (v_small, (gz_small, gv_small)) = (
        value_and_grads(cfg, mems[3000]), value_and_grads(small, m_small))
    assert np.isfinite(np.asarray(v_big)).all() and np.abs(np.asarray(gz_big)).sum() > 0
    np.testing.assert_array_equal(np.asarray(v_big), np.asarray(v_small))
    np.testing.assert_array_equal(np.asarray(gz_big), np.asarray(gz_small))
    np.testing.assert_array_equal(np.asarray(gv_big)[:, :small.capacity], np.asarray(gv_small))
