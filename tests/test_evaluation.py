"""The evaluation loop (``agent.evaluate_policy``): lanes that take the next waiting episode
when theirs ends give exactly the episodes of a one-at-a-time rollout, whatever the lane count."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.mountain_car import MountainCar
from hedger_jax.agent import evaluate_policy

ENV = MountainCar(continuous=False)
PARAMS = ENV.default_params()
N, MAX_STEPS = 23, 110


def _noisy_pump(obs, key):
    """Pump with the velocity, but a random push a third of the time (uses the key, so the
    episodes' lengths vary and some reach MAX_STEPS)."""
    u = jax.random.uniform(key, (2,))
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
        action = _noisy_pump(obs, jax.random.fold_in(k, 0))
        return ENV.step(jax.random.fold_in(k, 1), state, action, PARAMS)

    steps, success = [], []
    for i in range(n):
        state = jax.tree_util.tree_map(lambda a: a[i], states)
        obs = ENV.get_obs(state)
        reached = False
        for t in range(max_steps):
            obs, state, _, term, trunc, info = step(state, obs, jax.random.fold_in(keys[i], t))
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


# ------------------------------------------------------------ make_train's block evaluation
from hedger_jax.agent import RunConfig, evaluate, explore_action, make_train  # noqa: E402
from hedger_jax.config import HedgerConfig  # noqa: E402
from hedger_jax.greedy import greedy_action  # noqa: E402
from hedger_jax.memory import add_points, init_memory  # noqa: E402

#: The run of test_determinism.py (same env, config and run config): the compilation cache
#: serves this file's ``train``, ``init`` and ``run_block`` programs from that file's.
#: Training episodes (60 steps) are capped below the evaluation's cap (80).
CFG = HedgerConfig.for_env(ENV, capacity=256, bandwidth=0.05)
RUN = RunConfig(n_blocks=2, episodes_per_block=2, eval_episodes=6, eval_max_steps=80,
                train_max_steps=60, reuse_neighbours=False)


# Continuous (~11 s) in the full suite: the discrete case checks the same greedy_only switch.
@pytest.mark.parametrize("continuous, exploration", [
    (False, "random"), pytest.param(True, "gaussian", marks=pytest.mark.full)])
def test_explore_action_greedy_only_is_the_greedy_action(continuous, exploration):
    """``explore_action`` with ``greedy_only`` True (a Python bool, a concrete array or a
    traced value) is ``greedy_action``'s action key by key; traced False is the default
    (epsilon-greedy) path, which here (epsilon 0.9) explores."""
    env = MountainCar(continuous=continuous)
    cfg = HedgerConfig.for_env(env, capacity=256, bandwidth=0.1)
    run = RunConfig(exploration=exploration, epsilon=0.9)
    r = np.random.default_rng(0)
    s = r.uniform([-1.2, -0.07], [0.6, 0.07], (200, 2)).astype(np.float32)
    a = (r.uniform(-1, 1, (200, 1)) if continuous else r.integers(-1, 2, (200, 1)))
    mem = add_points(cfg, init_memory(cfg), s, a.astype(np.float32),
                     r.uniform(0, 1, 200).astype(np.float32))
    obs = jnp.asarray(s[:40] + 0.01)
    keys = jax.random.split(jax.random.PRNGKey(3), 40)
    want = np.asarray(jax.jit(jax.vmap(lambda o, k: greedy_action(cfg, mem, o, k)[0]))(
        obs, keys))
    explore = jax.jit(jax.vmap(lambda o, k, flag: explore_action(cfg, run, mem, o, k, flag),
                               in_axes=(0, 0, None)))
    for flag in (True, jnp.asarray(True)):
        np.testing.assert_array_equal(np.asarray(explore(obs, keys, flag)), want,
                                      err_msg=f"greedy_only={flag!r}")
    explored = np.asarray(explore(obs, keys, jnp.asarray(False)))
    default = jax.jit(jax.vmap(lambda o, k: explore_action(cfg, run, mem, o, k)))(obs, keys)
    np.testing.assert_array_equal(explored, np.asarray(default))
    assert not np.array_equal(explored, want)                     # epsilon 0.9


def _block_case(continuous):
    """(env, config, run config) of the block-evaluation test."""
    if not continuous:
        return ENV, CFG, RUN
    env = MountainCar(continuous=True)
    return env, HedgerConfig.for_env(env, capacity=2000, bandwidth=0.05, action_scale=0.5), RUN


# Continuous (~40 s) only in the full suite: the discrete case checks the same loop.
@pytest.mark.parametrize("continuous", [False, pytest.param(True, marks=pytest.mark.full)])
def test_block_evaluations_are_evaluate_episode_for_episode(continuous):
    """``make_train``'s blocks run their evaluation episodes through the training rollout
    (greedy): the results are ``evaluate``'s on the same memory and key, bit for bit -- for
    the first evaluation (``init`` calls ``evaluate``) and for a later block. Training
    episodes are capped below the evaluation's cap (the rollout's buffer is shorter)."""
    env, cfg, run = _block_case(continuous)
    assert run.train_max_steps < run.eval_max_steps
    tr = make_train(env, cfg, run)
    key = jax.random.PRNGKey(5)
    state0, r0 = jax.jit(tr.init)(key)
    _, results = jax.jit(tr.train)(key)
    state1, r1 = jax.jit(tr.run_block)(state0)
    k_eval = jax.random.split(state0.key, 3)[2]
    ref = jax.jit(lambda m, k: evaluate(env, env.default_params(), cfg, m, k,
                                        run.eval_episodes, run.eval_max_steps,
                                        refresh=False))(state1.memory, k_eval)
    for i, want in ((0, r0), (1, r1)):
        got = jax.tree_util.tree_map(lambda x: x[i], results)
        for j, (a, b) in enumerate(zip(jax.tree_util.tree_leaves(got),
                                       jax.tree_util.tree_leaves(want))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b),
                                          err_msg=f"block {i}, leaf {j}")
    np.testing.assert_array_equal(np.asarray(r1.evaluation.mean_steps),
                                  np.asarray(ref.mean_steps))
    np.testing.assert_array_equal(np.asarray(r1.evaluation.success_rate),
                                  np.asarray(ref.success_rate))
    assert int(r1.episodes) == 2 and int(state1.memory.size) > 0
    # Episodes of both outcomes (goal and timeout): the comparison is not of constants.
    assert 0.0 < float(r1.evaluation.success_rate) < 1.0
