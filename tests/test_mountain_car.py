"""MountainCar: equality with Gymnasium's MountainCar-v0, reward, walls, time limit, resets,
jit/vmap, rendering."""
from __future__ import annotations

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.mountain_car import (MountainCar, MountainCarParams, MountainCarState,
                               bottom_start)

ATOL = 2e-6  # float32 (ours) against float64 (Gymnasium) after one step


@pytest.fixture(scope="module")
def env():
    return MountainCar(continuous=False)


@pytest.fixture(scope="module")
def params(env):
    return env.default_params()


@pytest.fixture(scope="module")
def gym_env():
    e = gymnasium.make("MountainCar-v0").unwrapped
    e.reset(seed=0)
    yield e
    e.close()


def _state(x, v, t=0):
    x = jnp.asarray(x, jnp.float32)
    return MountainCarState(position=x, velocity=jnp.asarray(v, jnp.float32),
                            time=jnp.broadcast_to(jnp.asarray(t, jnp.int32), x.shape))


def _batched_step(env, params):
    return jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0, None)))


def _random_states(rng, n):
    # Whole state space, plus states right at both walls (where the clips matter).
    x = rng.uniform(-1.2, 0.5, n).astype(np.float32)
    v = rng.uniform(-0.07, 0.07, n).astype(np.float32)
    x[: n // 20] = np.float32(-1.2)
    x[n // 20: n // 10] = rng.uniform(-1.2, -1.1, n // 20).astype(np.float32)
    v[n // 20: n // 10] = rng.uniform(-0.07, 0.0, n // 20).astype(np.float32)
    x[n // 10: n // 7] = rng.uniform(0.4, 0.5, n // 7 - n // 10).astype(np.float32)
    return x, v


def _gym_step(gym_env, x, v, a):
    gym_env.state = (float(x), float(v))
    obs, _, term, trunc, _ = gym_env.step(int(a) + 1)  # Gymnasium action index = a + 1
    px, pv = gym_env.state
    return float(px), float(pv), bool(term), bool(trunc)


def test_one_step_equals_gymnasium_random_states(env, params, gym_env):
    rng = np.random.default_rng(0)
    n = 3000
    x, v = _random_states(rng, n)
    step = _batched_step(env, params)
    n_term = 0
    for a in (-1, 0, 1):
        acts = jnp.full((n, 1), float(a), jnp.float32)
        obs, s2, rew, term, trunc, _ = step(jax.random.PRNGKey(0), _state(x, v), acts, params)
        obs, px, pv = np.asarray(obs), np.asarray(s2.position), np.asarray(s2.velocity)
        term, trunc = np.asarray(term), np.asarray(trunc)
        assert obs.dtype == np.float32 and obs.shape == (n, 2)
        np.testing.assert_array_equal(obs[:, 0], px)
        np.testing.assert_array_equal(obs[:, 1], pv)
        assert not trunc.any()
        g = np.array([_gym_step(gym_env, x[i], v[i], a) for i in range(n)], dtype=np.float64)
        gx, gv, gterm = g[:, 0], g[:, 1], g[:, 2].astype(bool)
        # Gymnasium clips the position at 0.6; we clip at the goal, 0.5 (terminal states only).
        np.testing.assert_allclose(px, np.minimum(gx, 0.5), atol=ATOL, rtol=0)
        np.testing.assert_allclose(pv, gv, atol=ATOL, rtol=0)
        np.testing.assert_array_equal(term, gterm)
        assert np.all(px[term] == np.float32(0.5))
        n_term += int(term.sum())
        # Reward closed form on every sampled state.
        expected = np.where(term, 1.0 - np.abs(pv) / 0.07, 0.0)
        np.testing.assert_allclose(np.asarray(rew), expected, atol=1e-6)
    assert n_term > 50  # the goal region was actually exercised


def test_trajectories_follow_gymnasium(env, params, gym_env):
    """Random-action trajectories, Gymnasium's state re-set from ours every step (no drift)."""
    rng = np.random.default_rng(1)
    step = jax.jit(env.step)
    key = jax.random.PRNGKey(3)
    compared = 0
    for ep in range(6):
        key, k = jax.random.split(key)
        obs, s = env.reset(k, params)
        for t in range(300):
            a = int(rng.integers(-1, 2)) if ep % 2 else (1 if float(s.velocity) >= 0 else -1)
            gx, gv, gterm, _ = _gym_step(gym_env, s.position, s.velocity, a)
            obs, s, r, term, trunc, _ = step(key, s, jnp.array([a], jnp.float32), params)
            assert abs(float(s.position) - min(gx, 0.5)) <= ATOL
            assert abs(float(s.velocity) - gv) <= ATOL
            assert bool(term) == gterm
            assert int(s.time) == t + 1
            compared += 1
            if bool(term) or bool(trunc):
                break
    assert compared > 300


def test_continuous_equals_discrete_at_unit_actions(params):
    dis, con = MountainCar(False), MountainCar(True)
    assert con.action_space.is_discrete is False and dis.action_space.is_discrete
    assert dis.action_space.values_array().ravel().tolist() == [-1.0, 0.0, 1.0]
    assert con.action_space.low == (-1.0,) and con.action_space.high == (1.0,)
    rng = np.random.default_rng(2)
    x, v = _random_states(rng, 1000)
    for a in (-1.0, 0.0, 1.0):
        acts = jnp.full((1000, 1), a, jnp.float32)
        od = _batched_step(dis, params)(jax.random.PRNGKey(0), _state(x, v), acts, params)
        oc = _batched_step(con, params)(jax.random.PRNGKey(0), _state(x, v), acts, params)
        for u, w in zip(jax.tree_util.tree_leaves(od), jax.tree_util.tree_leaves(oc)):
            np.testing.assert_array_equal(np.asarray(u), np.asarray(w))


def test_continuous_intermediate_and_clipped_actions(params):
    con = MountainCar(True)
    s = _state(-0.5, 0.01)
    _, s_half, *_ = con.step(None, s, jnp.array([0.5]), params)
    expected = np.float32(0.01) + np.float32(0.0005) - np.float32(0.0025) * np.cos(np.float32(-1.5))
    assert abs(float(s_half.velocity) - expected) < 1e-7
    _, s_big, *_ = con.step(None, s, jnp.array([7.0]), params)
    _, s_one, *_ = con.step(None, s, jnp.array([1.0]), params)
    assert float(s_big.velocity) == float(s_one.velocity)  # clipped to [-1, 1] inside step


def test_reward_at_goal_closed_form(env, params):
    # From just below the goal, every velocity that reaches it: reward 1 - |v'|/0.07.
    vs = np.linspace(0.005, 0.07, 50, dtype=np.float32)
    xs = np.full_like(vs, 0.499)
    obs, s2, rew, term, trunc, _ = _batched_step(env, params)(
        jax.random.PRNGKey(0), _state(xs, vs), jnp.zeros((50, 1)), params)
    assert np.all(np.asarray(term)) and not np.any(np.asarray(trunc))
    v2 = np.asarray(s2.velocity)
    np.testing.assert_allclose(np.asarray(rew), 1.0 - np.abs(v2) / 0.07, atol=1e-6)
    assert np.all(np.asarray(rew) >= 0.0) and np.all(np.asarray(rew) <= 1.0)
    # Arriving at the maximal speed gives 0; arriving slowly gives nearly 1.
    _, s, r, t, _, _ = env.step(None, _state(0.45, 0.07), jnp.array([1.0]), params)
    assert bool(t) and float(s.velocity) == pytest.approx(0.07) and float(r) == pytest.approx(0.0, abs=1e-6)
    _, s, r, t, _, _ = env.step(None, _state(0.4995, 0.0025), jnp.array([1.0]), params)
    assert bool(t) and float(r) > 0.95
    # Anywhere else the reward is exactly 0.
    _, _, r, t, _, _ = env.step(None, _state(-0.5, 0.0), jnp.array([1.0]), params)
    assert not bool(t) and float(r) == 0.0


def test_left_wall_resets_velocity(env, params):
    for x0, v0 in [(-1.2, -0.07), (-1.19, -0.05), (-1.15, -0.07)]:
        _, s, r, term, trunc, _ = env.step(None, _state(x0, v0), jnp.array([-1.0]), params)
        assert float(s.position) == np.float32(-1.2)
        assert float(s.velocity) == 0.0
        assert not bool(term) and float(r) == 0.0
    # Moving away from the wall keeps its velocity.
    _, s, *_ = env.step(None, _state(-1.2, 0.0), jnp.array([1.0]), params)
    assert float(s.velocity) > 0.0 and float(s.position) > -1.2


def test_truncation_at_200_separate_from_termination(env, params):
    assert env.max_steps == 200
    step = jax.jit(env.step)
    # Do nothing from the bottom: never reaches the goal, truncated exactly at step 200.
    _, s = env.reset_to(None, params, bottom_start())
    for t in range(1, 201):
        _, s, r, term, trunc, _ = step(None, s, jnp.array([0.0]), params)
        assert not bool(term)
        assert bool(trunc) == (t == 200), t
    # Reaching the goal on the very last step: terminated, not truncated.
    _, s, r, term, trunc, _ = step(None, _state(0.49, 0.05, t=199), jnp.array([1.0]), params)
    assert bool(term) and not bool(trunc) and int(s.time) == 200
    # A longer limit is honoured.
    env_long = MountainCar(False, max_steps=1000)
    _, s, _, term, trunc, _ = env_long.step(None, _state(-0.5, 0.0, t=199), jnp.array([0.0]), params)
    assert not bool(trunc)
    _, s, _, term, trunc, _ = env_long.step(None, _state(-0.5, 0.0, t=999), jnp.array([0.0]), params)
    assert bool(trunc) and not bool(term)


def test_resets_resample_inside_bounds(env, params):
    keys = jax.random.split(jax.random.PRNGKey(0), 2000)
    obs, s = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    obs = np.asarray(obs)
    assert obs.shape == (2000, 2) and obs.dtype == np.float32
    assert np.all(obs[:, 0] >= -1.2) and np.all(obs[:, 0] < 0.5)
    assert np.all(np.abs(obs[:, 1]) <= 0.07)
    assert np.all(np.asarray(s.time) == 0)
    # Different keys give different starts; the spread covers the whole box.
    assert len(np.unique(obs[:, 0])) > 1990 and len(np.unique(obs[:, 1])) > 1990
    assert obs[:, 0].min() < -1.15 and obs[:, 0].max() > 0.45
    assert obs[:, 1].min() < -0.065 and obs[:, 1].max() > 0.065
    # Same key, same start.
    o1, _ = env.reset(jax.random.PRNGKey(5), params)
    o2, _ = env.reset(jax.random.PRNGKey(5), params)
    np.testing.assert_array_equal(np.asarray(o1), np.asarray(o2))
    # Evaluation starts: n uniform random starts, batched.
    eo, es = env.evaluation_starts(jax.random.PRNGKey(1), params, 500)
    eo = np.asarray(eo)
    assert eo.shape == (500, 2) and np.asarray(es.position).shape == (500,)
    assert np.all(eo[:, 0] >= -1.2) and np.all(eo[:, 0] < 0.5) and np.all(np.abs(eo[:, 1]) <= 0.07)
    assert len(np.unique(eo[:, 0])) == 500
    # obs bounds
    lo, hi = env.obs_bounds(params)
    np.testing.assert_allclose(np.asarray(lo), [-1.2, -0.07], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(hi), [0.5, 0.07], rtol=1e-6)
    assert np.asarray(lo).dtype == np.float32


def test_reset_to_and_bottom_start(env, params):
    b = np.asarray(bottom_start())
    assert b.dtype == np.float32 and b.tolist() == [np.float32(-0.5), 0.0]
    obs, s = env.reset_to(jax.random.PRNGKey(0), params, bottom_start())
    np.testing.assert_array_equal(np.asarray(obs), b)
    assert int(s.time) == 0
    starts = jnp.array([[-0.5, 0.0], [0.1, -0.02], [-1.0, 0.07]], jnp.float32)
    obs, s = jax.vmap(env.reset_to, in_axes=(None, None, 0))(None, params, starts)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(starts))
    bs = jax.vmap(lambda _: bottom_start())(jnp.arange(4))
    assert bs.shape == (4, 2)


def test_jit_vmap_1000_instances_and_params(env, params):
    n = 1000
    keys = jax.random.split(jax.random.PRNGKey(0), n)

    @jax.jit
    def rollout(keys, params):
        obs, s = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def body(carry, _):
            s, ret, done = carry
            a = jnp.where(s.velocity >= 0, 1.0, -1.0)[:, None]
            obs, s2, r, term, trunc, _ = jax.vmap(env.step, in_axes=(None, 0, 0, None))(
                None, s, a, params)
            s2 = jax.tree_util.tree_map(lambda new, old: jnp.where(done, old, new), s2, s)
            ret = ret + jnp.where(done, 0.0, r)
            return (s2, ret, done | term | trunc), None

        (s, ret, done), _ = jax.lax.scan(body, (s, jnp.zeros(n), jnp.zeros(n, bool)), None,
                                         length=200)
        return s, ret, done

    s, ret, done = rollout(keys, params)
    assert np.asarray(s.position).shape == (n,)
    # Energy pumping reaches the goal from every start within 200 steps.
    assert np.all(np.asarray(done))
    assert np.all(np.asarray(s.position) >= 0.5)
    assert np.all(np.asarray(ret) >= 0.0) and np.all(np.asarray(ret) <= 1.0)
    # vmap over params (e.g. several gravities at once).
    grav = jnp.array([0.0025, 0.0, 0.005], jnp.float32)
    pb = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (3,)), params)
    pb = MountainCarParams(**{**{f: getattr(pb, f) for f in pb.__dataclass_fields__}, "gravity": grav})
    _, s2, *_ = jax.vmap(env.step, in_axes=(None, None, None, 0))(
        None, _state(0.0, 0.0), jnp.array([0.0]), pb)
    v = np.asarray(s2.velocity)
    assert v[1] == 0.0 and v[0] == pytest.approx(-0.0025, abs=1e-7) and v[2] == pytest.approx(-0.005, abs=1e-7)


def test_env_attributes_and_protocol(env):
    from envs.base import FunctionalEnv
    assert isinstance(env, FunctionalEnv)
    assert env.name == "mountain_car_discrete" and MountainCar(True).name == "mountain_car_continuous"
    assert env.obs_dim == 2 and env.action_dim == 1 and env.action_space.action_dim == 1
    import envs
    assert envs.make("mountain_car_continuous").continuous
    assert not envs.make("mountain_car_discrete").continuous


def test_render_rgb(env, params):
    _, s_bottom = env.reset_to(None, params, bottom_start())
    _, s_top = env.reset_to(None, params, jnp.array([0.4, 0.0]))
    img = env.render_rgb(s_bottom, params)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[0] > 50 and img.shape[1] > 50
    img2 = env.render_rgb(s_top, params)
    assert not np.array_equal(img, img2)  # the car moved
    red = lambda im: (im[..., 0] == 200) & (im[..., 1] == 40)
    assert red(img).sum() > 20 and red(img2).sum() > 20
    # The car is drawn further right in the second picture.
    assert np.nonzero(red(img2))[1].mean() > np.nonzero(red(img))[1].mean() + 50
