"""``bandwidth_k``: one kernel width for the whole memory, read from the stored data
(``hedger_jax.data_bandwidth``) -- the width against a float64 NumPy computation of the rule
written here, and every entry point (predict, greedy action, training step, evaluation,
make_train) using that width."""
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, HedgerParams, InvalidParamsError, RunConfig,  # noqa: E402
                        Transition, add_points, greedy_action, init_memory, make_train,
                        predict, train_step)
from hedger_jax.agent import evaluate  # noqa: E402
from hedger_jax.data_bandwidth import (POOL, RATE_FROM, SAMPLE, data_bandwidth,  # noqa: E402
                                      with_data_bandwidth)
from hedger_np_ref import RefParams, f32  # noqa: E402

ACTIONS = ((-0.05,), (0.0,), (0.05,))
K = 16
CFG = HedgerConfig(2, 1, capacity=300, bandwidth=0.05, max_bandwidth=0.4, max_neighbours=K,
                   discrete_actions=ACTIONS, action_low=(-0.1,), action_high=(0.1,),
                   neighbour_index="brute", bandwidth_k=8, kernel_range=8.0)


def _data(seed=0, n=250):
    """Two clusters of different density, so the median width is not a trivial one."""
    rng = np.random.default_rng(seed)
    S = np.concatenate([rng.uniform(0.0, 0.1, (n // 2, 2)), rng.uniform(0.3, 0.9, (n - n // 2, 2))])
    A = rng.uniform(-0.1, 0.1, (n, 1))
    V = 0.3 + S @ np.array([0.5, -0.4]) + 0.02 * rng.standard_normal(n)
    return f32(S), f32(A), f32(V)


def reference_width(points, size, h, m, kernel_range, min_weight, shrink=False):
    """The rule in float64: a pool of POOL slots spread evenly over [0, size) (every slot
    while size <= POOL) and SAMPLE of its points spread evenly over it; each sample point's
    distance d_m to its m-th nearest pool point (itself included; fewer than m: infinite);
    the lower median of d_m / sqrt(ln(1 / min_weight)), with ``shrink`` times
    (size / RATE_FROM)^(-1/(d+4)) beyond RATE_FROM points, at most h * kernel_range; h
    itself for an empty memory or m = 0."""
    if size == 0 or m == 0:
        return h
    P = np.asarray(points, np.float64)[:size]
    pool = np.floor((np.arange(POOL) + 0.5) * max(size, POOL) / POOL).astype(int)
    pool = P[pool[pool < size]]
    rows = np.floor((np.arange(SAMPLE) + 0.5) * len(pool) / SAMPLE).astype(int)
    widths = []
    for r in rows:
        d = np.sort(np.sqrt(((pool - pool[r]) ** 2).sum(1)))
        widths.append(d[m - 1] if len(d) >= m else np.inf)
    lower_median = np.sort(widths)[SAMPLE // 2 - 1]
    factor = (max(size, RATE_FROM) / RATE_FROM) ** (-1.0 / (P.shape[1] + 4)) if shrink else 1.0
    return min(lower_median / np.sqrt(np.log(1.0 / min_weight)) * factor, h * kernel_range)


def _memory(cfg, n=250, seed=0):
    S, A, V = _data(seed, n)
    return add_points(cfg, init_memory(cfg), S, A, V), np.concatenate([S, A], 1)


# Fewer than m points, all in the pool, subsampled, and beyond RATE_FROM (where
# bandwidth_shrink narrows the width).
@pytest.mark.parametrize("n", [5, 250, 6000, 3 * RATE_FROM])
def test_the_width_matches_the_float64_rule_for_a_grid_of_settings(n):
    cfg = CFG.replace(capacity=max(n, 300))
    mem, P = _memory(cfg, n)
    grid = dict(bandwidth=[0.05, 0.02, 0.05, 0.01, 0.03], bandwidth_k=[8, 16, 3, 8, 0],
                kernel_range=[8.0, 8.0, 2.0, 1.5, 8.0], min_weight=[0.01, 0.01, 0.05, 0.01, 0.01],
                bandwidth_shrink=[False, False, True, True, True])
    params = HedgerParams.create(cfg, **{k: np.asarray(v) for k, v in grid.items()})
    got = np.asarray(jax.jit(jax.vmap(lambda p: data_bandwidth(cfg, mem, p)))(params))
    for i in range(5):
        want = reference_width(P, len(P), grid["bandwidth"][i], grid["bandwidth_k"][i],
                               grid["kernel_range"][i], grid["min_weight"][i],
                               grid["bandwidth_shrink"][i])
        assert got[i] == pytest.approx(want, rel=1e-5), i
    # The cases the grid exercises: a median below h (with enough points), the cap at
    # h * kernel_range (not reached by the densest memory), and off.
    assert got[4] == pytest.approx(0.03) and (got[0] < 0.05) == (n > 8)
    assert (got[3] == pytest.approx(0.015)) == (n < 6000)


def test_bandwidth_shrink_narrows_the_width_at_the_local_linear_rate():
    """A memory of one distribution filled from RATE_FROM to 4 RATE_FROM points: with
    ``bandwidth_shrink`` the width falls by about 4^(-1/(d+4)) (d = 3), not the 4^(-1/d) of
    the m-th neighbour of all points; without it, not at all (a fixed span)."""
    n_max = 4 * RATE_FROM
    cfg = CFG.replace(capacity=n_max, bandwidth_shrink=True)
    rng = np.random.default_rng(4)
    S, A = f32(rng.uniform(0, 1, (n_max, 2))), f32(rng.uniform(-0.1, 0.1, (n_max, 1)))
    widths = [float(data_bandwidth(cfg, add_points(cfg, init_memory(cfg), S[:n], A[:n],
                                                   f32(np.zeros(n))))) for n in (RATE_FROM, n_max)]
    assert widths[1] / widths[0] == pytest.approx(4 ** (-1 / 7), rel=0.1)
    mem = add_points(cfg, init_memory(cfg), S, A, f32(np.zeros(n_max)))
    kept = float(data_bandwidth(cfg, mem, HedgerParams.create(cfg, bandwidth_shrink=False)))
    assert widths[1] / kept == pytest.approx(4 ** (-1 / 7), rel=1e-5)


def test_the_width_does_not_shrink_as_a_memory_of_one_distribution_fills():
    """The kernel spans a fraction of the data: 4x the points (all beyond the pool) leave the
    width within a few per cent, where the m-th neighbour of all of them would be ~2x closer."""
    n_max = 4 * (POOL + 1000)
    cfg = CFG.replace(capacity=n_max)
    rng = np.random.default_rng(3)
    S, A = f32(rng.uniform(0, 1, (n_max, 2))), f32(rng.uniform(-0.1, 0.1, (n_max, 1)))
    widths = [float(data_bandwidth(cfg, add_points(cfg, init_memory(cfg), S[:n], A[:n],
                                                   f32(np.zeros(n))))) for n in (n_max // 4, n_max)]
    assert widths[1] == pytest.approx(widths[0], rel=0.1)


def test_an_empty_memory_keeps_the_bandwidth_and_off_changes_nothing():
    assert float(data_bandwidth(CFG, init_memory(CFG))) == pytest.approx(CFG.bandwidth)
    off = CFG.replace(bandwidth_k=0)
    params = HedgerParams.create(off)
    assert with_data_bandwidth(off, init_memory(off), None) is None
    assert with_data_bandwidth(off, init_memory(off), params) is params


def _resolved(cfg, mem, params):
    """The same settings with the data's width as a fixed bandwidth (bandwidth_k = 0)."""
    h = float(data_bandwidth(cfg, mem, params))
    return params.replace(bandwidth=np.float32(h), bandwidth_k=np.int32(0)), h


def test_predictions_training_and_evaluation_use_the_data_width():
    mem, P = _memory(CFG)
    params = HedgerParams.create(CFG)
    fixed, h = _resolved(CFG, mem, params)
    assert h < CFG.bandwidth                    # the dense data asks for a narrower kernel
    s, a = jnp.asarray(f32([0.05, 0.04])), jnp.asarray(f32([0.02]))
    # predict against the float64 reference at the data's width.
    ref = RefParams(bandwidth=h, k_min=CFG.k_min, max_neighbours=K,
                    k_thresh=h * np.sqrt(np.log(1.0 / CFG.min_weight)),
                    default_value=CFG.default_value, use_ivh=True, ivh_tol=CFG.ivh_tol,
                    alpha=CFG.alpha, gamma=CFG.gamma, region_update=True,
                    discrete_actions=ACTIONS)
    want = ref.predict(P, np.asarray(mem.values, np.float64)[:len(P)], len(P),
                       np.concatenate([s, a]))
    got = jax.jit(lambda: predict(CFG, mem, s, a))()
    assert bool(got[1]) == want.known
    assert float(got[0]) == pytest.approx(want.value, rel=2e-4, abs=2e-5)
    # Given params (bandwidth_k from the config: the width read in the program) and the
    # resolved fixed width agree, in one program for both.
    both = jax.jit(lambda p: (predict(CFG, mem, s, a, p),
                              greedy_action(CFG, mem, s, jax.random.PRNGKey(3), p)))
    for x, y in zip(jax.tree_util.tree_leaves(both(params)),
                    jax.tree_util.tree_leaves(both(fixed))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    tr = Transition(obs=s, action=a, reward=jnp.float32(0.1),
                    next_obs=jnp.asarray(f32([0.06, 0.05])), terminated=jnp.bool_(False),
                    valid=jnp.bool_(True))
    m1, i1 = jax.jit(lambda: train_step(CFG, mem, tr))()
    m2, i2 = jax.jit(lambda: train_step(CFG, mem, tr, params=fixed))()
    np.testing.assert_array_equal(np.asarray(m1.values), np.asarray(m2.values))
    np.testing.assert_array_equal(np.asarray(i1.q_new), np.asarray(i2.q_new))


def test_evaluation_and_a_swept_run_use_the_data_width():
    """A run swept over bandwidth_k (24: the data's width, 0: the fixed bandwidth) from the
    same key: the width changes the run (which predictions are known, so the actions and the
    states visited); and an evaluation with bandwidth_k equals one at the resolved fixed
    width."""
    from envs.mountain_car import MountainCar

    env = MountainCar()
    cfg = HedgerConfig.for_env(env, capacity=1200, bandwidth=0.02, max_bandwidth=0.16,
                               neighbour_index="brute", bandwidth_k=24, kernel_range=8.0)
    run = RunConfig(n_blocks=1, episodes_per_block=2, eval_episodes=3)
    train = make_train(env, cfg, run)
    params = HedgerParams.create(cfg, bandwidth_k=np.asarray([24, 0]))
    key = jax.random.PRNGKey(0)
    state, res = jax.jit(jax.vmap(train.train, in_axes=(None, 0)))(key, params)
    assert res.evaluation.mean_steps.shape == (2, 2)
    size = np.asarray(state.memory.size)
    assert np.all(size > 0)
    n = int(size.min())
    assert not np.array_equal(np.asarray(state.memory.points)[0, :, :n],
                              np.asarray(state.memory.points)[1, :, :n])
    mem = jax.tree_util.tree_map(lambda x: x[0], state.memory)
    one = jax.tree_util.tree_map(lambda x: x[0], params)
    fixed, h = _resolved(cfg, mem, one)
    assert h != pytest.approx(cfg.bandwidth)
    ev = jax.jit(lambda p: evaluate(env, env.default_params(), cfg, mem, key, 3, 200,
                                    params=p))
    assert float(ev(one).mean_steps) == float(ev(fixed).mean_steps)


def test_bad_settings_are_refused_with_named_errors():
    with pytest.raises(ValueError, match="bandwidth_k"):
        CFG.replace(bandwidth_k=POOL + 1)
    assert CFG.replace(bandwidth_k=K + 1).bandwidth_k == K + 1   # m is not limited by k
    with pytest.raises(InvalidParamsError, match="bandwidth_k"):
        HedgerParams.create(CFG, bandwidth_k=-1)
    with pytest.raises(InvalidParamsError, match="bandwidth_k"):
        HedgerParams.create(CFG.replace(bandwidth_k=0), bandwidth_k=np.asarray([8, POOL + 1]))
