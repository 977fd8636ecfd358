"""``envs.gymnax_adapter.GymnaxEnv``: on a stand-in that follows gymnax's API (always), and
step for step against gymnax's own ``step`` on its own states (when gymnax is installed)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import scaling
from envs.gymnax_adapter import GymnaxEnv
from envs.pytree import pytree_dataclass
from hedger_jax.agent import RunConfig, make_train, rollout
from hedger_jax.config import HedgerConfig


# ---- a stand-in with gymnax's API -------------------------------------------------------
@pytree_dataclass
class WalkParams:
    max_steps_in_episode: int = 12
    noise: float = 0.01


@pytree_dataclass
class WalkState:
    x: jax.Array
    v: jax.Array
    time: int


class _Box:
    def __init__(self, low, high, shape):
        self.low, self.high, self.shape = low, high, shape


class _Discrete:
    def __init__(self, n):
        self.n, self.shape = n, ()


class Walk:
    """A noisy 1-D walk in gymnax's style: v <- clip(v + 0.1 (a - 1) + noise N(0, 1), +-0.3)
    (discrete a in {0, 1, 2}) or v + 0.1 a (continuous a in [-1, 1]); x <- x + v; natural
    terminal at x >= 1. obs = (x, v, 1.0): v and the constant third entry declared
    unbounded. ``folds``: gymnax < 1.0's ``done`` (time limit folded in, no
    ``is_truncated``); else gymnax 1.0's."""

    def __init__(self, continuous=False, folds=False, action_space=None):
        self.continuous, self.folds = continuous, folds
        self._action_space = action_space
        if not folds:
            self.is_truncated = lambda state, params: state.time >= params.max_steps_in_episode

    @property
    def default_params(self):
        return WalkParams()

    def reset_env(self, key, params):
        x = jax.random.uniform(key, (), minval=-0.5, maxval=0.5)
        state = WalkState(x=x, v=jnp.array(0.0), time=0)
        return self.get_obs(state), state

    def get_obs(self, state):
        return jnp.array([state.x, state.v, 1.0])

    def step_env(self, key, state, action, params):
        if self.continuous:
            push = 0.1 * jnp.clip(action, -1.0, 1.0)[0]
        else:
            push = 0.1 * (action - 1)       # an int index, as gymnax's discrete envs take
        v = jnp.clip(state.v + push + params.noise * jax.random.normal(key), -0.3, 0.3)
        state = WalkState(x=state.x + v, v=v, time=state.time + 1)
        done = state.x >= 1.0
        if self.folds:
            done = done | (state.time >= params.max_steps_in_episode)
        return self.get_obs(state), state, jnp.where(done, 1.0, 0.0), done, {"discount": 1.0}

    def observation_space(self, params):
        inf = jnp.finfo(jnp.float32).max
        return _Box(jnp.array([-3.0, -inf, -jnp.inf]), jnp.array([3.0, inf, jnp.inf]), (3,))

    def action_space(self, params=None):
        if self._action_space is not None:
            return self._action_space
        return _Box(-1.0, 1.0, (1,)) if self.continuous else _Discrete(3)


def _state(x, v, t):
    return WalkState(x=jnp.float32(x), v=jnp.float32(v), time=jnp.int32(t))


def test_description_and_hash():
    gx = Walk()
    env = GymnaxEnv(gx)
    assert (env.obs_dim, env.max_steps, env.name) == (3, 12, "gymnax/Walk")
    assert env.action_space.values == ((0.0,), (1.0,), (2.0,)) and not env.folds_time_limit
    assert GymnaxEnv(Walk(folds=True)).folds_time_limit
    cont = GymnaxEnv(Walk(continuous=True))
    assert cont.action_space.values is None and cont.action_space.low == (-1.0,)
    assert env == GymnaxEnv(gx) and hash(env) == hash(GymnaxEnv(gx)) and env != GymnaxEnv(Walk())
    assert GymnaxEnv(gx, WalkParams(max_steps_in_episode=30)).max_steps == 30
    with pytest.raises(NotImplementedError):
        env.render_rgb(None)
    for space in (_Box(-1.0, 1.0, (2,)), _Box(-np.inf, np.inf, (1,)), object()):
        with pytest.raises(ValueError, match="unsupported gymnax action space"):
            GymnaxEnv(Walk(action_space=space))


@pytest.mark.parametrize("folds", [False, True])
def test_terminated_and_truncated(folds):
    env = GymnaxEnv(Walk(folds=folds))
    p = env.default_params()
    step = jax.jit(env.step)
    key = jax.random.PRNGKey(0)
    stay = jnp.array([1.0])
    # The time limit alone: truncated, not terminated.
    _, s, r, te, tr, _ = step(key, _state(0.0, 0.0, 11), stay, p)
    assert (bool(te), bool(tr), int(s.time)) == (False, True, 12)
    # A natural terminal before the limit: terminated only.
    _, _, r, te, tr, _ = step(key, _state(0.95, 0.2, 3), stay, p)
    assert (bool(te), bool(tr), float(r)) == (True, False, 1.0)
    # Neither.
    _, _, _, te, tr, _ = step(key, _state(0.0, 0.0, 3), stay, p)
    assert (bool(te), bool(tr)) == (False, False)
    # A natural terminal on the limit's step: a fold has lost the difference (documented).
    _, _, _, te, tr, _ = step(key, _state(0.95, 0.2, 11), stay, p)
    assert (bool(te), bool(tr)) == ((False, True) if folds else (True, False))


@pytest.mark.parametrize("continuous", [False, True])
def test_step_is_step_env_with_gymnax_key_path(continuous):
    gx = Walk(continuous=continuous)
    env = GymnaxEnv(gx)
    p = env.default_params()
    key = jax.random.PRNGKey(3)
    obs, s = env.reset(key, p)
    ref_obs, ref_s = gx.reset_env(key, p)
    np.testing.assert_array_equal(obs, ref_obs)
    assert obs.dtype == jnp.float32 and s.time.dtype == jnp.int32
    for t, a in enumerate([2.0, 0.0, 1.0, 2.0, 2.0] if not continuous else
                          [0.5, -1.0, 0.25, 1.0, 0.0]):
        k = jax.random.fold_in(key, t)
        out = env.step(k, s, jnp.array([a], jnp.float32), p)
        gx_action = jnp.array([a]) if continuous else int(a)
        ref = gx.step_env(jax.random.split(k)[0], s, gx_action, p)
        np.testing.assert_allclose(out[0], ref[0], rtol=1e-6)
        np.testing.assert_allclose(float(out[2]), float(ref[2]))
        assert float(out[1].x) == pytest.approx(float(ref[1].x), rel=1e-6)
        s = out[1]


def test_obs_bounds_rule():
    env = GymnaxEnv(Walk())
    p = env.default_params()
    samples = np.asarray(env.random_observations(p), np.float64)
    assert samples.shape == (scaling.SAMPLE_STEPS, 3)
    # The first sample is the first reset's observation; episodes restart (every start has
    # v = 0 and |x| <= 0.5, and no observation is past a terminal x >= 1).
    k0, _ = jax.random.split(jax.random.PRNGKey(scaling.SAMPLE_SEED))
    np.testing.assert_array_equal(samples[0], env.reset(k0, p)[0])
    starts = np.flatnonzero(samples[:, 1] == 0.0)
    assert len(starts) >= scaling.SAMPLE_STEPS // 12 and np.all(samples[:, 0] < 1.0)
    low, high = (np.asarray(b) for b in env.obs_bounds(p))
    v = samples[:, 1]
    span = v.max() - v.min()
    np.testing.assert_allclose([low[1], high[1]], [v.min() - 0.1 * span, v.max() + 0.1 * span],
                               rtol=1e-5)
    np.testing.assert_allclose([low[0], high[0], low[2], high[2]], [-3.0, 3.0, 0.5, 1.5])
    jitted = jax.jit(env.obs_bounds)(p)
    np.testing.assert_allclose(jitted[0], low, rtol=1e-6)


def test_make_train_jitted_and_vmapped():
    env = GymnaxEnv(Walk(), WalkParams(max_steps_in_episode=30))
    config = HedgerConfig.for_env(env, capacity=400, bandwidth=0.1, gamma=0.9)
    run = RunConfig(n_blocks=2, episodes_per_block=4, eval_episodes=4, eval_max_steps=30)
    train = make_train(env, config, run).train
    state, res = jax.jit(jax.vmap(train))(jax.random.split(jax.random.PRNGKey(0), 2))
    steps = np.asarray(res.evaluation.mean_steps)
    assert steps.shape == (2, 3) and np.all((steps >= 1) & (steps <= 30))
    pts = np.asarray(res.points)
    assert np.all(pts[:, 0] == 0) and np.all(np.diff(pts, axis=1) > 0)
    np.testing.assert_array_equal(np.asarray(state.memory.size), pts[:, -1])
    assert np.all(np.asarray(res.flags) == 0)


def test_continuous_rollout_records_truncation():
    env = GymnaxEnv(Walk(continuous=True))
    p = env.default_params()
    obs, s = env.reset(jax.random.PRNGKey(1), p)
    ep, n = jax.jit(lambda k: rollout(env, p, lambda k, o, st: (jnp.zeros((1,)), st), k, 20,
                                      obs, s))(jax.random.PRNGKey(2))
    # Standing still never reaches x >= 1: 12 steps (the time limit), none terminal.
    assert int(n) == 12 and not np.any(np.asarray(ep.terminated))
    assert np.all(np.asarray(ep.valid)[:12]) and not np.any(np.asarray(ep.valid)[12:])


# ---- real gymnax ---------------------------------------------------------------------------
GYMNAX_IDS = ["MountainCar-v0", "MountainCarContinuous-v0", "CartPole-v1", "Pendulum-v1",
              "Acrobot-v1"]


@pytest.mark.parametrize("env_id", GYMNAX_IDS)
def test_against_gymnax_step(env_id):
    gymnax = pytest.importorskip("gymnax")
    gx, p = gymnax.make(env_id)
    env = GymnaxEnv(env_id)
    n_envs, n_steps = 32, env.max_steps + 20     # every lane reaches the time limit
    keys = jax.random.split(jax.random.PRNGKey(0), n_envs)
    _, states = jax.vmap(gx.reset, in_axes=(0, None))(keys, p)
    space = gx.action_space(p)

    def one(state, key):
        k_a, k_s = jax.random.split(key)
        a = space.sample(k_a)
        value = jnp.reshape(jnp.asarray(a, jnp.float32), (1,))
        g_obs, g_state, g_r, g_te, g_tr, info = gx.step(k_s, state, a, p)
        obs, _, r, te, tr, _ = env.step(k_s, state, value, p)
        return g_state, (info["final_observation"], obs, g_r, r, g_te, te, g_tr, tr)

    def body(states, key):
        return jax.vmap(one)(states, jax.random.split(key, n_envs))

    _, out = jax.jit(lambda s: jax.lax.scan(body, s, jax.random.split(
        jax.random.PRNGKey(1), n_steps)))(states)
    g_obs, obs, g_r, r, g_te, te, g_tr, tr = (np.asarray(x) for x in out)
    np.testing.assert_allclose(obs, g_obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r, g_r, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(te, g_te)
    np.testing.assert_array_equal(tr, g_tr & ~g_te)
    # Random actions end every CartPole episode by a terminal, every other one by the limit.
    assert (te.any(), tr.any()) == ((True, False) if env_id == "CartPole-v1" else (False, True))


def test_gymnax_cartpole_bounds_and_make_train():
    pytest.importorskip("gymnax")
    env = GymnaxEnv("CartPole-v1")
    p = env.default_params()
    low, high = (np.asarray(b) for b in env.obs_bounds(p))
    np.testing.assert_allclose([low[0], high[0]], [-4.8, 4.8], rtol=1e-6)
    assert np.all(np.abs(low[[1, 3]]) < 10) and np.all(np.abs(high[[1, 3]]) < 10)
    config = HedgerConfig.for_env(env, capacity=600, bandwidth=0.2, gamma=0.99)
    run = RunConfig(n_blocks=1, episodes_per_block=4, eval_episodes=4, eval_max_steps=500)
    train = make_train(env, config, run).train
    state, res = jax.jit(jax.vmap(train))(jax.random.split(jax.random.PRNGKey(0), 2))
    assert np.all(np.asarray(state.memory.size) > 0) and np.all(np.asarray(res.flags) == 0)
