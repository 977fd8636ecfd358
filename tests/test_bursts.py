"""Exploratory bursts (``RunConfig(exploration="bursts")``, ``hedger_jax.bursts``): the burst
lengths follow the zeta pmf, and an episode's actions are each fresh step's action held for
its burst's length, in the jitted rollout and in the host loop alike (checked against a NumPy
simulation of the holding built from one-step draws)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.mountain_car import MountainCar
from hedger_jax import bursts, host_loop
from hedger_jax.agent import (RunConfig, explore_action, explore_action_burst, rollout,
                              training_act)
from hedger_jax.config import HedgerConfig
from hedger_jax.greedy import greedy_action, greedy_action_from_uniform, greedy_draws
from hedger_jax.learner import Hedger
from hedger_jax.memory import add_points, init_memory

#: Holding is the same for any action; a discrete set's greedy search compiles in a moment.
DISCRETE = HedgerConfig.for_env(MountainCar(continuous=False), capacity=256, bandwidth=0.1)


def _memory(cfg, n=200, seed=0):
    """A memory of n random mountain-car points with values in [0, 1]."""
    r = np.random.default_rng(seed)
    s = r.uniform([-1.2, -0.07], [0.6, 0.07], (n, 2)).astype(np.float32)
    a = (r.integers(-1, 2, (n, 1)) if cfg.is_discrete else r.uniform(-1, 1, (n, 1))).astype(
        np.float32)
    return add_points(cfg, init_memory(cfg), s, a, r.uniform(0, 1, n).astype(np.float32))


def test_burst_lengths_follow_the_truncated_zeta_pmf():
    """Inverse-CDF lengths: on an even grid of 10^6 draws each length n's share is P(n) (the
    float64 pmf n^-2 / sum_{m <= 1000} m^-2) to within the grid's spacing and float32's
    rounding of the CDF; the last draws below 1 give the longest, 1000."""
    u = jnp.arange(1_000_000, dtype=jnp.float32) / 1_000_000
    n = np.asarray(jax.jit(jax.vmap(bursts.duration))(u))
    share = np.bincount(n, minlength=bursts.MAX_STEPS + 1)[1:] / n.size
    m = np.arange(1, 1001, dtype=np.float64)
    pmf = m ** -2.0 / np.sum(m ** -2.0)
    np.testing.assert_allclose(share, pmf, rtol=0, atol=2e-6)
    assert n.min() == 1 and n.max() >= 990                 # P(1000) is below the spacing
    assert int(bursts.duration(jnp.float32(1.0 - 2 ** -24))) == bursts.MAX_STEPS


def _held(fresh_actions, fresh_lengths, length):
    """NumPy: the actions an episode takes when a step's fresh draw (action, burst length n)
    is held for n steps and a burst's later steps draw nothing."""
    out, t = [], 0
    while t < length:
        n = max(int(fresh_lengths[t]), 1)
        out += [fresh_actions[t]] * min(n, length - t)
        t += n
    return np.stack(out)


def _fresh(cfg, run, mem, obs, step_keys):
    """Each step's draw with no burst under way: (actions (T, A), burst lengths (T,))."""
    one = jax.jit(jax.vmap(lambda o, k: explore_action_burst(cfg, run, mem, o, k,
                                                             bursts.start(cfg))))
    a, b = one(obs, step_keys)
    return np.asarray(a), np.asarray(b.left) + 1


def _step_keys(key, n):
    """The acting keys of steps 0..n-1 of an episode keyed ``key`` (``rollout``'s)."""
    return jax.vmap(lambda t: jax.random.fold_in(jax.random.fold_in(key, t), 0))(jnp.arange(n))


def test_a_jitted_rollout_holds_each_burst_for_its_length():
    """epsilon = 1: every fresh step explores, so its draw depends on its key alone; the
    rollout's actions equal the NumPy holding of those draws; bursts of 2+ steps occur.
    (Discrete actions, cheap to compile; the host-loop test below holds continuous ones.)"""
    run = RunConfig(exploration="bursts", epsilon=1.0, reuse_neighbours=False)
    env, cfg = MountainCar(continuous=False), DISCRETE
    mem = _memory(cfg)
    params = env.default_params()
    key = jax.random.PRNGKey(5)
    obs0, s0 = env.reset(jax.random.PRNGKey(1), params)

    @jax.jit
    def episode(key):
        return rollout(env, params, training_act(cfg, run, mem), key, 120, obs0, s0)

    buf, length = episode(key)
    length = int(length)
    acts, lengths = _fresh(cfg, run, mem, jnp.zeros((length, 2)) + obs0,
                           _step_keys(key, length))
    np.testing.assert_array_equal(np.asarray(buf.action)[:length], _held(acts, lengths, length))
    assert lengths.max() >= 2 and lengths.min() == 1


def test_epsilon_zero_is_greedy_and_greedy_only_ends_a_burst():
    """No exploration: each step is the greedy action on its draws and no burst starts;
    greedy_only during a burst: the greedy action, and the burst is over. One-step
    ``explore_action`` under bursts is the first step of a burst. (Discrete actions: the
    holding does not depend on the action space.)"""
    cfg = DISCRETE
    mem = _memory(cfg)
    obs = jnp.asarray(np.random.default_rng(2).uniform([-1.2, -0.07], [0.6, 0.07], (16, 2)),
                      jnp.float32)
    keys = jax.random.split(jax.random.PRNGKey(9), 16)
    want = np.asarray(jax.jit(jax.vmap(lambda o, k: greedy_action(cfg, mem, o, k)[0]))(obs,
                                                                                 keys))
    n_g = greedy_draws(cfg)

    def greedy_on_the_step_s_draws(o, k):             # epsilon-greedy's draw layout
        u = jax.random.uniform(k, (1 + n_g + cfg.action_dim + 1,))
        return greedy_action_from_uniform(cfg, mem, o, u[1:1 + n_g])[0]

    greedy_run = RunConfig(exploration="bursts", epsilon=0.0)
    a, b, ref = jax.jit(jax.vmap(lambda o, k: explore_action_burst(
        cfg, greedy_run, mem, o, k, bursts.start(cfg)) + (greedy_on_the_step_s_draws(o, k),)))(
            obs, keys)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(ref))
    assert not np.asarray(b.left).any()

    run = RunConfig(exploration="bursts", epsilon=1.0)
    mid = bursts.Burst(jnp.full((1,), 0.77, jnp.float32), jnp.int32(5))
    held = jax.jit(jax.vmap(lambda o, k, flag: explore_action_burst(cfg, run, mem, o, k, mid,
                                                                    flag),
                            in_axes=(0, 0, None)))
    a, b = held(obs, keys, jnp.asarray(True))
    np.testing.assert_array_equal(np.asarray(a), want)
    assert not np.asarray(b.left).any()
    a, b = held(obs, keys, jnp.asarray(False))
    assert np.all(np.asarray(a) == np.float32(0.77)) and np.all(np.asarray(b.left) == 4)
    first = jax.jit(jax.vmap(lambda o, k: explore_action(cfg, run, mem, o, k)))(obs, keys)
    np.testing.assert_array_equal(np.asarray(first), _fresh(cfg, run, mem, obs, keys)[0])
    with pytest.raises(ValueError, match="bursts"):
        explore_action_burst(cfg, RunConfig(), mem, obs[0], keys[0], bursts.start(cfg))


def test_the_host_loop_holds_each_burst_for_its_length():
    """A Gymnasium task with a continuous action explores in bursts by default (a discrete
    one does not); the host loop's episode equals the NumPy holding of its one-step draws
    (each on the observation the episode met at that step)."""
    assert Hedger("CartPole-v1", capacity=64).run_config.exploration == "random"
    m = Hedger("MountainCarContinuous-v0", capacity=256, seed=3)
    assert m.run_config.exploration == "bursts"
    cfg = m.config
    mem = host_loop.refresh(_memory(cfg), config=cfg)                  # a memory to act on
    buf = host_loop.EpisodeBuffer(150, cfg.state_dim, cfg.action_dim)
    key = jax.random.PRNGKey(11)
    ep = host_loop.run_episode(m.env, host_loop.Explorer(mem, key, config=cfg, run=m.run_config),
                               seed=4, max_steps=150, buffer=buf)
    width = host_loop.kernel_width(mem, config=cfg)
    fresh = [host_loop.explore_step(mem, buf.obs[t], key, t, width, bursts.start(cfg),
                                    config=cfg, run=m.run_config) for t in range(ep.length)]
    acts = np.stack([np.asarray(a) for a, _ in fresh])
    lengths = np.asarray([int(b.left) + 1 for _, b in fresh])
    np.testing.assert_array_equal(buf.action[:ep.length], _held(acts, lengths, ep.length))
    assert lengths.max() >= 2


@pytest.mark.full
def test_bursts_take_the_continuous_car_to_the_goal():
    """What bursts are for: ``Hedger("MountainCarContinuous-v0")`` with its defaults reaches
    the goal and learns to (greedy return >= 90, the task's solved mark) within 30,000 steps on
    the tuning seed 100 (its runs were solved between 10,000 and 30,000 steps); with one-step
    epsilon-greedy no run reached the goal in 50,000 (docs/classic-control.md). About 95 s
    on 2 cores."""
    m = Hedger("MountainCarContinuous-v0", seed=100)
    m.learn(30_000)
    ev = m.evaluate(n_episodes=10)
    assert ev["success_rate"] >= 0.9 and ev["mean_return"] >= 90, ev
