"""Algorithm 2 (train_step) and reverse replay (train_episode) against a float64 reference."""
import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, HedgerParams, Transition, add_points,  # noqa: E402
                        init_memory, train_episode, train_step)
from hedger_jax.agent import train_prefix  # noqa: E402
from hedger_np_ref import (RefParams, default_k_thresh, f32, ref_train_episode,  # noqa: E402
                           ref_train_step)

ACTIONS = ((-0.05,), (0.0,), (0.05,))
_KW = dict(capacity=256, bandwidth=0.1, max_neighbours=16, alpha=0.8, gamma=0.8,
           default_value=0.1, discrete_actions=ACTIONS, action_low=(-0.1,), action_high=(0.1,))
CFG = HedgerConfig(2, 1, **_KW)
CFG_NOREG = HedgerConfig(2, 1, region_update=False, **_KW)

_step = jax.jit(functools.partial(train_step, CFG))
_step_noreg = jax.jit(functools.partial(train_step, CFG_NOREG))
_episode = jax.jit(functools.partial(train_episode, CFG))


def _refp(cfg):
    return RefParams(bandwidth=cfg.bandwidth, k_min=cfg.k_min,
                     max_neighbours=cfg.max_neighbours,
                     k_thresh=default_k_thresh(cfg.bandwidth, cfg.min_weight),
                     default_value=cfg.default_value, use_ivh=cfg.use_ivh, ivh_tol=cfg.ivh_tol,
                     alpha=cfg.alpha, gamma=cfg.gamma, region_update=cfg.region_update,
                     discrete_actions=cfg.discrete_actions)


def _tr(s, a, r, s2, term=False, valid=True):
    return Transition(obs=jnp.asarray(s, jnp.float32), action=jnp.asarray(a, jnp.float32),
                      reward=jnp.float32(r), next_obs=jnp.asarray(s2, jnp.float32),
                      terminated=jnp.bool_(term), valid=jnp.bool_(valid))


def _make_data(seed=0, n=200, value_scale=1.0):
    rng = np.random.default_rng(seed)
    S = f32(rng.uniform(0.0, 0.3, (n, 2)))
    A = f32(rng.uniform(-0.1, 0.1, (n, 1)))
    Z = np.concatenate([S, A], 1).astype(np.float64)
    V = f32(value_scale * (0.3 + Z @ np.array([0.5, -0.4, 1.0]) + 0.02 * rng.standard_normal(n)))
    return S, A, V


@pytest.fixture(scope="module")
def data():
    S, A, V = _make_data()
    mem = add_points(CFG, init_memory(CFG), S, A, V)
    return S, A, V, mem


def _check_step(cfg, step_fn, S, A, V, mem, s, a, r, s2, term, expect_known=None,
                expect_n=None):
    n = len(V)
    P = np.concatenate([S, A], 1)
    s, a, s2 = f32(s), f32(a), f32(s2)
    refp = _refp(cfg)
    new_P, new_V, q, q_next, q_new, pred = ref_train_step(refp, P, V, n, s, a, r, s2, term)
    assert not pred.ambiguous
    if expect_known is not None:
        assert pred.known == expect_known
    if expect_n is not None:
        assert expect_n(pred.n), pred.n
    mem2, info = step_fn(mem, _tr(s, a, r, s2, term))
    ctx = f"s={s} a={a}: ref q={q} q_next={q_next} q_new={q_new} known={pred.known} n={pred.n}"
    assert bool(info.known) == pred.known, ctx
    vs = max(1.0, float(np.max(np.abs(V))))
    assert float(info.q) == pytest.approx(q, rel=2e-4, abs=2e-4 * vs), ctx
    assert float(info.q_next) == pytest.approx(q_next, rel=2e-4, abs=2e-4 * vs), ctx
    assert float(info.q_new) == pytest.approx(q_new, rel=2e-4, abs=2e-4 * vs), ctx
    assert int(mem2.size) == n + 1
    assert int(mem2.flags) == 0
    np.testing.assert_array_equal(np.asarray(mem2.points)[:, :n + 1], new_P.T.astype(np.float32))
    got_V = np.asarray(mem2.values)[:n + 1].astype(np.float64)
    np.testing.assert_allclose(got_V, new_V, rtol=2e-4, atol=2e-4 * vs, err_msg=ctx)
    return mem2, info, pred, q_new


def test_interior_step_matches_reference(data):
    S, A, V, mem = data
    mem2, info, pred, q_new = _check_step(CFG, _step, S, A, V, mem, [0.15, 0.15], [0.02], 0.1,
                                          [0.16, 0.14], False, expect_known=True,
                                          expect_n=lambda n: n == CFG.max_neighbours)
    assert pred.known
    # neighbours really moved: each by kappa_i (q_new - Q_i), nothing else moved
    old = V.astype(np.float64)
    new = np.asarray(mem2.values)[:len(V)].astype(np.float64)
    moved = np.nonzero(np.abs(new - old) > 0)[0]
    assert set(moved.tolist()) <= set(pred.idx.tolist())
    expect = old[pred.idx] + pred.kappa * (q_new - old[pred.idx])
    np.testing.assert_allclose(new[pred.idx], expect, rtol=2e-4, atol=2e-5)
    # the new point sits at slot 200 with q_new
    assert float(mem2.values[len(V)]) == pytest.approx(q_new, rel=2e-4)


def test_terminal_step_does_not_bootstrap(data):
    S, A, V, mem = data
    mem2, info, pred, q_new = _check_step(CFG, _step, S, A, V, mem, [0.15, 0.15], [0.02], 0.5,
                                          [0.16, 0.14], True, expect_known=True)
    assert float(info.q_next) == 0.0
    assert float(info.q_new) == pytest.approx(pred.value + 0.8 * (0.5 - pred.value), rel=2e-4)


def test_unknown_prediction_still_updates_neighbours(data):
    """Outside the hull: q = default_value, but K is non-empty and still moves toward q_new.
    s' far from everything: q_next = default_value."""
    S, A, V, mem = data
    mem2, info, pred, q_new = _check_step(CFG, _step, S, A, V, mem, [0.36, 0.15], [0.02], 0.2,
                                          [0.9, 0.9], False, expect_known=False,
                                          expect_n=lambda n: n >= CFG.k_min)
    assert float(info.q) == pytest.approx(CFG.default_value)
    assert float(info.q_next) == pytest.approx(CFG.default_value)
    q_new_expect = 0.1 + 0.8 * (0.2 + 0.8 * 0.1 - 0.1)
    assert float(info.q_new) == pytest.approx(q_new_expect, rel=1e-5)
    assert pred.n > 0
    new = np.asarray(mem2.values)[pred.idx].astype(np.float64)
    assert np.all(np.abs(new - V[pred.idx]) > 0)


def test_fewer_than_k_min_neighbours_still_updates_them(data):
    S, A, V, mem = data
    P = np.concatenate([S, A], 1).astype(np.float64)
    kt = default_k_thresh(CFG.bandwidth, CFG.min_weight)
    # walk outward from the cloud until 1..k_min-1 points are within k_thresh
    for t in np.linspace(0.0, 0.4, 401):
        z = np.array([0.3 + t, 0.3 + t, 0.0])
        n = int(np.sum(np.linalg.norm(P - z, axis=1) <= kt))
        d = np.linalg.norm(P - z, axis=1)
        if 1 <= n < CFG.k_min and np.min(np.abs(d - kt)) > 1e-3:
            break
    else:
        pytest.fail("no location with few neighbours found")
    mem2, info, pred, q_new = _check_step(CFG, _step, S, A, V, mem, z[:2], z[2:], 0.3,
                                          [0.9, 0.9], False, expect_known=False,
                                          expect_n=lambda n: 1 <= n < CFG.k_min)
    assert float(info.q) == pytest.approx(CFG.default_value)


def test_region_update_off_leaves_neighbours_untouched(data):
    S, A, V, _ = data
    mem = add_points(CFG_NOREG, init_memory(CFG_NOREG), S, A, V)
    mem2, info, pred, q_new = _check_step(CFG_NOREG, _step_noreg, S, A, V, mem, [0.15, 0.15],
                                          [0.02], 0.1, [0.16, 0.14], False, expect_known=True)
    np.testing.assert_array_equal(np.asarray(mem2.values)[:len(V)], V)
    assert float(mem2.values[len(V)]) == pytest.approx(q_new, rel=2e-4)


def test_tiny_values_keep_relative_precision_in_training():
    """Values ~1e-10 (gamma^100): the TD update with r = 0 must stay relatively exact."""
    S, A, V = _make_data(seed=1, value_scale=1e-10)
    mem = add_points(CFG, init_memory(CFG), S, A, V)
    P = np.concatenate([S, A], 1)
    s, a, s2 = f32([0.15, 0.12]), f32([0.01]), f32([0.14, 0.13])
    new_P, new_V, q, q_next, q_new, pred = ref_train_step(_refp(CFG), P, V, len(V), s, a, 0.0,
                                                          s2, False)
    assert pred.known and not pred.ambiguous and abs(q_new) < 1e-9
    mem2, info = _step(mem, _tr(s, a, 0.0, s2))
    assert float(info.q) == pytest.approx(q, rel=2e-4)
    assert float(info.q_next) == pytest.approx(q_next, rel=2e-4)
    assert float(info.q_new) == pytest.approx(q_new, rel=2e-4)
    np.testing.assert_allclose(np.asarray(mem2.values)[:len(V) + 1], new_V, rtol=2e-4, atol=0)


def test_invalid_transition_changes_nothing(data):
    S, A, V, mem = data
    mem2, info = _step(mem, _tr([0.15, 0.15], [0.02], 0.1, [0.16, 0.14], valid=False))
    for x, y in zip(jax.tree_util.tree_leaves(mem), jax.tree_util.tree_leaves(mem2)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# In the full suite (~8 s op by op): test_lwr_predict.py runs the prediction it is built
# on eagerly in the quick tier.
@pytest.mark.full
def test_unjitted_train_step_equals_jitted(data):
    S, A, V, mem = data
    tr = _tr([0.1, 0.2], [-0.03], 0.05, [0.12, 0.18])
    m1, i1 = _step(mem, tr)
    m2, i2 = train_step(CFG, mem, tr)
    np.testing.assert_allclose(np.asarray(m1.values), np.asarray(m2.values), rtol=1e-5,
                               atol=1e-7)
    np.testing.assert_array_equal(np.asarray(m1.points), np.asarray(m2.points))
    assert int(m1.size) == int(m2.size)
    assert float(i1.q_new) == pytest.approx(float(i2.q_new), rel=1e-5)


# ------------------------------------------------------------------ reverse replay
def _episode_arrays(rng, T, valid):
    s = f32(rng.uniform(0.02, 0.28, (T, 2)))
    a = f32(rng.choice([-0.05, 0.0, 0.05], size=(T, 1)))
    s2 = f32(np.clip(s + rng.normal(0, 0.01, (T, 2)), 0, 0.3))
    r = f32(rng.uniform(0, 1, T))
    term = np.zeros(T, bool)
    last = np.nonzero(valid)[0]
    if len(last):
        term[last[-1]] = True
    return Transition(obs=jnp.asarray(s), action=jnp.asarray(a), reward=jnp.asarray(r),
                      next_obs=jnp.asarray(s2), terminated=jnp.asarray(term),
                      valid=jnp.asarray(np.asarray(valid, bool)))


def _loop(mem, ep, valid):
    infos = {}
    for t in reversed(range(len(valid))):
        if valid[t]:
            tr = jax.tree_util.tree_map(lambda x: x[t], ep)
            mem, info = _step(mem, tr)
            infos[t] = info
    return mem, infos


@pytest.mark.parametrize("valid", [[1, 1, 1, 1, 0, 0], [1, 0, 1, 1, 0, 1], [0, 0, 0, 0, 0, 0]])
def test_train_episode_equals_reverse_loop_of_train_step(data, valid):
    S, A, V, mem = data
    rng = np.random.default_rng(sum(valid) * 7 + valid[1])
    ep = _episode_arrays(rng, len(valid), valid)
    m_ep, infos = _episode(mem, ep)
    m_loop, loop_infos = _loop(mem, ep, valid)
    assert int(m_ep.size) == int(m_loop.size) == len(V) + sum(valid)
    assert int(m_ep.head) == int(m_loop.head)
    assert int(m_ep.flags) == int(m_loop.flags) == 0
    np.testing.assert_array_equal(np.asarray(m_ep.points), np.asarray(m_loop.points))
    np.testing.assert_allclose(np.asarray(m_ep.values), np.asarray(m_loop.values),
                               rtol=1e-5, atol=1e-6)
    # infos: one per step (time order or scan order; accept either)
    q_new = np.asarray(infos.q_new)
    assert q_new.shape == (len(valid),)
    if loop_infos:
        ts = sorted(loop_infos)
        want = np.array([float(loop_infos[t].q_new) for t in ts])
        time_order = q_new[ts]
        scan_order = q_new[::-1][ts]
        assert (np.allclose(time_order, want, rtol=1e-5, atol=1e-6)
                or np.allclose(scan_order, want, rtol=1e-5, atol=1e-6)), (q_new, want)
    if sum(valid) == 0:
        for x, y in zip(jax.tree_util.tree_leaves(mem), jax.tree_util.tree_leaves(m_ep)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_train_episode_newest_first_order_matters(data):
    """Reverse replay: the last (terminal, rewarded) step is learned first, so its value is
    already in memory when the earlier step bootstraps from it."""
    S, A, V, _ = data
    cfg = CFG
    mem = add_points(cfg, init_memory(cfg), S, A, f32(np.zeros_like(V)))
    s0, s1 = f32([0.15, 0.15]), f32([0.16, 0.15])
    ep = Transition(obs=jnp.asarray(np.stack([s0, s1])),
                    action=jnp.asarray(f32([[0.0], [0.0]])),
                    reward=jnp.asarray(f32([0.0, 1.0])),
                    next_obs=jnp.asarray(np.stack([s1, f32([0.17, 0.15])])),
                    terminated=jnp.asarray([False, True]), valid=jnp.asarray([True, True]))
    m_ep, infos = _episode(mem, ep)
    m_fwd = mem
    for t in range(2):  # forward order, for contrast
        m_fwd, _ = _step(m_fwd, jax.tree_util.tree_map(lambda x: x[t], ep))
    m_rev, _ = _loop(mem, ep, [1, 1])
    np.testing.assert_allclose(np.asarray(m_ep.values), np.asarray(m_rev.values), rtol=1e-5,
                               atol=1e-6)
    assert not np.allclose(np.asarray(m_ep.values), np.asarray(m_fwd.values), atol=1e-4)


# ------------------------------------------------------------------ replay_floor
def _chain(rng, T, reward_last=2.0):
    """A connected episode (next_obs[t] = obs[t + 1]) ending in a rewarded terminal."""
    s = f32(np.cumsum(np.r_[[[0.05, 0.1]], rng.uniform(0.0, 0.03, (T, 2))], axis=0))
    a = f32(rng.choice([-0.05, 0.0, 0.05], size=(T, 1)))
    r = f32(np.r_[rng.uniform(0, 0.05, T - 1), reward_last])
    term = np.arange(T) == T - 1
    return dict(obs=s[:-1], action=a, reward=r, next_obs=s[1:], terminated=term)


def _as_transition(ep, valid=None):
    T = len(ep["reward"])
    valid = np.ones(T, bool) if valid is None else np.asarray(valid, bool)
    return Transition(**{k: jnp.asarray(v) for k, v in ep.items()}, valid=jnp.asarray(valid))


def test_replay_floor_matches_reference(data):
    """With replay_floor each step's max_a' Q(s', a') is at least the target the step after
    it stored: the float64 reference's reverse replay, and not the plain replay."""
    S, A, V, mem = data
    cfg = CFG.replace(replay_floor=True)
    ep = _chain(np.random.default_rng(3), 8)
    m_ep, infos = jax.jit(functools.partial(train_episode, cfg))(mem, _as_transition(ep))
    P = np.concatenate([S, A], 1)
    refp = _refp(CFG)
    ref_P, ref_V, ref_q_new = ref_train_episode(refp, P, V, len(V), ep, replay_floor=True)
    _, _, plain_q_new = ref_train_episode(refp, P, V, len(V), ep, replay_floor=False)
    np.testing.assert_allclose(np.asarray(infos.q_new), ref_q_new, rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(np.asarray(m_ep.values)[:len(ref_V)], ref_V, rtol=2e-4, atol=2e-4)
    assert np.max(np.abs(ref_q_new - plain_q_new)) > 0.1     # the floor did bind


def test_replay_floor_gives_the_discounted_return_where_nothing_is_known():
    """alpha = 1, isolated steps (every prediction "don't know", default 0): with the floor
    each stored target is the episode's discounted return from that step (closed form);
    without it, the step's reward alone. A sweep over the switch gives both at once, and
    train_prefix (the padded, length-limited replay) gives the same."""
    cfg = HedgerConfig(2, 1, capacity=64, bandwidth=0.01, max_neighbours=8, alpha=1.0,
                       gamma=0.9, default_value=0.0, discrete_actions=ACTIONS,
                       action_low=(-0.1,), action_high=(0.1,))
    T = 5
    s = f32(np.stack([np.arange(T + 1) * 1.0, np.zeros(T + 1)], 1))     # far apart
    r = f32([0.5, 0.0, 1.0, 0.0, 3.0])
    ep = dict(obs=s[:-1], action=f32(np.zeros((T, 1))), reward=r, next_obs=s[1:],
              terminated=np.arange(T) == T - 1)
    returns = np.array([sum(0.9 ** (j - t) * r[j] for j in range(t, T)) for t in range(T)])
    params = HedgerParams.create(cfg, replay_floor=np.array([False, True]))
    run = jax.jit(jax.vmap(lambda p: train_episode(cfg, init_memory(cfg), _as_transition(ep),
                                                   p)))
    mem, infos = run(params)
    np.testing.assert_allclose(np.asarray(infos.q_new[0]), r, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(infos.q_new[1]), returns, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(mem.values[1])[:T][::-1], returns, rtol=1e-5)
    padded = _as_transition({k: np.concatenate([v, v[:2]]) for k, v in ep.items()},
                            valid=np.r_[np.ones(T, bool), False, False])
    one = HedgerParams.create(cfg, replay_floor=True)
    mem_p = jax.jit(lambda m, e, p: train_prefix(cfg, m, e, jnp.int32(T), params=p))(
        init_memory(cfg), padded, one)
    np.testing.assert_allclose(np.asarray(mem_p.values)[:T][::-1], returns, rtol=1e-5)
