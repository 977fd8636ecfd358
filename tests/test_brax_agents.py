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


@pytest.mark.parametrize("env_name", ["mountain_car_continuous", CORRIDOR])
def test_ppo_trains_end_to_end(env_name):
    """A few hundred environment steps of brax's PPO: it runs, evaluates and returns a policy
    that acts in the env's action range."""
    make_policy, params, metrics = train_ppo(
        env_name, num_timesteps=400, num_envs=4, episode_length=50, unroll_length=5,
        batch_size=4, num_minibatches=2, num_updates_per_batch=1, num_evals=2,
        num_eval_envs=4, seed=0)
    assert "eval/episode_reward" in metrics and np.isfinite(metrics["eval/episode_reward"])
    policy = make_policy(params, deterministic=True)
    obs_dim = 2 if env_name.startswith("mountain_car") else 3
    action, _ = policy(np.zeros((2, obs_dim), np.float32),
                       jax.random.PRNGKey(0))
    assert action.shape == (2, 1) and np.all(np.abs(np.asarray(action)) <= 1.0)


@pytest.mark.parametrize("env_name", ["mountain_car_continuous", CORRIDOR])
def test_sac_trains_end_to_end(env_name):
    make_policy, params, metrics = train_sac(
        env_name, num_timesteps=400, num_envs=4, episode_length=50, batch_size=16,
        min_replay_size=64, max_replay_size=1000, grad_updates_per_step=1, num_evals=2,
        num_eval_envs=4, seed=0)
    assert "eval/episode_reward" in metrics and np.isfinite(metrics["eval/episode_reward"])


def test_importing_the_adapter_prints_no_warp_message():
    out = subprocess.run([sys.executable, "-c", "import envs.brax_adapter"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "warp" not in out.stdout and "warp" not in out.stderr
