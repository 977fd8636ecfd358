"""Gymnasium adapter: env checker, rendering, key path, Discrete mapping, time limits."""
from __future__ import annotations

import os
import subprocess
import sys
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs.gym_adapter import REGISTERED_IDS, FunctionalGymEnv, register_envs
from toy_functional_env import ToyEnv

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _available_ids():
    """Registered ids whose env module exists (others are skipped, not failed)."""
    ids = register_envs()
    return [pytest.param(i, marks=pytest.mark.skipif(i not in ids, reason=f"{i}: env module "
                                                     "not available")) for i in REGISTERED_IDS]


# ---- toy env (independent of the real envs) --------------------------------------------

@pytest.mark.parametrize("continuous", [False, True])
def test_check_env_toy(continuous):
    env = FunctionalGymEnv(ToyEnv(continuous), render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no spec" warning for a non-registered env
        check_env(env, skip_render_check=False)
    assert env.metadata["jax"] is True
    assert env.metadata["render_fps"] == ToyEnv.render_fps


def _functional_rollout(fenv, params, seed, actions):
    """The documented key path, driven through the (separately jitted) functional API."""
    reset, step = jax.jit(fenv.reset), jax.jit(fenv.step)
    key = jax.random.PRNGKey(seed)
    key, sub = jax.random.split(key)
    obs, state = reset(sub, params)
    out = [np.asarray(obs)]
    flags = []
    for a in actions:
        key, sub = jax.random.split(key)
        obs, state, r, te, tr, _ = step(sub, state, jnp.asarray(a, jnp.float32), params)
        out.append(np.asarray(obs))
        flags.append((float(r), bool(te), bool(tr)))
    return np.stack(out), flags


def test_rollout_matches_functional_key_path():
    fenv = ToyEnv(continuous=False, max_steps=40)
    params = fenv.default_params().__class__(noise=jnp.float32(0.05), goal=jnp.float32(0.9))
    env = FunctionalGymEnv(fenv, params=params)
    rng = np.random.default_rng(0)
    idx = rng.integers(0, 3, size=12)
    values = fenv.action_space.values_array()[idx]
    want_obs, want_flags = _functional_rollout(fenv, params, 7, values)
    obs, _ = env.reset(seed=7)
    got = [obs]
    got_flags = []
    for i in idx:
        obs, r, te, tr, _ = env.step(int(i))
        got.append(obs)
        got_flags.append((r, te, tr))
        assert obs.dtype == np.float32 and obs.shape == (2,)
        assert obs in env.observation_space
    np.testing.assert_array_equal(np.stack(got), want_obs)  # noise makes the key path visible
    assert got_flags == want_flags
    # Unseeded reset continues the chain (differs from a reseed), reseeding reproduces.
    o_next, _ = env.reset()
    o_again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(o_again, want_obs[0])
    assert not np.array_equal(o_next, want_obs[0])


def test_discrete_index_mapping():
    env = FunctionalGymEnv(ToyEnv(continuous=False))
    assert isinstance(env.action_space, gymnasium.spaces.Discrete) and env.action_space.n == 3
    for i, v in enumerate([-1.0, 0.0, 1.0]):
        np.testing.assert_array_equal(env.action_value(i), np.array([v], np.float32))
        np.testing.assert_array_equal(env.action_value(np.int64(i)), np.array([v], np.float32))
    with pytest.raises(ValueError):
        env.action_value(3)
    # Index 2 (= +1) moves the noise-free toy cart by +0.1 per step.
    params = ToyEnv().default_params().__class__(noise=jnp.float32(0.0), goal=jnp.float32(0.9))
    env = FunctionalGymEnv(ToyEnv(), params=params, reset_options={"start": [0.0, 0.0]})
    env.reset(seed=0)
    obs, *_ = env.step(2)
    np.testing.assert_allclose(obs, [0.1, 0.1], rtol=1e-6)
    obs, *_ = env.step(0)
    np.testing.assert_allclose(obs, [0.0, -0.1], atol=1e-6)
    cont = FunctionalGymEnv(ToyEnv(continuous=True))
    assert isinstance(cont.action_space, gymnasium.spaces.Box)
    assert cont.action_space.shape == (1,) and cont.action_space.dtype == np.float32


def test_truncation_at_time_limit_and_override():
    params = ToyEnv().default_params().__class__(noise=jnp.float32(0.0), goal=jnp.float32(0.9))
    env = FunctionalGymEnv(ToyEnv(max_steps=5), params=params,
                           reset_options={"start": [0.0, 0.0]})
    env.reset(seed=0)
    flags = [env.step(1)[2:4] for _ in range(5)]  # action 0.0: never reaches the goal
    assert flags == [(False, False)] * 4 + [(False, True)]
    # Own time limit: longer episodes than the env's max_steps, env flag ignored.
    env = FunctionalGymEnv(ToyEnv(max_steps=5), params=params, time_limit=8,
                           reset_options={"start": [0.0, 0.0]})
    env.reset(seed=0)
    flags = [env.step(1)[3] for _ in range(8)]
    assert flags == [False] * 7 + [True] and env.elapsed_steps == 8
    # Termination before the limit (goal 0.85: x = 0.6, 0.7, 0.8, 0.9 -> terminal at step 4).
    params = params.__class__(noise=jnp.float32(0.0), goal=jnp.float32(0.85))
    env = FunctionalGymEnv(ToyEnv(max_steps=50), params=params,
                           reset_options={"start": [0.5, 0.0]})
    env.reset(seed=0)
    out = [env.step(2) for _ in range(4)]
    assert [(o[2], o[3]) for o in out] == [(False, False)] * 3 + [(True, False)]
    assert out[3][1] == 1.0


def test_human_render_headless():
    pytest.importorskip("pygame")
    code = ("import os; os.environ['SDL_VIDEODRIVER']='dummy';"
            "import sys; sys.path.insert(0, 'tests');"
            "from toy_functional_env import ToyEnv; from envs.gym_adapter import FunctionalGymEnv;"
            "e = FunctionalGymEnv(ToyEnv(), render_mode='human'); e.reset(seed=0);"
            "e.step(0); assert e.render() is None; e.close(); print('ok')")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]


# ---- registered ids ---------------------------------------------------------------------

def test_register_is_idempotent():
    first = register_envs()
    second = register_envs()
    assert first == second
    for gym_id in first:
        spec = gymnasium.spec(gym_id)
        assert spec.max_episode_steps == envs.make(REGISTERED_IDS[gym_id]).max_steps


@pytest.mark.parametrize("gym_id", _available_ids())
def test_registered_env_checker_and_render(gym_id):
    env = gymnasium.make(gym_id, render_mode="rgb_array")
    # The corridor's laser pipeline takes seconds to compile: skip the checker's extra
    # instances for other render modes there (rendering is checked below).
    check_env(env.unwrapped, skip_render_check=gym_id == "HedgerCorridor-v0")
    obs, _ = env.reset(seed=1)
    assert obs in env.observation_space
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
    assert frame.ndim == 3 and frame.shape[2] == 3
    # A random rollout's observations stay inside observation_space.
    for _ in range(60):
        obs, r, te, tr, _ = env.step(env.action_space.sample())
        assert obs in env.observation_space, (gym_id, obs)
        if te or tr:
            break
    env.close()


@pytest.mark.parametrize("gym_id", _available_ids())
def test_registered_rollout_matches_functional(gym_id):
    kwargs = {}
    if gym_id == "HedgerCorridor-v0":
        # Same adapter code path; the geometric observation compiles much faster than the
        # laser pipeline (the laser obs are covered by the checker test above).
        kwargs = {"env_kwargs": {"observation": "geometric"}}
    fenv = envs.make(REGISTERED_IDS[gym_id], **kwargs.get("env_kwargs", {}))
    params = fenv.default_params()
    env = gymnasium.make(gym_id, **kwargs)
    rng = np.random.default_rng(1)
    if fenv.action_space.is_discrete:
        idx = rng.integers(0, fenv.action_space.n_actions, size=30)
        gym_actions = [int(i) for i in idx]
        values = fenv.action_space.values_array()[idx]
    else:
        low, high = np.asarray(fenv.action_space.low), np.asarray(fenv.action_space.high)
        values = rng.uniform(low, high, size=(30, len(low))).astype(np.float32)
        gym_actions = list(values)
    want, want_flags = _functional_rollout(fenv, params, 3, values)
    obs, _ = env.reset(seed=3)
    got, got_flags = [obs], []
    for a in gym_actions:
        obs, r, te, tr, _ = env.step(a)
        got.append(obs)
        got_flags.append((r, te, tr))
        if te or tr:
            break
    n = len(got)
    # Same key path; only XLA fusion differences (float32 ulps) are allowed.
    np.testing.assert_allclose(np.stack(got), want[:n], rtol=1e-5, atol=1e-6)
    assert got_flags == want_flags[:n - 1]


def test_mountain_car_truncates_at_max_steps_under_make():
    if "HedgerMountainCar-v0" not in register_envs():
        pytest.skip("mountain car not available")
    env = gymnasium.make("HedgerMountainCar-v0")
    fenv = envs.make("mountain_car_discrete")
    # Bottom of the hill doing nothing never reaches the goal: truncated exactly at max_steps.
    env.reset(seed=0, options={"start": [-0.5, 0.0]})
    n = 0
    while True:
        _, _, te, tr, _ = env.step(1)
        n += 1
        if te or tr:
            break
    assert (n, te, tr) == (fenv.max_steps, False, True)
    # Longer episodes through make: time_limit (the env) and max_episode_steps (TimeLimit).
    env = gymnasium.make("HedgerMountainCar-v0", time_limit=300, max_episode_steps=300)
    env.reset(seed=0, options={"start": [-0.5, 0.0]})
    n = 0
    while True:
        _, _, te, tr, _ = env.step(1)
        n += 1
        if te or tr:
            break
    assert (n, te, tr) == (300, False, True)


def test_import_does_not_pull_brax():
    code = ("import sys, importlib.util, envs, envs.gym_adapter;"
            "importlib.util.find_spec('hedger_jax') and __import__('hedger_jax');"
            "bad = [m for m in sys.modules if m == 'brax' or m.startswith('brax.')];"
            "assert not bad, bad; print('ok')")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]
