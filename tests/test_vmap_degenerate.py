"""Batching (jit of vmap over memories, queries and candidate actions) equals separate calls;
degenerate memories give finite answers, jitted and not."""
import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, Transition, add_points, greedy_action,  # noqa: E402
                        init_memory, predict, predict_detailed, train_step)
from hedger_jax.memory import add_scaled  # noqa: E402
from hedger_np_ref import f32, ref_predict  # noqa: E402

# ------------------------------------------------------------------ batching
CFG_V = HedgerConfig(2, 1, capacity=64, bandwidth=0.15, max_neighbours=16,
                     discrete_actions=((-0.05,), (0.0,), (0.05,)), default_value=0.1,
                     action_low=(-0.1,), action_high=(0.1,))
_add_v = jax.jit(functools.partial(add_points, CFG_V))
_pred_v = jax.jit(functools.partial(predict, CFG_V))
_step_v = jax.jit(functools.partial(train_step, CFG_V))
_vm_pred = jax.jit(jax.vmap(functools.partial(predict, CFG_V)))
_vm_step = jax.jit(jax.vmap(functools.partial(train_step, CFG_V)))
_vq_pred = jax.jit(jax.vmap(functools.partial(predict, CFG_V), in_axes=(None, 0, 0)))
_va_pred = jax.jit(jax.vmap(functools.partial(predict, CFG_V), in_axes=(None, None, 0)))
_vmq_pred = jax.jit(jax.vmap(jax.vmap(functools.partial(predict, CFG_V), in_axes=(None, 0, 0)),
                             in_axes=(0, None, None)))


def _stack(trees):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *trees)


def _index(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@pytest.fixture(scope="module")
def three_memories():
    mems, datas = [], []
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        S = f32(rng.uniform(0.0, 0.3, (50, 2)))
        A = f32(rng.uniform(-0.1, 0.1, (50, 1)))
        V = f32(seed + 0.3 + S[:, 0] - 2 * S[:, 1] + A[:, 0] + 0.01 * rng.standard_normal(50))
        mems.append(_add_v(init_memory(CFG_V), S, A, V))
        datas.append((S, A, V))
    return mems, datas


def _close(a, b, rtol=1e-5, atol=1e-6):
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=rtol,
                               atol=atol)


def test_vmap_predict_over_memories_equals_separate_calls(three_memories):
    mems, datas = three_memories
    S = f32([[0.15, 0.15], [0.1, 0.2], [0.35, 0.1]])
    A = f32([[0.0], [0.03], [0.0]])
    v, k, n = _vm_pred(_stack(mems), jnp.asarray(S), jnp.asarray(A))
    assert v.shape == (3,)
    for i in range(3):
        vi, ki, ni = _pred_v(mems[i], jnp.asarray(S[i]), jnp.asarray(A[i]))
        assert bool(k[i]) == bool(ki) and int(n[i]) == int(ni)
        _close(v[i], vi)
        Si, Ai, Vi = datas[i]
        r = ref_predict(np.concatenate([Si, Ai], 1), Vi, 50, np.concatenate([S[i], A[i]]),
                        bandwidth=CFG_V.bandwidth, k_min=CFG_V.k_min,
                        max_neighbours=CFG_V.max_neighbours, default_value=0.1)
        assert not r.ambiguous and r.known == bool(ki)
        assert float(vi) == pytest.approx(r.value, rel=2e-4, abs=2e-4)
    assert bool(k[0]) and bool(k[1])  # two interior queries


def test_vmap_train_step_over_memories_equals_separate_calls(three_memories):
    mems, _ = three_memories
    trs = [Transition(obs=jnp.asarray(f32([0.15, 0.1 + 0.05 * i])),
                      action=jnp.asarray(f32([0.01 * i])), reward=jnp.float32(0.5 * i),
                      next_obs=jnp.asarray(f32([0.16, 0.1 + 0.05 * i])),
                      terminated=jnp.bool_(i == 2), valid=jnp.bool_(True))
           for i in range(3)]
    m_b, info_b = _vm_step(_stack(mems), _stack(trs))
    for i in range(3):
        m_i, info_i = _step_v(mems[i], trs[i])
        mb = _index(m_b, i)
        np.testing.assert_array_equal(np.asarray(mb.points), np.asarray(m_i.points))
        _close(mb.values, m_i.values)
        for f in ("size", "head", "flags"):
            assert int(getattr(mb, f)) == int(getattr(m_i, f))
        for f in ("q", "q_next", "q_new"):
            _close(getattr(info_b, f)[i], getattr(info_i, f))
        assert bool(info_b.known[i]) == bool(info_i.known)


def test_vmap_over_queries_and_candidate_actions(three_memories):
    mems, _ = three_memories
    mem = mems[0]
    rng = np.random.default_rng(0)
    S = f32(rng.uniform(-0.02, 0.32, (16, 2)))
    A = f32(rng.uniform(-0.12, 0.12, (16, 1)))
    v, k, n = _vq_pred(mem, jnp.asarray(S), jnp.asarray(A))
    for j in range(16):
        vj, kj, nj = _pred_v(mem, jnp.asarray(S[j]), jnp.asarray(A[j]))
        assert bool(k[j]) == bool(kj) and int(n[j]) == int(nj)
        _close(v[j], vj)
    # candidate actions for one state
    s = jnp.asarray(f32([0.15, 0.15]))
    cand = f32(np.linspace(-0.1, 0.1, 16)[:, None])
    v, k, n = _va_pred(mem, s, jnp.asarray(cand))
    for j in range(16):
        vj, kj, nj = _pred_v(mem, s, jnp.asarray(cand[j]))
        assert bool(k[j]) == bool(kj) and int(n[j]) == int(nj)
        _close(v[j], vj)
    assert bool(np.all(np.asarray(k)[4:12]))  # interior actions are known
    # nested: memories x queries
    vv, kk, nn = _vmq_pred(_stack(mems), jnp.asarray(S), jnp.asarray(A))
    assert vv.shape == (3, 16)
    for i in range(3):
        vi, ki, ni = _vq_pred(mems[i], jnp.asarray(S), jnp.asarray(A))
        _close(vv[i], vi)
        np.testing.assert_array_equal(np.asarray(kk[i]), np.asarray(ki))
        np.testing.assert_array_equal(np.asarray(nn[i]), np.asarray(ni))


# ------------------------------------------------------------------ degenerate memories
CFG_G = HedgerConfig(1, 1, capacity=16, bandwidth=0.1, k_min=3, max_neighbours=8,
                     default_value=-0.5)
_pred_g = jax.jit(functools.partial(predict_detailed, CFG_G))
_step_g = jax.jit(functools.partial(train_step, CFG_G))
_greedy_g = jax.jit(functools.partial(greedy_action, CFG_G))


@jax.jit
def _fill_g(Z, V, n):
    """CFG_G's memory holding the first n rows of Z (capacity, 2), values V, written one by
    one (``add_scaled``, as ``add_points`` does with the identity scaling): one program for
    every n."""
    def write(m, x):
        return add_scaled(CFG_G, m, *x), None

    writes = jnp.arange(Z.shape[0]) < n
    return jax.lax.scan(write, init_memory(CFG_G), (Z, V, writes))[0]


def _mem_g(Z, V):
    Z, V = f32(np.reshape(Z, (-1, 2))), f32(V)
    n, pad = len(V), CFG_G.capacity - len(V)
    mem = _fill_g(np.pad(Z, ((0, pad), (0, 0))), np.pad(V, (0, pad)), n)
    assert int(mem.size) == n and int(mem.flags) == 0
    return mem


def _both(mem, zq):
    """predict_detailed jitted and not; both must be finite and agree."""
    s, a = jnp.asarray(f32(zq[:1])), jnp.asarray(f32(zq[1:]))
    pj = _pred_g(mem, s, a)
    pu = predict_detailed(CFG_G, mem, s, a)
    for p in (pj, pu):
        assert np.isfinite(float(p.value))
        assert np.all(np.isfinite(np.asarray(p.weights)))
    assert bool(pj.known) == bool(pu.known)
    assert int(pj.n_neighbours) == int(pu.n_neighbours)
    assert float(pj.value) == pytest.approx(float(pu.value), rel=1e-4, abs=1e-6)
    if not bool(pj.known):
        assert float(pj.value) == CFG_G.default_value
    return pj


def _ref_g(Z, V, zq):
    return ref_predict(np.reshape(Z, (-1, 2)), V, len(V), np.asarray(zq, np.float64),
                       bandwidth=CFG_G.bandwidth, k_min=CFG_G.k_min,
                       max_neighbours=CFG_G.max_neighbours, default_value=CFG_G.default_value)


def _train_finite(mem, zq):
    tr = Transition(obs=jnp.asarray(f32(zq[:1])), action=jnp.asarray(f32(zq[1:])),
                    reward=jnp.float32(1.0), next_obs=jnp.asarray(f32(zq[:1])),
                    terminated=jnp.bool_(False), valid=jnp.bool_(True))
    m2, info = _step_g(mem, tr)
    n = int(m2.size)
    assert np.all(np.isfinite(np.asarray(m2.values)[:n]))
    for f in info:
        assert np.all(np.isfinite(np.asarray(f, np.float64)))
    assert int(m2.flags) == 0
    a, v, k = _greedy_g(mem, jnp.asarray(f32(zq[:1])), jax.random.PRNGKey(0))
    assert np.all(np.isfinite(np.asarray(a))) and np.isfinite(float(v))
    assert -1.0 <= float(a[0]) <= 1.0


# ~40 s: in the full suite (HEDGER_JAX_FULL_TESTS=1); tests/test_determinism.py checks vmap over
# seeds on every run, this one the continuous grid trace that once failed.
@pytest.mark.full
def test_vmapped_continuous_grid_training_equals_separate_runs():
    """``jax.vmap(train)`` over seeds, continuous actions, grid index: traces (it failed to:
    the exploration's ``lax.cond`` broadcast an array constant into a custom_vmap function,
    see ``kselect._before``) and gives each seed's own run."""
    import envs
    from hedger_jax.agent import RunConfig, make_train

    env = envs.make("mountain_car_continuous")
    cfg = HedgerConfig.for_env(env, capacity=600, neighbour_index="grid")
    run = RunConfig(n_blocks=1, episodes_per_block=2, eval_episodes=2, eval_max_steps=30,
                    train_max_steps=40)
    train = make_train(env, cfg, run).train
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    batched = jax.jit(jax.vmap(train))(keys)
    single = jax.jit(train)
    for i in range(2):
        for x, y in zip(jax.tree_util.tree_leaves(single(keys[i])),
                        jax.tree_util.tree_leaves(batched)):
            x, y = np.asarray(x), np.asarray(y)[i]
            if np.issubdtype(x.dtype, np.floating):
                np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
            else:
                np.testing.assert_array_equal(x, y)
    assert int(np.asarray(batched[0].memory.size).min()) > 0


def test_empty_memory():
    mem = _mem_g(np.zeros((0, 2)), [])
    for zq in ([0.0, 0.0], [0.5, 0.5]):
        p = _both(mem, np.array(zq))
        assert not bool(p.known) and int(p.n_neighbours) == 0
        assert not np.any(np.asarray(p.mask))
        _train_finite(mem, np.array(zq))


def test_one_point():
    Z, V = [[0.5, 0.5]], [2.0]
    mem = _mem_g(Z, V)
    for zq in ([0.5, 0.5], [0.55, 0.5]):
        p = _both(mem, np.array(zq))
        assert not bool(p.known) and int(p.n_neighbours) == 1
        _train_finite(mem, np.array(zq))


def test_duplicated_points():
    Z, V = np.tile([0.5, 0.5], (6, 1)), np.full(6, 2.0)
    mem = _mem_g(Z, V)
    p = _both(mem, np.array([0.5, 0.5]))  # on the point: the hull is that point
    assert int(p.n_neighbours) == 6
    if bool(p.known):
        assert float(p.value) == pytest.approx(2.0, rel=1e-4)
    p = _both(mem, np.array([0.53, 0.5]))  # off the point: outside the (degenerate) hull
    assert int(p.n_neighbours) == 6 and not bool(p.known)
    for zq in ([0.5, 0.5], [0.53, 0.5]):
        _train_finite(mem, np.array(zq))


def test_duplicated_points_with_different_values():
    Z, V = np.tile([0.3, 0.7], (5, 1)), [1.0, 2.0, 3.0, 4.0, 5.0]
    mem = _mem_g(Z, V)
    p = _both(mem, np.array([0.3, 0.7]))
    if bool(p.known):
        assert float(p.value) == pytest.approx(3.0, rel=1e-4)
    _train_finite(mem, np.array([0.3, 0.7]))


def test_collinear_points():
    t = np.linspace(0.0, 1.0, 8)
    Z = np.stack([0.4 + 0.2 * t, 0.4 + 0.2 * t], 1)
    V = 1.0 + 2.0 * Z[:, 0] + 3.0 * Z[:, 1]
    Zf, Vf = f32(Z), f32(V)
    mem = _mem_g(Zf, Vf)
    # on the line, between points: inside the (flat) hull, exact linear interpolation
    for zq in ([0.5, 0.5], [0.43, 0.43]):
        r = _ref_g(Zf, Vf, zq)
        assert r.known and not r.ambiguous
        p = _both(mem, np.array(zq))
        assert bool(p.known)
        assert float(p.value) == pytest.approx(1.0 + 5.0 * zq[0], rel=1e-4)
    # off the line, or on it beyond the end: outside the hull
    for zq in ([0.52, 0.48], [0.66, 0.66]):
        r = _ref_g(Zf, Vf, zq)
        assert r.n >= CFG_G.k_min and not r.known
        p = _both(mem, np.array(zq))
        assert not bool(p.known)
    for zq in ([0.5, 0.5], [0.52, 0.48]):
        _train_finite(mem, np.array(zq))


def _cloud(seed=0, n=12):
    rng = np.random.default_rng(seed)
    return f32(rng.uniform(0.45, 0.55, (n, 2)))


@pytest.mark.parametrize("scale", [1e30, 1e20, 1e-20, 1e-30])
def test_huge_and_tiny_values(scale):
    Z = _cloud(1)
    base = 1.0 + Z[:, 0].astype(np.float64) - 0.5 * Z[:, 1]
    V = f32(scale * base)
    mem = _mem_g(Z, V)
    zq = np.array([0.5, 0.5])
    r = _ref_g(Z, V.astype(np.float64), zq)
    assert r.known and not r.ambiguous
    p = _both(mem, zq)
    assert bool(p.known)
    assert float(p.value) == pytest.approx(r.value, rel=1e-3)
    assert float(p.value) == pytest.approx(scale * (1.0 + 0.5 - 0.25), rel=1e-3)
    _train_finite(mem, zq)


def test_mixed_huge_and_tiny_values_in_one_neighbourhood():
    """Values 1e20 and 1e-20 side by side: the fit is still the float64 reference's."""
    Z = _cloud(2)
    V = np.where(np.arange(len(Z)) % 2 == 0, 1e20, 1e-20)
    mem = _mem_g(Z, V)
    zq = np.array([0.5, 0.5])
    r = _ref_g(Z, V, zq)
    assert r.known and not r.ambiguous
    p = _both(mem, zq)
    assert bool(p.known) and int(p.n_neighbours) == r.n
    assert float(p.value) == pytest.approx(r.value, rel=1e-3)
    _train_finite(mem, zq)


def test_very_close_points_tiny_spread():
    """Neighbourhood spread 1e-4 (uncentred float32 normal equations go NaN around 1e-3)."""
    rng = np.random.default_rng(3)
    Z = f32(0.5 + 1e-4 * rng.uniform(-1, 1, (10, 2)))
    V = f32(2.0 + 100.0 * (Z[:, 0].astype(np.float64) - 0.5))
    mem = _mem_g(Z, V)
    zq = Z.astype(np.float64).mean(0)
    p = _both(mem, zq)
    r = _ref_g(Z, V.astype(np.float64), zq)
    assert r.known
    if bool(p.known):
        assert float(p.value) == pytest.approx(r.value, rel=1e-3)
    _train_finite(mem, zq)


def test_full_memory_and_far_query():
    Z = _cloud(4, n=16)
    mem = _mem_g(Z, np.linspace(-1, 1, 16))
    p = _both(mem, np.array([5.0, -5.0]))
    assert not bool(p.known) and int(p.n_neighbours) == 0
    p = _both(mem, np.array([0.5, 0.5]))
    assert int(p.n_neighbours) == CFG_G.max_neighbours
