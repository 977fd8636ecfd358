"""``HedgerParams``: traced hyperparameters -- a grid of settings in one program, checked
against the float64 reference per setting; static fields refused with a named error."""
import dataclasses
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, HedgerParams, InvalidParamsError, RunConfig,  # noqa: E402
                        StaticFieldError, Transition, add_points, init_memory, make_train,
                        predict, train_step)
from hedger_np_ref import RefParams, f32, ref_predict, ref_train_step  # noqa: E402

ACTIONS = ((-0.05,), (0.0,), (0.05,))
CFG = HedgerConfig(2, 1, capacity=256, bandwidth=0.05, max_bandwidth=0.2, max_neighbours=16,
                   discrete_actions=ACTIONS, action_low=(-0.1,), action_high=(0.1,),
                   neighbour_index="brute")


def _data(seed=0, n=200):
    rng = np.random.default_rng(seed)
    S = f32(rng.uniform(0.0, 0.3, (n, 2)))
    A = f32(rng.uniform(-0.1, 0.1, (n, 1)))
    Z = np.concatenate([S, A], 1).astype(np.float64)
    V = f32(0.3 + Z @ np.array([0.5, -0.4, 1.0]) + 0.02 * rng.standard_normal(n))
    return S, A, V


def _ref(params_row):
    p = {k: np.asarray(v).item() if np.ndim(v) == 0 else v for k, v in params_row.items()}
    return RefParams(bandwidth=p["bandwidth"], k_min=int(p["k_min"]), max_neighbours=16,
                     k_thresh=float(p["k_thresh"]), default_value=p["default_value"],
                     use_ivh=bool(p["use_ivh"]), ivh_tol=p["ivh_tol"], alpha=p["alpha"],
                     gamma=p["gamma"], region_update=bool(p["region_update"]),
                     discrete_actions=ACTIONS)


def test_defaults_come_from_the_config_and_equal_no_params():
    params = HedgerParams.create(CFG)
    assert float(params.bandwidth) == np.float32(CFG.bandwidth)
    assert float(params.k_thresh) == np.float32(CFG.k_thresh)
    assert int(params.k_min) == CFG.k_min and bool(params.use_ivh) and bool(params.region_update)
    np.testing.assert_array_equal(params.input_scale, np.float32(CFG.input_scale))
    S, A, V = _data()
    mem = add_points(CFG, init_memory(CFG), S, A, V)
    q = jnp.asarray(np.random.default_rng(1).uniform(0, 0.3, (64, 2)), jnp.float32)
    a = jnp.full((64, 1), 0.02, jnp.float32)
    f = jax.jit(jax.vmap(lambda s, a, p: predict(CFG, mem, s, a, p), (0, 0, None)))
    g = jax.jit(jax.vmap(lambda s, a: predict(CFG, mem, s, a)))
    for got, want in zip(f(q, a, params), g(q, a)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-7)


def test_a_grid_of_settings_in_one_program_matches_the_reference_per_setting():
    """train_step vmapped over 6 settings (bandwidth, alpha, gamma, k_min, default value and
    both ablation switches varying) equals the float64 reference of each setting."""
    grid = dict(bandwidth=[0.03, 0.05, 0.08, 0.12, 0.05, 0.2],
                alpha=[0.8, 0.5, 0.8, 0.2, 0.8, 0.9], gamma=[0.8, 0.9, 0.99, 0.8, 0.5, 0.8],
                k_min=[4, 4, 6, 8, 4, 5], default_value=[0.0, 0.1, 0.0, -0.2, 0.3, 0.0],
                use_ivh=[True, True, False, True, False, True],
                region_update=[True, False, True, True, False, True])
    params = HedgerParams.create(CFG, **{k: np.asarray(v) for k, v in grid.items()})
    assert params.bandwidth.shape == (6,) and params.input_scale.shape == (6, 3)
    S, A, V = _data()
    mem = add_points(CFG, init_memory(CFG), S, A, V)
    s, a, s2 = f32([0.15, 0.12]), f32([0.02]), f32([0.16, 0.13])
    tr = Transition(obs=jnp.asarray(s), action=jnp.asarray(a), reward=jnp.float32(0.1),
                    next_obs=jnp.asarray(s2), terminated=jnp.bool_(False),
                    valid=jnp.bool_(True))
    step = jax.jit(jax.vmap(lambda p: train_step(CFG, mem, tr, params=p)))
    mems, infos = step(params)
    P = np.concatenate([S, A], 1)
    for i in range(6):
        row = {k: np.asarray(v)[i] for k, v in params._asdict().items()}
        _, new_V, q, q_next, q_new, _ = ref_train_step(_ref(row), P, V, len(V), s, a, 0.1, s2,
                                                       False)
        assert float(infos.q[i]) == pytest.approx(q, rel=2e-4, abs=2e-5), i
        assert float(infos.q_next[i]) == pytest.approx(q_next, rel=2e-4, abs=2e-5), i
        assert float(infos.q_new[i]) == pytest.approx(q_new, rel=2e-4, abs=2e-5), i
        np.testing.assert_allclose(np.asarray(mems.values[i])[:len(V) + 1], new_V,
                                   rtol=2e-4, atol=2e-5, err_msg=str(i))


def test_input_scaling_is_traced_too():
    """An action-scale sweep in one program: the same stored points predicted under two
    input scalings equal the reference on the correspondingly scaled data."""
    S, A, V = _data(3)
    scales = np.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, 0.5]], np.float32)
    params = HedgerParams.create(CFG, input_scale=scales)
    zq = f32([0.15, 0.15, 0.02])

    def one(p):
        mem = add_points(CFG, init_memory(CFG), S, A, V, params=p)
        return predict(CFG, mem, zq[:2], zq[2:], p)

    got = jax.jit(jax.vmap(one))(params)
    for i in range(2):
        P = np.concatenate([S, A], 1).astype(np.float64) * scales[i]
        want = ref_predict(P, V.astype(np.float64), len(V), zq * scales[i], bandwidth=0.05,
                           k_thresh=float(params.k_thresh[i]), k_min=4, max_neighbours=16)
        assert bool(got[1][i]) == want.known
        assert float(got[0][i]) == pytest.approx(want.value, rel=2e-4, abs=1e-5)


def test_static_fields_refuse_traced_values_with_a_named_error():
    with pytest.raises(StaticFieldError, match="capacity: HedgerConfig fields are static"):
        jax.vmap(lambda c: HedgerConfig(2, capacity=c))(jnp.arange(2) + 10)
    with pytest.raises(StaticFieldError, match="bandwidth.*HedgerParams"):
        jax.vmap(lambda h: HedgerConfig(2, bandwidth=h))(jnp.asarray([0.1, 0.2]))
    with pytest.raises(StaticFieldError, match="epsilon: RunConfig fields are static"):
        jax.vmap(lambda e: RunConfig(epsilon=e))(jnp.asarray([0.1, 0.2]))
    with pytest.raises(StaticFieldError, match="max_neighbours: a static HedgerConfig field"):
        HedgerParams.create(CFG, max_neighbours=8)


def test_a_bandwidth_beyond_the_configs_bound_is_refused():
    grid = HedgerConfig(2, 1, capacity=512, bandwidth=0.02, neighbour_index="grid")
    assert grid.max_bandwidth == 0.02
    with pytest.raises(InvalidParamsError, match="bandwidth.*max_bandwidth = 0.02"):
        HedgerParams.create(grid, bandwidth=np.asarray([0.02, 0.03]))
    HedgerParams.create(grid.replace(max_bandwidth=0.03), bandwidth=np.asarray([0.02, 0.03]))
    with pytest.raises(InvalidParamsError, match="alpha: must be in"):
        HedgerParams.create(CFG, alpha=1.5)
    with pytest.raises(InvalidParamsError, match="k_min"):
        HedgerParams.create(CFG, k_min=np.asarray([4, 40]))
    with pytest.raises(ValueError, match="max_bandwidth"):
        HedgerConfig(2, bandwidth=0.1, max_bandwidth=0.05)


def test_replace_derives_the_radius_and_keeps_shapes():
    p = HedgerParams.create(CFG)
    q = p.replace(bandwidth=jnp.float32(0.1))
    ratio = float(p.k_thresh) / float(p.bandwidth)
    assert float(q.k_thresh) == pytest.approx(0.1 * ratio, rel=1e-6)
    assert HedgerParams.create(CFG, bandwidth=0.1).k_thresh == pytest.approx(0.1 * ratio)


@pytest.mark.slow
def test_a_sweep_equals_separate_runs_per_setting():
    """make_train's train(key, params) over 2 bandwidths x 2 seeds, one program, against the
    program of the static config (the pre-params way) for the bandwidth that is not the
    config's own: the same evaluations and stored points, to float32 rounding (fits are
    bit-identical; programs compiled differently may round a multiply-add differently). The
    other member differs from it, so the sweep did not run one setting twice."""
    from envs.mountain_car import MountainCar
    from hedger_jax.agent import transitions_from_demonstrations
    from envs.demonstrators import simulated_person_demonstrations

    env = MountainCar()
    demos = transitions_from_demonstrations(simulated_person_demonstrations(seed=0))
    demos = jax.tree_util.tree_map(lambda x: x[:2], demos)
    run = RunConfig(n_blocks=1, episodes_per_block=2, eval_episodes=6)
    values = [0.015, 0.03]
    # Brute force: the programs compile in a third of the grid's time (the grid's traced
    # radius is tested against the reference above).
    base = HedgerConfig.for_env(env, capacity=3000, bandwidth=0.015, max_bandwidth=0.03,
                                neighbour_index="brute")
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    params = HedgerParams.create(base, run, bandwidth=np.repeat(values, 2))
    sweep = jax.jit(jax.vmap(make_train(env, base, run, phase1=demos).train))
    state, res = sweep(jnp.tile(keys, (len(values), 1)), params)
    # One static program (a compile costs seconds): the swept value 0.03, not the config's.
    cfg = dataclasses.replace(base, bandwidth=values[1], k_thresh=None, max_bandwidth=None)
    _, want = jax.jit(jax.vmap(make_train(env, cfg, run, phase1=demos).train))(keys)
    got = jax.tree_util.tree_map(lambda x: x[2:], res)
    np.testing.assert_array_equal(np.asarray(got.memory_size), np.asarray(want.memory_size))
    np.testing.assert_allclose(np.asarray(got.evaluation.mean_steps),
                               np.asarray(want.evaluation.mean_steps), rtol=0, atol=1e-4)
    points = np.asarray(state.memory.points)
    assert not np.array_equal(points[:2], points[2:])


def test_log_values_match_the_reference():
    """value_eps > 0: the memory stores sign(q) log1p(|q| / eps) and fits those; predictions
    map the fit back. Values spanning orders of magnitude (gamma^steps), predictions and a
    training step against the float64 reference, two value_eps and the identity vmapped."""
    S, A, _ = _data(7)
    Z = np.concatenate([S, A], 1).astype(np.float64)
    V = f32(0.8 ** (40 * Z[:, 0] + 30 * Z[:, 1]))           # 1 ... ~1e-5
    params = HedgerParams.create(CFG, value_eps=np.asarray([0.0, 1e-6, 1e-3]))
    mems = jax.jit(jax.vmap(lambda p: add_points(CFG, init_memory(CFG), S, A, V, params=p)))(
        params)
    P = np.concatenate([S, A], 1)

    def ref_of(i):
        r = _ref({k: np.asarray(v)[i] for k, v in params._asdict().items()})
        r.value_eps = float(params.value_eps[i])
        return r

    for i in range(3):
        from hedger_np_ref import to_fit
        np.testing.assert_allclose(np.asarray(mems.values[i])[:len(V)],
                                   to_fit(V, ref_of(i).value_eps), rtol=2e-6, atol=1e-7)
    s, a = f32([0.12, 0.2]), f32([0.03])
    got = jax.jit(jax.vmap(lambda m, p: predict(CFG, m, s, a, p)))(mems, params)
    for i in range(3):
        want = ref_of(i).predict(P, V, len(V), np.concatenate([s, a]))
        assert bool(got[1][i]) == want.known
        assert float(got[0][i]) == pytest.approx(want.value, rel=1e-3), i
    tr = Transition(obs=jnp.asarray(s), action=jnp.asarray(a), reward=jnp.float32(0.0),
                    next_obs=jnp.asarray(f32([0.13, 0.19])), terminated=jnp.bool_(False),
                    valid=jnp.bool_(True))
    new, infos = jax.jit(jax.vmap(lambda m, p: train_step(CFG, m, tr, params=p)))(mems, params)
    for i in range(3):
        _, new_V, _, _, q_new, _ = ref_train_step(ref_of(i), P, V, len(V), s, a, 0.0,
                                                  f32([0.13, 0.19]), False)
        assert float(infos.q_new[i]) == pytest.approx(q_new, rel=1e-3), i
        np.testing.assert_allclose(np.asarray(new.values[i])[:len(V) + 1], new_V, rtol=1e-3,
                                   atol=1e-6, err_msg=str(i))
