"""The evaluation loop (``agent.evaluate_policy``): lanes that take the next waiting episode
when theirs ends give exactly the episodes of a one-at-a-time rollout, whatever the lane count."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.mountain_car import MountainCar
from hedger_jax import rng
from hedger_jax.agent import evaluate_policy

ENV = MountainCar(continuous=False)
PARAMS = ENV.default_params()
N, MAX_STEPS = 23, 110


def _noisy_pump(obs, key):
    """Pump with the velocity, but a random push a third of the time (uses the key, so the
    episodes' lengths vary and some reach MAX_STEPS)."""
    u = rng.uniform(key, 2)
    pump = jnp.where(obs[1] >= 0.0, 1.0, -1.0)
    return jnp.where(u[0] < 0.35, jnp.where(u[1] < 0.5, -1.0, 1.0), pump)[None]


def _one_at_a_time(key, n, max_steps):
    """Reference: each episode alone, step by step on the host (start i of
    ``evaluation_starts``, step-t key = fold_in(split(k_run, n)[i], t))."""
    k_starts, k_run = jax.random.split(key)
    _, states = ENV.evaluation_starts(k_starts, PARAMS, n)
    keys = jax.random.split(k_run, n)

    @jax.jit
    def step(state, obs, k):
        action = _noisy_pump(obs, rng.fold_in(k, 0))
        return ENV.step(rng.fold_in(k, 1), state, action, PARAMS)

    steps, success = [], []
    for i in range(n):
        state = jax.tree_util.tree_map(lambda a: a[i], states)
        obs = ENV.get_obs(state)
        reached = False
        for t in range(max_steps):
            obs, state, _, term, trunc, info = step(state, obs, rng.fold_in(keys[i], t))
            reached = reached or bool(info["reached_goal"] if "reached_goal" in info else term)
            if bool(term) or bool(trunc):
                break
        steps.append(t + 1 if reached else max_steps)
        success.append(reached)
    return np.asarray(steps, np.float32), np.asarray(success)


@pytest.fixture(scope="module")
def reference():
    return _one_at_a_time(jax.random.PRNGKey(5), N, MAX_STEPS)


@pytest.mark.parametrize("lanes", [1, 4, N, None])
def test_lanes_give_the_one_at_a_time_episodes(reference, lanes):
    steps, success = jax.jit(lambda k: evaluate_policy(ENV, PARAMS, _noisy_pump, k, N,
                                                       MAX_STEPS, lanes=lanes))(
        jax.random.PRNGKey(5))
    want_steps, want_success = reference
    assert 0 < want_success.sum() < N                 # both outcomes occur
    assert len(set(want_steps[want_success].tolist())) > 3   # lengths vary
    np.testing.assert_array_equal(np.asarray(steps), want_steps)
    np.testing.assert_array_equal(np.asarray(success), want_success)


def test_lanes_under_vmap_over_seeds_equal_separate_calls():
    keys = jax.random.split(jax.random.PRNGKey(9), 3)
    ev = jax.jit(jax.vmap(lambda k: evaluate_policy(ENV, PARAMS, _noisy_pump, k, N, MAX_STEPS,
                                                    lanes=4)))
    steps, success = ev(keys)
    for i in range(3):
        s1, ok1 = jax.jit(lambda k: evaluate_policy(ENV, PARAMS, _noisy_pump, k, N,
                                                    MAX_STEPS, lanes=N))(keys[i])
        np.testing.assert_array_equal(np.asarray(steps[i]), np.asarray(s1))
        np.testing.assert_array_equal(np.asarray(success[i]), np.asarray(ok1))


def test_lanes_must_be_positive():
    with pytest.raises(ValueError, match="lanes"):
        evaluate_policy(ENV, PARAMS, _noisy_pump, jax.random.PRNGKey(0), N, MAX_STEPS, lanes=0)
