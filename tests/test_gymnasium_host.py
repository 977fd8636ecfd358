"""``Hedger`` on Gymnasium's own envs (the host loop), with tiny capacities and budgets.

The learners share one config per env (the host loop's jitted pieces compile once per
config) and a capacity below 512, where the neighbour search is brute force: it compiles
about three times faster than the grid index, which this file is not about."""
import re

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

import envs.gym_adapter  # noqa: F401  (registers the project's ids)
from envs.mountain_car import MountainCar
from hedger_jax.checkpoint import CheckpointError
from hedger_jax.environments import GymnasiumEnv
from hedger_jax.learner import Hedger
from hedger_jax.validation import InvalidInputError

CAP = 500


def _arrays(mem):
    return [np.asarray(getattr(mem, k)) for k in ("points", "values", "size", "head", "flags")]


class Counter(gymnasium.Env):
    """obs = (t, 3.0) after t steps, reward 1 per step; terminated at ``terminate_at`` (if
    set). The second dimension is declared unbounded and never changes."""

    def __init__(self, terminate_at=None, high=np.inf):
        self.observation_space = spaces.Box(np.array([0.0, -high], np.float32),
                                            np.array([10.0, high], np.float32))
        self.action_space = spaces.Discrete(3, start=-1)
        self.terminate_at = terminate_at
        self.t = 0

    def _obs(self):
        return np.array([self.t, 3.0], np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        assert self.action_space.contains(action), action
        self.t += 1
        terminated = self.terminate_at is not None and self.t >= self.terminate_at
        return self._obs(), 1.0, terminated, False, {}


class Spaces(gymnasium.Env):
    """An env with the given spaces (never stepped)."""

    def __init__(self, observation_space, action_space):
        self.observation_space, self.action_space = observation_space, action_space


CAR = dict(capacity=CAP, bandwidth=0.05, gamma=0.99, preset="paper")
PENDULUM = dict(capacity=CAP, bandwidth=0.1, gamma=0.9, preset="paper")


@pytest.fixture(scope="module")
def car():
    model = Hedger("MountainCar-v0", seed=3, **CAR)
    model.learn(150)            # whole episodes: one of 200 steps
    return model


@pytest.fixture(scope="module")
def pendulum():
    model = Hedger("Pendulum-v1", seed=1, **PENDULUM)
    model.learn(150)
    return model


def test_learn_counts(car, pendulum):
    """learn runs whole episodes (the last one overshoots the budget), counts them and
    stores every step; the callback after each chunk can stop learning."""
    for model, cap in ((car, 200), (pendulum, 200)):
        assert model.host_loop and model.env.max_steps == cap
        assert model.num_timesteps == 200 and model.num_episodes == 1
        assert len(model.ep_info_buffer) == 1
        assert int(model.memory.size) == model.num_timesteps
        assert all(e["l"] == cap for e in model.ep_info_buffer)  # no goal reached this early
    assert all(e["r"] == -200.0 for e in car.ep_info_buffer)
    assert all(-16.3 * 200 <= e["r"] < 0 for e in pendulum.ep_info_buffer)
    seen = []
    car2 = Hedger("MountainCar-v0", chunk_episodes=1, **CAR)
    car2.learn(1000, callback=lambda info: seen.append(info) or False)
    assert len(seen) == 1 and car2.num_episodes == 1 and seen[0]["lengths"].tolist() == [200]
    assert seen[0]["num_timesteps"] == seen[0]["memory_size"] == 200


def _visited_observations(model, n, seed):
    """n observations near stored ones (the memory's states, unscaled, jittered by 1 %)."""
    cfg = model.config
    pts = np.asarray(model.memory.points)[:cfg.state_dim, :int(model.memory.size)].T
    obs = pts / np.asarray(cfg.input_scale[:cfg.state_dim]) + np.asarray(
        cfg.input_offset[:cfg.state_dim])
    rng = np.random.default_rng(seed)
    pick = obs[rng.choice(len(obs), n, replace=False)]
    return (pick + 0.01 * rng.standard_normal(pick.shape) / np.asarray(
        cfg.input_scale[:cfg.state_dim])).astype(np.float32)


def test_predict_valid_actions(car, pendulum):
    rng = np.random.default_rng(0)
    obs = rng.uniform([-1.2, -0.07], [0.6, 0.07], (6, 2)).astype(np.float32)
    a, state = car.predict(obs[0])
    assert state is None and a.shape == () and a.dtype == np.int64
    batch, _ = car.predict(obs)
    assert batch.shape == (6,) and all(car.env.gym_env.action_space.contains(int(x))
                                       for x in batch)
    np.testing.assert_array_equal(car.predict_action_value(obs)[:, 0], batch)
    th = rng.uniform(-np.pi, np.pi, 6)
    pobs = np.stack([np.cos(th), np.sin(th), rng.uniform(-8, 8, 6)], 1).astype(np.float32)
    a, _ = pendulum.predict(pobs[0])
    assert a.shape == (1,) and a.dtype == np.float32
    assert pendulum.env.gym_env.action_space.contains(a)
    noisy, _ = pendulum.predict(pobs, deterministic=False)
    assert noisy.shape == (6, 1) and np.all(np.abs(noisy) <= 2.0)
    env = gymnasium.make("Pendulum-v1")
    o, _ = env.reset(seed=0)
    o2, *_ = env.step(pendulum.predict(o)[0])
    assert env.observation_space.contains(o2)


def test_predict_is_greedy_in_q_value(car):
    """The predicted (greedy) action of the discrete car has the largest Q(s, a) of the three
    actions, as ``q_value`` (a separate program) predicts them ("don't know" counting as the
    default value; ties to rounding allowed), near the states it has visited."""
    obs = _visited_observations(car, 8, seed=2)
    chosen = car.predict(obs)[0]
    q = np.stack([car.q_value(obs, np.full((8, 1), float(a), np.float32))[0]
                  for a in range(3)], axis=1)
    known = np.stack([car.q_value(obs, np.full((8, 1), float(a), np.float32))[1]
                      for a in range(3)], axis=1)
    best = q.max(axis=1)
    np.testing.assert_array_less(best - 1e-5 * (1 + np.abs(best)), q[np.arange(8), chosen] + 1e-12)
    # The comparison is about learned values: most candidates are known, and not all equal.
    assert known.mean() >= 0.5 and np.ptp(q[known]) > 0


def test_scaling_rules(car, pendulum):
    # Bounded boxes: [0, 1] from the bounds; continuous actions span 0.2 ([-2, 2] x 0.05).
    np.testing.assert_allclose(car.config.input_offset, [-1.2, -0.07, 0.0], rtol=1e-6)
    np.testing.assert_allclose(car.config.input_scale, [1 / 1.8, 1 / 0.14, 1.0], rtol=1e-6)
    assert car.config.discrete_actions == ((0.0,), (1.0,), (2.0,))
    np.testing.assert_allclose(pendulum.config.input_scale, [0.5, 0.5, 1 / 16, 0.05], rtol=1e-6)
    assert (pendulum.config.action_low, pendulum.config.action_high) == ((-2.0,), (2.0,))
    assert Hedger("Pendulum-v1", capacity=64, action_scale=1.0, preset="paper").config.input_scale[-1] == 1.0


def _documented_range(env, n=2000, seed=0):
    """The rule of ``envs.scaling``, in NumPy: the observation of each of n random-action
    steps (seeded env and action space, restarts on episode end), min/max widened by 10 %
    per side, a constant dimension a unit range."""
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    seen = []
    for _ in range(n):
        seen.append(np.asarray(obs, np.float64))
        obs, _, te, tr, _ = env.step(env.action_space.sample())
        if te or tr:
            obs, _ = env.reset()
    x = np.array(seen)
    lo, hi = x.min(0), x.max(0)
    span = hi - lo
    return np.where(span > 0, lo - 0.1 * span, lo - 0.5), np.where(span > 0, hi + 0.1 * span,
                                                                      hi + 0.5)


def test_unbounded_dimensions_from_samples():
    model = Hedger("CartPole-v1", capacity=64, bandwidth=0.2, preset="paper")
    lo, hi = _documented_range(gymnasium.make("CartPole-v1"))
    box = model.env.gym_env.observation_space
    lo[[0, 2]], hi[[0, 2]] = box.low[[0, 2]], box.high[[0, 2]]   # bounded: kept
    np.testing.assert_allclose(model.config.input_offset[:4], lo, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(model.config.input_scale[:4], 1 / (hi - lo), rtol=1e-5)
    assert np.all(np.isfinite(model.config.input_scale))
    # A constant dimension declared unbounded (inf or float32's max): a unit range.
    for high in (np.inf, np.finfo(np.float32).max):
        m = Hedger(TimeLimit(Counter(high=high), 5), capacity=64, bandwidth=0.01, preset="paper")
        np.testing.assert_allclose(m.config.input_offset[:2], [0.0, 2.5])
        np.testing.assert_allclose(m.config.input_scale[:2], [0.1, 1.0])


@pytest.mark.parametrize("terminate_at, expect", [(None, [6.0] * 5), (5, [1.0] + [6.0] * 4)])
def test_truncation_is_not_terminal(terminate_at, expect):
    # alpha = 1, no neighbours within reach: a stored value is r + gamma * default_value
    # (1 + 0.5 * 10 = 6) unless the step is terminal (1). Reverse replay stores the last step
    # first. A time-limit truncation at step 5 must bootstrap like any other step.
    env = TimeLimit(Counter(terminate_at), max_episode_steps=5)
    m = Hedger(env, capacity=64, bandwidth=0.01, alpha=1.0, gamma=0.5, default_value=10.0,
               preset="paper")
    m.learn(1)
    assert m.num_episodes == 1 and m.num_timesteps == 5
    np.testing.assert_allclose(np.asarray(m.memory.values)[:5], expect, rtol=1e-6)
    t_seen = np.asarray(m.memory.points)[0, :5] / m.config.input_scale[0]
    np.testing.assert_allclose(t_seen, [4, 3, 2, 1, 0], atol=1e-5)    # newest first
    r = m.evaluate(3)
    assert r == {"mean_steps": 5.0, "mean_return": 5.0,       # not a goal task: no success_rate
                 "terminated_rate": 0.0 if terminate_at is None else 1.0}
    a, _ = m.predict(np.array([2.0, 3.0], np.float32))
    assert int(a) in (-1, 0, 1)                                        # Discrete(3, start=-1)


def test_evaluate(car):
    r1 = car.evaluate(2)
    assert set(r1) == {"mean_steps", "mean_return", "terminated_rate", "success_rate"}
    assert 1 <= r1["mean_steps"] <= 200 and r1["mean_return"] == -r1["mean_steps"]
    assert car.evaluate(2) == r1                                       # same seeds, same policy
    assert car.evaluate(2, max_steps=7) == {"mean_steps": 7.0, "mean_return": -7.0,
                                            "terminated_rate": 0.0, "success_rate": 0.0}


def test_save_load_round_trip(car, tmp_path):
    path = car.save(tmp_path / "car.npz")
    loaded = Hedger.load(path)
    assert loaded.host_loop and loaded.env_id == "MountainCar-v0"
    assert loaded.config == car.config and loaded.run_config == car.run_config
    for x, y in zip(_arrays(car.memory), _arrays(loaded.memory)):
        assert x.tobytes() == y.tobytes()
    obs = np.random.default_rng(1).uniform([-1.2, -0.07], [0.6, 0.07], (16, 2))
    np.testing.assert_array_equal(loaded.predict(obs)[0], car.predict(obs)[0])
    assert loaded.evaluate(2) == car.evaluate(2)
    a, b = Hedger.load(path).learn(200), Hedger.load(path).learn(200)  # same key stream
    for x, y in zip(_arrays(a.memory), _arrays(b.memory)):
        assert x.tobytes() == y.tobytes()


def test_save_load_instance_needs_env(pendulum, tmp_path):
    m = Hedger(gymnasium.make("Pendulum-v1"), config=pendulum.config, seed=1)
    m.memory = pendulum.memory
    path = m.save(tmp_path / "p.npz")
    with pytest.raises(CheckpointError, match=r"built from a Gymnasium env instance "
                                              r"\(Pendulum-v1\); pass env="):
        Hedger.load(path)
    loaded = Hedger.load(path, env=gymnasium.make("Pendulum-v1"))
    obs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -3.0]], np.float32)
    np.testing.assert_array_equal(loaded.predict(obs)[0], pendulum.predict(obs)[0])


@pytest.mark.parametrize("obs_space, act_space, named", [
    (spaces.Dict({"x": spaces.Box(-1, 1, (2,))}), spaces.Discrete(2), "observation"),
    (spaces.Box(-1, 1, (2, 2)), spaces.Discrete(2), "observation"),
    (spaces.Box(-1, 1, (2,)), spaces.MultiDiscrete([2, 3]), "action"),
    (spaces.Box(-1, 1, (2,)), spaces.Tuple((spaces.Discrete(2), spaces.Discrete(2))), "action"),
    (spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (2,)), "action"),
    (spaces.Box(-1, 1, (2,)), spaces.Box(-np.inf, np.inf, (1,)), "action"),
])
def test_unsupported_spaces(obs_space, act_space, named):
    space = obs_space if named == "observation" else act_space
    with pytest.raises(ValueError, match=f"unsupported {named} space {re.escape(str(space))}"):
        Hedger(Spaces(obs_space, act_space))


def test_project_envs_keep_the_fast_path():
    m = Hedger(gymnasium.make("HedgerMountainCar-v0"), capacity=64)
    assert not m.host_loop and m.env == MountainCar() and m.env_id == "HedgerMountainCar-v0"
    m2 = Hedger("HedgerMountainCar-v0", capacity=64)
    assert m2.config == m.config and not m2.host_loop
    host = Hedger("MountainCar-v0", capacity=64, preset="paper")
    assert isinstance(host.env, GymnasiumEnv)
    with pytest.raises(InvalidInputError, match="runs in the host loop"):
        host.learn_from_demonstrations(object.__new__(type("P", (), {"act": 0, "init": 0})),
                                       n_episodes=1)
    with pytest.raises(ValueError, match="unknown environment 'NoSuchEnv-v9'"):
        Hedger("NoSuchEnv-v9")


def test_import_pulls_no_env_module():
    import os
    import subprocess
    import sys

    code = ("import sys, hedger_jax; bad = [m for m in sys.modules if m.split('.')[0] in "
            "('gymnasium', 'envs', 'gymnax')]; assert not bad, bad; print('ok')")
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]


def test_an_episode_reads_the_kernel_width_once(car):
    """The host loop reads the data-chosen kernel width once per episode (``kernel_width``)
    and passes it to each step: the epsilon-greedy and greedy actions equal those of steps
    that read it from the memory themselves, and the width is the memory's
    ``data_bandwidth``; with a fixed width (the paper's preset) there is nothing to pass."""
    import jax
    from hedger_jax.data_bandwidth import data_bandwidth
    from hedger_jax.host_loop import explore_step, greedy_step, kernel_width

    assert kernel_width(car.memory, config=car.config) is None
    cfg, run, mem = car.config.replace(bandwidth_k=4), car.run_config, car.memory
    width = kernel_width(mem, config=cfg)
    assert float(width.bandwidth) == float(data_bandwidth(cfg, mem))
    assert float(width.bandwidth) != cfg.bandwidth
    rng = np.random.default_rng(0)
    obs = rng.uniform([-1.2, -0.07], [0.6, 0.07], (16, 2)).astype(np.float32)
    key = jax.random.PRNGKey(5)
    for t, o in enumerate(obs):
        for step, kw in ((explore_step, dict(config=cfg, run=run)),
                         (greedy_step, dict(config=cfg))):
            np.testing.assert_array_equal(np.asarray(step(mem, o, key, t, width, **kw)),
                                          np.asarray(step(mem, o, key, t, **kw)))
