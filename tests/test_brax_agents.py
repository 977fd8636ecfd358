"""Brax's own PPO and SAC train on our environments (through ``envs.brax_adapter``)."""
from __future__ import annotations

import os
import subprocess
import sys

import jax
import numpy as np
import pytest

pytest.importorskip("brax.training.agents.ppo.train")

from envs.brax_adapter import brax_compat, train_ppo, train_sac  # noqa: E402


def _has_device_put_replicated():
    try:
        jax.device_put_replicated  # noqa: B018
        return True
    except AttributeError:
        return False


def test_compat_restores_the_jax_module():
    before = _has_device_put_replicated()
    with brax_compat():
        assert _has_device_put_replicated()
        out = jax.device_put_replicated({"a": np.arange(3.0)}, jax.local_devices())
        assert out["a"].shape == (len(jax.local_devices()), 3)
        np.testing.assert_array_equal(np.asarray(out["a"])[0], np.arange(3.0))
    assert _has_device_put_replicated() == before


# The corridor's runs take ~50 s each (its laser model compiles slowly): in the suite only
# with HEDGER_JAX_FULL_TESTS=1, to keep CI within its time.
CORRIDOR = pytest.param("corridor", marks=pytest.mark.skipif(
    not os.environ.get("HEDGER_JAX_FULL_TESTS"), reason="slow: set HEDGER_JAX_FULL_TESTS=1"))


EPISODE_LENGTH = 50
STEPS = 400
#: Observations of different states (for mountain car; the corridor's are 3-D).
PROBE = {"mountain_car_continuous": np.array([[-0.5, 0.0], [-1.0, 0.05], [0.3, -0.03]],
                                             np.float32),
         "corridor": np.array([[0.0, 0.0, 10.0], [0.3, 0.4, 6.0], [-0.2, -0.5, 2.0]],
                              np.float32)}


def _check_training_saw_the_env(env_name, params, metrics):
    """What a broken integration would get wrong: brax's observation normaliser counted
    every training step's observation (exactly STEPS) and its statistics are those of the
    env's observations (inside the observation bounds, each dimension varying); mountain
    car's evaluation episodes run to the episode length (the time limit is a truncation, not
    an early end; the corridor's walls may end them earlier)."""
    import envs

    env = envs.make(env_name)
    stats = params[0]
    assert int(stats.count) == STEPS
    low, high = (np.asarray(b) for b in env.obs_bounds(env.default_params()))
    mean, std = np.asarray(stats.mean), np.asarray(stats.std)
    assert np.all((low <= mean) & (mean <= high)), (mean, low, high)
    assert np.all(std > 0) and np.all(std <= high - low), std
    length = metrics["eval/avg_episode_length"]
    if env_name.startswith("mountain_car"):   # no goal within 50 steps: cut by the time limit
        assert length == EPISODE_LENGTH
    else:                                      # the corridor's walls end episodes earlier
        assert 1 <= length <= EPISODE_LENGTH
    assert np.isfinite(metrics["eval/episode_reward"])


def _deterministic_actions(make_policy, params, env_name):
    action, _ = make_policy(params, deterministic=True)(PROBE[env_name], jax.random.PRNGKey(0))
    action = np.asarray(action)
    assert action.shape == (3, 1) and np.all(np.abs(action) <= 1.0)
    assert len(np.unique(action)) == 3                     # depends on the observation
    return action


# Mountain car in the full suite: the corridor runs the same adapter path (BraxEnv,
# wrap_for_training, brax_compat, _train) in the quick tier.
@pytest.mark.parametrize("env_name", [pytest.param("mountain_car_continuous",
                                                  marks=pytest.mark.full), CORRIDOR])
def test_ppo_trains_end_to_end(env_name):
    """A few hundred environment steps of brax's PPO on the env: it trains on the env's
    observations (``_check_training_saw_the_env``), and the updates change the policy: its
    deterministic actions differ from those of the initial parameters (brax hands both to
    ``policy_params_fn``; the run is seeded, so this is deterministic)."""
    seen = []
    make_policy, params, metrics = train_ppo(
        env_name, num_timesteps=STEPS, num_envs=4, episode_length=EPISODE_LENGTH,
        unroll_length=5, batch_size=4, num_minibatches=2, num_updates_per_batch=1,
        num_evals=2, num_eval_envs=4, seed=0, normalize_observations=True,
        policy_params_fn=lambda step, _, p: seen.append((step, p)))
    _check_training_saw_the_env(env_name, params, metrics)
    assert [step for step, _ in seen] == [0, STEPS]
    trained = _deterministic_actions(make_policy, params, env_name)
    initial = _deterministic_actions(make_policy, seen[0][1], env_name)
    assert np.max(np.abs(trained - initial)) > 1e-3


# In the full suite (~11 s): PPO above takes the same adapter path (BraxEnv,
# wrap_for_training, brax_compat, _train) on every run; test_brax_adapter.py checks the
# dtypes and flags brax's replay buffer stores.
@pytest.mark.full
@pytest.mark.parametrize("env_name", ["mountain_car_continuous", CORRIDOR])
def test_sac_trains_end_to_end(env_name):
    """A few hundred environment steps of brax's SAC (replay buffer prefilled, then one
    gradient step per env step) on the env's observations (``_check_training_saw_the_env``);
    the evaluations happen before and after training."""
    progress = []
    make_policy, params, metrics = train_sac(
        env_name, num_timesteps=STEPS, num_envs=4, episode_length=EPISODE_LENGTH,
        batch_size=16, min_replay_size=64, max_replay_size=1000, grad_updates_per_step=1,
        num_evals=2, num_eval_envs=4, seed=0, normalize_observations=True,
        progress_fn=lambda step, m: progress.append(step))
    _check_training_saw_the_env(env_name, params, metrics)
    assert progress == [0, STEPS]
    _deterministic_actions(make_policy, params, env_name)


def test_importing_the_adapter_prints_no_warp_message():
    out = subprocess.run([sys.executable, "-c", "import envs.brax_adapter"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "warp" not in out.stdout and "warp" not in out.stderr
