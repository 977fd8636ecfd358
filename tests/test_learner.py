"""The SB3-style ``Hedger`` learner, with tiny budgets (capacity ~1000, a few hundred steps).

The learners that learn search their memory by brute force (``LEARNER``): it compiles about
three times faster than the grid index that capacity ~1000 would choose, and ``Hedger`` does
not depend on the search (the grid index is covered by test_index.py, by make_train in
test_replay_cache.py and by its rebuild on load in test_checkpoint.py)."""
import dataclasses
import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs.gym_adapter  # noqa: F401  (registers the Gymnasium ids)
from envs.demonstrations import save_demonstrations
from envs.demonstrations import Demonstrations
from envs.demonstrators import energy_pumping_policy
from envs.mountain_car import MountainCar, bottom_start
from hedger_jax.agent import RunConfig
from hedger_jax.checkpoint import CheckpointError
from hedger_jax.config import HedgerConfig
from hedger_jax.learner import ENV_PRESETS, Hedger
from hedger_jax.memory import FLAG_FULL, FLAG_NONFINITE, MemoryFullError, NonFiniteValueError
from hedger_jax.validation import InvalidInputError

CAP = 1024
LEARNER = dict(capacity=CAP, neighbour_index="brute")
RUN = RunConfig(eval_episodes=8, eval_max_steps=60, train_max_steps=100)


def _energy_pumping_demos(starts, max_steps=400):
    """Demonstrations of the energy-pumping controller, rolled out in NumPy (no compilation):
    the mountain-car dynamics of ``envs.mountain_car`` in float32."""
    f = np.float32
    E = len(starts)
    arr = {k: np.zeros((E, max_steps) + s, dt) for k, s, dt in (
        ("obs", (2,), np.float32), ("action", (1,), np.float32), ("reward", (), np.float32),
        ("next_obs", (2,), np.float32), ("terminated", (), bool), ("truncated", (), bool),
        ("valid", (), bool))}
    for e, (x, v) in enumerate(starts):
        x, v = f(x), f(v)
        for t in range(max_steps):
            a = f(1.0) if v >= 0 else f(-1.0)
            v2 = np.clip(v + a * f(0.001) - np.cos(f(3.0) * x) * f(0.0025), f(-0.07), f(0.07))
            x2 = np.clip(x + v2, f(-1.2), f(0.5))
            v2 = f(0.0) if (x2 <= f(-1.2) and v2 < 0) else v2
            term = bool(x2 >= f(0.5) and v2 >= 0)
            arr["obs"][e, t] = (x, v)
            arr["action"][e, t] = a
            arr["next_obs"][e, t] = (x2, v2)
            arr["reward"][e, t] = (f(1.0) - abs(v2) / f(0.07)) if term else f(0.0)
            arr["terminated"][e, t] = term
            arr["valid"][e, t] = True
            x, v = x2, v2
            if term:
                break
        else:
            arr["truncated"][e, max_steps - 1] = True
    return Demonstrations(**arr, env_id="mountain_car_discrete", source="energy pumping (test)")


@pytest.fixture(scope="module")
def demos():
    return _energy_pumping_demos([(-0.5, 0.0), (-0.9, 0.01)])


@pytest.fixture(scope="module")
def trained(demos):
    model = Hedger("HedgerMountainCar-v0", run_config=RUN, seed=1, **LEARNER)
    model.learn_from_demonstrations(demos)
    model.learn(250)
    return model


def _obs(n=8, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-1.2, -0.07], [0.5, 0.07], (n, 2)).astype(np.float32)


def _arrays(mem):
    return [np.asarray(getattr(mem, k)) for k in ("points", "values", "size", "head", "flags")]


def test_construction_defaults():
    m = Hedger("HedgerMountainCar-v0", capacity=CAP)
    expect = HedgerConfig.for_env(MountainCar(), capacity=CAP,
                                  **ENV_PRESETS["mountain_car_discrete"]["hedger"])
    assert m.config == expect and m.run_config == RunConfig()
    assert int(m.memory.size) == 0 and m.num_timesteps == 0
    m2 = Hedger(MountainCar(), config=expect, run_config=RUN, alpha=0.5)
    assert m2.config.alpha == 0.5 and m2.env_id == "mountain_car_discrete"
    with pytest.raises(ValueError, match="unknown environment 'NoSuchEnv-v0'"):
        Hedger("NoSuchEnv-v0")
    with pytest.raises(ValueError, match=r"config.state_dim 3 != env obs_dim 2"):
        Hedger(MountainCar(), config=HedgerConfig(3, 1, discrete_actions=((1.0,),)))
    with pytest.raises(ValueError, match="config is continuous but the env's action space is "
                                         "discrete"):
        Hedger(MountainCar(), config=HedgerConfig(2, 1))
    with pytest.raises(ValueError, match=r"config.discrete_actions: \(2.0,\) is not an action"):
        Hedger(MountainCar(), config=HedgerConfig(2, 1, discrete_actions=((2.0,), (1.0,))))
    with pytest.raises(ValueError, match="bandwidth: must be a finite number > 0"):
        Hedger("HedgerMountainCar-v0", bandwidth=0.0)


def test_demonstrations_object_file_and_policy(demos, trained, tmp_path):
    n = demos.n_transitions
    assert trained.num_demo_timesteps == n
    a = Hedger("HedgerMountainCar-v0", run_config=RUN, seed=1, **LEARNER)
    a.learn_from_demonstrations(demos)
    assert int(a.memory.size) == n
    path = save_demonstrations(tmp_path / "d.npz", demos)
    b = Hedger("HedgerMountainCar-v0", run_config=RUN, seed=1, **LEARNER)
    b.learn_from_demonstrations(path)
    for x, y in zip(_arrays(a.memory), _arrays(b.memory)):
        assert x.tobytes() == y.tobytes()
    c = Hedger("HedgerMountainCar-v0", run_config=RUN, seed=1, **LEARNER)
    c.learn_from_demonstrations(energy_pumping_policy(), n_episodes=2, start=bottom_start(),
                                max_steps=150)
    assert 0 < c.num_demo_timesteps == int(c.memory.size) <= 300
    with pytest.raises(InvalidInputError, match="a policy needs n_episodes >= 1"):
        c.learn_from_demonstrations(energy_pumping_policy())


def test_demonstrations_refused(demos):
    m = Hedger("HedgerMountainCar-v0", run_config=RUN, capacity=CAP)
    with pytest.raises(InvalidInputError, match=r"recorded for env 'mountain_car_discrete', this "
                                                r"learner's env is 'mountain_car_continuous'"):
        Hedger("HedgerMountainCarContinuous-v0", capacity=CAP).learn_from_demonstrations(demos)
    bad = demos.action.copy()
    bad[0, 0, 0] = 0.5
    from hedger_jax.train import Transition
    tr = Transition(demos.obs, bad, demos.reward, demos.next_obs, demos.terminated, demos.valid)
    with pytest.raises(InvalidInputError, match=r"demonstrations.action \(valid steps\): 1 "
                                                r"action\(s\) not in the discrete set"):
        m.learn_from_demonstrations(tr)
    rew = demos.reward.copy()
    rew[1, 3] = np.nan
    with pytest.raises(InvalidInputError, match=r"demonstrations.reward: 1 value\(s\) is NaN or "
                                                r"inf; first at index \(1, 3\): nan"):
        m.learn_from_demonstrations(tr._replace(action=demos.action, reward=rew))
    with pytest.raises(ValueError, match="missing file"):
        m.learn_from_demonstrations("/nonexistent/demos.npz")
    assert int(m.memory.size) == 0


def test_learn_counts_progress_and_callback(trained):
    assert trained.num_timesteps >= 250 and trained.num_episodes >= 1
    assert int(trained.memory.size) == trained.num_demo_timesteps + trained.num_timesteps
    assert all(1 <= e["l"] <= 100 for e in trained.ep_info_buffer)
    m = Hedger("HedgerMountainCar-v0", run_config=RUN, seed=2, **LEARNER)
    seen = []
    m.learn(5000, progress_bar=True, callback=lambda info: seen.append(info) or False)
    # Stopped after the first chunk (<= chunk_episodes episodes of <= 100 steps).
    assert len(seen) == 1 and 1 <= m.num_episodes <= 10 and m.num_timesteps <= 1000
    assert seen[0]["memory_size"] == m.num_timesteps == int(np.sum(seen[0]["lengths"]))
    with pytest.raises(InvalidInputError, match=r"total_timesteps: must be an integer >= 0"):
        m.learn(-5)
    m.learn(0)


def test_learn_raises_memory_flags():
    m = Hedger("HedgerMountainCar-v0", run_config=RUN, capacity=CAP)
    m.memory = m.memory._replace(flags=jnp.int32(FLAG_NONFINITE))
    with pytest.raises(NonFiniteValueError):
        m.learn(10)
    m.memory = m.memory._replace(flags=jnp.int32(FLAG_FULL))
    with pytest.raises(MemoryFullError):
        m.learn(10)


def test_predict_semantics(trained):
    obs = _obs()
    a, state = trained.predict(obs[0])
    assert state is None and a.shape == () and a.dtype == np.int64 and 0 <= a < 3
    batch, _ = trained.predict(obs)
    assert batch.shape == (8,) and batch.dtype == np.int64
    # An observation's action does not depend on its batch position.
    np.testing.assert_array_equal(batch[5], trained.predict(obs[5])[0])
    values = trained.predict_action_value(obs)
    assert values.shape == (8, 1) and values.dtype == np.float32
    np.testing.assert_array_equal(trained.action_value(batch), values)
    assert set(np.unique(values)) <= {-1.0, 0.0, 1.0}
    # deterministic=True is repeatable; False draws from the key stream (epsilon-greedy).
    np.testing.assert_array_equal(trained.predict(obs)[0], batch)
    key_before = np.asarray(trained.key).copy()
    noisy, _ = trained.predict(obs, deterministic=False)
    assert noisy.shape == (8,) and not np.array_equal(np.asarray(trained.key), key_before)
    v, known = trained.q_value(obs[0], values[0])
    assert np.shape(v) == () and np.isfinite(v) and known.dtype == np.bool_
    vb, kb = trained.q_value(obs, values)
    assert vb.shape == (8,) and vb[0] == v
    # Odd batch sizes are padded to a bucket: the same answers row by row.
    np.testing.assert_array_equal(trained.predict(obs[:5])[0], batch[:5])
    np.testing.assert_array_equal(trained.q_value(obs[:3], values[:3])[0], vb[:3])


@pytest.mark.parametrize("obs, match", [
    (np.array([np.nan, 0.0]), r"observation: 1 value\(s\) is NaN or inf"),
    (np.zeros(3), r"observation: expected last dimension 2"),
    (np.zeros((2, 2, 2)), r"observation: expected 1 or 2 dimensions"),
])
def test_predict_refuses_bad_observations(trained, obs, match):
    with pytest.raises(InvalidInputError, match=match):
        trained.predict(obs)


def test_q_value_and_action_value_refused(trained):
    with pytest.raises(InvalidInputError, match=r"action_value: 1 action\(s\) not in the "
                                                r"discrete set"):
        trained.q_value([0.0, 0.0], [0.3])
    with pytest.raises(InvalidInputError, match=r"index out of range \[0, 3\)"):
        trained.action_value(3)


def evaluate_policy(model, env, n_eval_episodes=2):
    """A minimal SB3 ``evaluate_policy`` loop."""
    returns, lengths = [], []
    for i in range(n_eval_episodes):
        obs, _ = env.reset(seed=i)
        done, total, n = False, 0.0, 0
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            total += reward
            n += 1
            done = terminated or truncated
        returns.append(total)
        lengths.append(n)
    return float(np.mean(returns)), lengths


def test_evaluate_policy_with_gym_env(trained):
    env = gymnasium.make("HedgerMountainCar-v0")
    mean_return, lengths = evaluate_policy(trained, env)
    assert all(1 <= n <= 200 for n in lengths) and 0.0 <= mean_return <= 1.0
    env.close()


def test_continuous_predict_with_gym_env():
    """A continuous learner's prediction is the action vector the Gymnasium env takes; with
    nothing learned it is random, but deterministic (the fixed key) unless asked otherwise."""
    m = Hedger("HedgerMountainCarContinuous-v0", capacity=256)
    a, _ = m.predict(np.array([-0.5, 0.0], np.float32))
    assert a.shape == (1,) and a.dtype == np.float32 and -1.0 <= a[0] <= 1.0
    env = gymnasium.make("HedgerMountainCarContinuous-v0")
    obs, _ = env.reset(seed=0)
    action, _ = m.predict(obs)
    assert env.action_space.contains(action)
    np.testing.assert_array_equal(m.predict(obs)[0], action)
    np.testing.assert_array_equal(m.predict_action_value(obs), action)
    obs2, *_ = env.step(action)
    assert env.observation_space.contains(obs2) and not np.array_equal(obs2, obs)
    env.close()


def test_evaluate(trained):
    r1 = trained.evaluate(8, max_steps=60)
    r2 = trained.evaluate()
    assert r1 == r2                                           # same starts, same greedy policy
    assert 1.0 <= r1["mean_steps"] <= 60.0 and 0.0 <= r1["success_rate"] <= 1.0
    with pytest.raises(InvalidInputError):
        trained.evaluate(0)


def test_save_load_round_trip(trained, tmp_path):
    path = trained.save(tmp_path / "agent.npz")
    loaded = Hedger.load(path)
    assert loaded.config == trained.config and loaded.run_config == trained.run_config
    assert loaded.env_id == "HedgerMountainCar-v0" and loaded.seed == trained.seed
    for x, y in zip(_arrays(trained.memory), _arrays(loaded.memory)):
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    np.testing.assert_array_equal(np.asarray(loaded.key), np.asarray(trained.key))
    assert (loaded.num_timesteps, loaded.num_demo_timesteps, loaded.num_episodes) == \
        (trained.num_timesteps, trained.num_demo_timesteps, trained.num_episodes)
    for seed in range(4):
        obs = _obs(8, seed=10 + seed)
        np.testing.assert_array_equal(loaded.predict(obs)[0], trained.predict(obs)[0])
        acts = trained.predict_action_value(obs)
        v1, k1 = trained.q_value(obs, acts)
        v2, k2 = loaded.q_value(obs, acts)
        assert v1.tobytes() == v2.tobytes() and np.array_equal(k1, k2)
    assert loaded.evaluate() == trained.evaluate()
    # Both continue identically (same key stream, same memory): bitwise.
    a = Hedger.load(path).learn(120)
    b = Hedger.load(path).learn(120)
    for x, y in zip(_arrays(a.memory), _arrays(b.memory)):
        assert x.tobytes() == y.tobytes()
    with pytest.raises(CheckpointError, match=r"config mismatch in fields \['capacity'\]"):
        Hedger.load(path, config=trained.config.replace(capacity=2048))


def test_load_custom_env_params(tmp_path):
    env = MountainCar(max_steps=120)
    params = env.default_params()
    params = dataclasses.replace(params, force=jnp.float32(0.0012))
    m = Hedger(env, env_params=params, run_config=RUN, capacity=256)
    path = m.save(tmp_path / "c.npz")
    loaded = Hedger.load(path)
    assert loaded.env.max_steps == 120
    assert float(loaded.env_params.force) == pytest.approx(0.0012)
    jax.tree_util.tree_map(lambda x, y: np.testing.assert_array_equal(x, y),
                           loaded.env_params, params)
