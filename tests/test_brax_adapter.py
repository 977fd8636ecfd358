"""Brax adapter: brax's own wrappers on BraxEnv, key path, action mapping, truncation, resets."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

brax_training = pytest.importorskip("brax.envs.wrappers.training")

import envs  # noqa: E402
from envs.brax_adapter import BraxEnv, ResamplingAutoResetWrapper, wrap_for_training  # noqa: E402
from toy_functional_env import ToyEnv  # noqa: E402


def _noisy_params(noise=0.05, goal=0.9):
    return ToyEnv().default_params().__class__(noise=jnp.float32(noise), goal=jnp.float32(goal))


def test_properties_and_discrete_nearest_mapping():
    env = BraxEnv(ToyEnv(continuous=False))
    assert (env.observation_size, env.action_size, env.backend) == (2, 1, "jax")
    a = jnp.array([[-1.0], [-0.7], [-0.49], [0.0], [0.3], [0.51], [2.0]])
    got = np.asarray(env.action_value(a))[:, 0]
    np.testing.assert_array_equal(got, [-1.0, -1.0, 0.0, 0.0, 0.0, 1.0, 1.0])
    cont = BraxEnv(ToyEnv(continuous=True))
    np.testing.assert_allclose(np.asarray(cont.action_value(jnp.array([0.25, 3.0])[:, None]))[:, 0],
                               [0.25, 1.0])


def test_single_env_matches_functional_key_path():
    fenv, params = ToyEnv(continuous=True, max_steps=50), _noisy_params()
    env = BraxEnv(fenv, params=params)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    f_reset, f_step = jax.jit(fenv.reset), jax.jit(fenv.step)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(10, 1)).astype(np.float32)
    st = reset(jax.random.PRNGKey(5))
    key, sub = jax.random.split(jax.random.PRNGKey(5))
    obs, fs = f_reset(sub, params)
    np.testing.assert_array_equal(st.obs, obs)
    for a in actions:
        st = step(st, jnp.asarray(a))
        key, sub = jax.random.split(key)
        obs, fs, r, te, tr, _ = f_step(sub, fs, jnp.asarray(a), params)
        np.testing.assert_allclose(st.obs, obs, rtol=1e-6, atol=1e-8)  # XLA fusion ulps only
        assert float(st.reward) == float(r) and float(st.done) == float(te | tr)
        assert st.done.dtype == jnp.float32 and st.obs.dtype == jnp.float32


def test_own_time_limit_sets_truncation():
    env = BraxEnv(ToyEnv(max_steps=6), params=_noisy_params(noise=0.0))
    st = env.reset(jax.random.PRNGKey(0))
    flags = []
    for _ in range(6):
        st = env.step(st, jnp.zeros(1))  # a = 0 after mapping: never reaches the goal
        flags.append((float(st.done), float(st.info["truncation"]), float(st.info["terminated"])))
    assert flags == [(0.0, 0.0, 0.0)] * 5 + [(1.0, 1.0, 0.0)]
    # Terminal: done without truncation.
    env = BraxEnv(ToyEnv(max_steps=50), params=_noisy_params(noise=0.0, goal=-2.0))
    st = env.step(env.reset(jax.random.PRNGKey(0)), jnp.zeros(1))
    assert (float(st.done), float(st.info["truncation"]), float(st.info["terminated"])) == \
        (1.0, 0.0, 1.0)


def _scan(env, state, actions):
    def body(s, a):
        s = env.step(s, a)
        return s, (s.obs, s.done, s.info["truncation"], s.info["steps"])
    return jax.lax.scan(body, state, actions)


def test_brax_training_wrap_runs_and_matches_functional():
    """brax's own wrap (Vmap + Episode + AutoReset) on BraxEnv(time_limit=False)."""
    B, L, T = 4, 7, 9
    fenv, params = ToyEnv(continuous=True, max_steps=200), _noisy_params()
    env = brax_training.wrap(BraxEnv(fenv, params=params, time_limit=False),
                             episode_length=L, action_repeat=1)
    keys = jax.random.split(jax.random.PRNGKey(1), B)
    actions = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (T, B, 1)), jnp.float32)
    st0 = jax.jit(env.reset)(keys)
    assert st0.obs.shape == (B, 2) and st0.done.shape == (B,)
    st, (obs, done, trunc, steps) = jax.jit(lambda s, a: _scan(env, s, a))(st0, actions)
    # Episode limit: every slot is cut (truncation, not termination) at step L.
    np.testing.assert_array_equal(np.asarray(done)[L - 1], np.ones(B))
    np.testing.assert_array_equal(np.asarray(trunc)[L - 1], np.ones(B))
    assert not np.asarray(done)[:L - 1].any()
    # Before the limit the observations are the functional env's, batch-wise.
    def f_roll(k, acts):
        k, sub = jax.random.split(k)
        o, s = fenv.reset(sub, params)

        def body(c, a):
            k, s = c
            k, sub = jax.random.split(k)
            o, s, *_ = fenv.step(sub, s, a, params)
            return (k, s), o
        return jax.lax.scan(body, (k, s), acts)[1]
    want = jax.jit(jax.vmap(f_roll, in_axes=(0, 1), out_axes=1))(keys, actions[:L - 1])
    np.testing.assert_allclose(np.asarray(obs)[:L - 1], np.asarray(want), rtol=1e-6, atol=1e-7)
    # brax's AutoResetWrapper restores the cached first observation (the reason for ours).
    np.testing.assert_array_equal(np.asarray(obs)[L - 1], np.asarray(st0.obs))


def test_resampling_auto_reset_draws_fresh_starts():
    B, L, T = 4, 5, 12
    fenv = envs.make("mountain_car_discrete")
    env = wrap_for_training(fenv, episode_length=L)
    assert isinstance(env, ResamplingAutoResetWrapper)
    keys = jax.random.split(jax.random.PRNGKey(2), B)
    st0 = jax.jit(env.reset)(keys)
    st, (obs, done, trunc, steps) = jax.jit(lambda s, a: _scan(env, s, a))(
        st0, jnp.zeros((T, B, 1)))
    obs, done, trunc, steps = map(np.asarray, (obs, done, trunc, steps))
    # Truncation at L and 2L, counter restarts after each reset.
    assert done[L - 1].all() and trunc[L - 1].all() and done[2 * L - 1].all()
    np.testing.assert_array_equal(steps[:, 0], [1, 2, 3, 4, 5, 1, 2, 3, 4, 5, 1, 2])
    # Fresh starts: the first obs after each reset differs from the cached first one and
    # from each other, and is a valid mountain-car start (v within the start range).
    firsts = [np.asarray(st0.obs), obs[L - 1], obs[2 * L - 1]]
    assert not np.allclose(firsts[0], firsts[1]) and not np.allclose(firsts[1], firsts[2])
    assert (np.abs(firsts[1][:, 1]) <= 0.07).all()
    # The step right after a reset continues from the fresh start with a = 0 dynamics.
    mc = fenv
    p = mc.default_params()
    _, s = jax.vmap(mc.reset_to, in_axes=(None, None, 0))(jax.random.PRNGKey(0), p,
                                                          jnp.asarray(obs[L - 1]))
    o_next = jax.vmap(lambda s: mc.step(jax.random.PRNGKey(0), s, jnp.zeros(1), p)[0])(s)
    np.testing.assert_allclose(obs[L], np.asarray(o_next), rtol=1e-5, atol=1e-7)


def test_brax_env_on_real_envs_jit_vmap():
    """brax's VmapWrapper over BraxEnv(mountain car): a jitted batch of resets and one step
    are the functional env's along the documented key path (reset: split the key, reset with
    the second half; step: split the carried key, step with the second half)."""
    fenv = envs.make("mountain_car_continuous")
    params = fenv.default_params()
    env = brax_training.VmapWrapper(BraxEnv(fenv))
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    st0 = jax.jit(env.reset)(keys)
    st = jax.jit(env.step)(st0, jnp.ones((3, env.action_size)))
    assert st.obs.shape == (3, env.observation_size) and st.info["rng"].shape == (3, 2)

    def reference(key):
        rng, sub = jax.random.split(key)
        obs0, s = fenv.reset(sub, params)
        rng, sub = jax.random.split(rng)
        obs1, _, r, te, tr, _ = fenv.step(sub, s, jnp.ones(1), params)
        return obs0, obs1, r, (te | tr).astype(jnp.float32), rng

    obs0, obs1, r, done, rng = jax.jit(jax.vmap(reference))(keys)
    np.testing.assert_array_equal(np.asarray(st0.obs), np.asarray(obs0))
    np.testing.assert_allclose(np.asarray(st.obs), np.asarray(obs1), rtol=1e-6, atol=1e-8)
    assert not np.array_equal(np.asarray(st.obs), np.asarray(st0.obs))      # the cars moved
    np.testing.assert_array_equal(np.asarray(st.reward), np.asarray(r))
    np.testing.assert_array_equal(np.asarray(st.done), np.asarray(done))
    np.testing.assert_array_equal(np.asarray(st.info["rng"]), np.asarray(rng))
