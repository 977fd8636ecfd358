"""Tests of the simulated corridor (envs.corridor) and its controllers (envs.corridor_controllers)."""
import jax
import jax.numpy as jnp
import numpy as np

from envs.corridor import (EVAL_STARTS, Corridor, evaluate_controller,
                           geometric_obs, laser_obs, make_state, straight_line_lower_bound)
from envs.corridor_controllers import (BEST_CONTROLLER_PARAMS, best_policy,
                                       find_best_controller, hand_coded_demonstrations,
                                       hand_coded_policy)
from envs.pytree import replace

ENV = Corridor()
P = ENV.default_params()
PG = replace(P, observation="geometric")

# representative geometries (x, y, theta): centred and parallel, angled, offset, near the end,
# and combinations
POSES = np.array([
    [0.0, 0.0, 0.0],
    [2.0, 0.0, 0.4],
    [2.0, 0.0, -0.6],
    [4.0, 0.6, 0.0],
    [4.0, -0.6, 0.0],
    [3.0, 0.4, -0.3],
    [9.5, 0.2, 0.1],
    [9.9, -0.3, 0.4],
    [9.0, 0.0, 0.0],
], np.float32)

# laser noise 2 cm std: bounds measured as ~3x the largest error seen over 200 draws
NOISE_TOL = np.array([0.03, 0.03, 0.08], np.float32)


def _states(poses):
    return jax.vmap(lambda p: make_state(p[0], p[1], p[2]))(jnp.asarray(poses))


def test_api_attributes():
    assert ENV.name == "corridor" and ENV.obs_dim == 3 and ENV.action_dim == 1
    assert ENV.max_steps == 200
    assert ENV.action_space.low == (-1.0,) and ENV.action_space.high == (1.0,)
    assert not ENV.action_space.is_discrete
    lo, hi = ENV.obs_bounds(P)
    assert lo.shape == hi.shape == (3,) and lo.dtype == jnp.float32
    assert np.all(np.asarray(hi) > np.asarray(lo))


def test_laser_matches_geometric():
    states = _states(POSES)
    geo = jax.vmap(lambda s: geometric_obs(s, P))(states)
    keys = jax.random.split(jax.random.PRNGKey(0), 100)
    las = jax.jit(jax.vmap(lambda k: jax.vmap(lambda s: laser_obs(k, s, P))(states)))(keys)
    err = np.abs(np.asarray(las - geo[None]))
    assert np.all(err.max(axis=(0, 1)) <= NOISE_TOL), err.max(axis=(0, 1))
    # unbiased to well within the noise
    assert np.all(np.abs(np.asarray(las - geo[None]).mean(0)) < NOISE_TOL / 5)
    # noise off: tight agreement
    p0 = replace(P, range_noise=0.0)
    las0 = jax.jit(jax.vmap(lambda s: laser_obs(keys[0], s, p0)))(states)
    np.testing.assert_allclose(np.asarray(las0), np.asarray(geo), atol=1e-4)


def test_obs_space_bounds_contain_every_observation():
    """Hard observation bounds (the Gymnasium observation_space) hold for poses anywhere:
    any heading, against either wall, behind the start and past the goal."""
    rng = np.random.default_rng(0)
    n = 2000
    ylim = float(P.width) / 2 - float(P.robot_radius)
    poses = np.stack([rng.uniform(-3.0, float(P.length) + 0.5, n),
                      rng.uniform(-ylim, ylim, n),
                      rng.uniform(-np.pi, np.pi, n)], axis=1).astype(np.float32)
    poses[:50, 1] = ylim          # touching the left wall
    poses[50:100, 1] = -ylim      # touching the right wall
    poses[100:150, 2] = np.pi     # facing backwards
    states = _states(poses)
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    las = np.asarray(jax.jit(jax.vmap(lambda k, s: laser_obs(k, s, P)))(keys, states))
    geo = np.asarray(jax.vmap(lambda s: geometric_obs(s, PG))(states))
    for obs, params in ((las, P), (geo, PG)):
        low, high = ENV.obs_space_bounds(params)
        assert low.dtype == high.dtype == np.float32 and low.shape == high.shape == (3,)
        assert np.all(np.isfinite(obs))
        assert np.all(obs >= low) and np.all(obs <= high), (obs.min(0), obs.max(0), low, high)
    # the laser bounds are finite (a bounded Box), and the nominal scaling range lies inside
    low, high = ENV.obs_space_bounds(P)
    assert np.all(np.isfinite(low)) and np.all(np.isfinite(high))
    s_low, s_high = map(np.asarray, ENV.obs_bounds(P))
    assert np.all(low <= s_low) and np.all(s_high <= high)
    # laser observations do leave the nominal range somewhere (why hard bounds are needed)
    assert np.any((las < s_low) | (las > s_high))


def test_wall_never_crossed_random_actions():
    n = 256
    half = float(P.width) / 2

    def episode(key):
        k0, k1 = jax.random.split(key)
        _, s = ENV.reset(k0, PG)
        # sticky random actions (re-drawn every 8 steps) so that walls do get hit
        acts = jax.random.uniform(k1, (25, 1), minval=-1.0, maxval=1.0)
        acts = jnp.repeat(acts, 8, axis=0)

        def body(c, a):
            s, done = c
            _, s2, r, term, trunc, info = ENV.step(jax.random.PRNGKey(0), s, a, PG)
            s2 = jax.tree_util.tree_map(lambda new, old: jnp.where(done, old, new), s2, s)
            out = (s2.y, term & ~done, info["hit_wall"] & ~done, r * (~done))
            return (s2, done | term | trunc), out

        _, (ys, term, hit, r) = jax.lax.scan(body, (s, jnp.zeros((), bool)), acts)
        return ys, term, hit, r

    ys, term, hit, r = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(1), n))
    ys, term, hit, r = map(np.asarray, (ys, term, hit, r))
    assert hit.sum() > 20, "random actions should crash into walls sometimes"
    # the body (disc) never goes beyond a wall
    assert np.all(np.abs(ys) + float(P.robot_radius) <= half + 1e-5)
    assert np.all(term[hit])          # contact terminates
    assert np.all(r[hit] == 0.0)      # ... with reward 0


def test_goal_reward_and_termination():
    x_goal = float(P.length - P.goal_distance)
    s = make_state(x_goal - 0.1, 0.0, 0.0, v=float(P.v_cruise))
    _, s1, r, term, trunc, info = ENV.step(jax.random.PRNGKey(0), s, jnp.zeros(1), P)
    assert bool(term) and not bool(trunc) and float(r) == 10.0 and bool(info["reached_goal"])
    # short of the goal: reward 0, not terminated
    s = make_state(x_goal - 1.0, 0.0, 0.0, v=float(P.v_cruise))
    _, _, r, term, trunc, _ = ENV.step(jax.random.PRNGKey(0), s, jnp.zeros(1), P)
    assert float(r) == 0.0 and not bool(term) and not bool(trunc)


def test_rewards_zero_until_goal_then_exactly_10():
    starts = jnp.asarray(EVAL_STARTS[:3])
    pol = best_policy()

    def ep(start):
        o, s = ENV.reset_to(jax.random.PRNGKey(0), PG, start)

        def body(c, _):
            o, s, done = c
            a, _ = pol.act(None, o, jnp.zeros(()))
            o2, s2, r, term, trunc, _ = ENV.step(jax.random.PRNGKey(0), s, a, PG)
            return (o2, s2, done | term), (r * ~done, term & ~done)
        _, (r, term) = jax.lax.scan(body, (o, s, jnp.zeros((), bool)), None, length=200)
        return r, term
    r, term = map(np.asarray, jax.jit(jax.vmap(ep))(starts))
    assert np.all(term.sum(1) == 1)
    assert np.all(r.sum(1) == 10.0) and np.all(r[term] == 10.0) and np.all(r[~term] == 0.0)


def test_truncation_separate_from_termination():
    # facing backwards down the open corridor: never terminates, truncated at max_steps
    o, s = ENV.reset_to(jax.random.PRNGKey(0), PG, jnp.array([5.0, 0.0, np.pi]))

    def body(s, _):
        _, s2, r, term, trunc, _ = ENV.step(jax.random.PRNGKey(0), s, jnp.zeros(1), PG)
        return s2, (term, trunc)
    _, (term, trunc) = jax.lax.scan(body, s, None, length=ENV.max_steps)
    term, trunc = np.asarray(term), np.asarray(trunc)
    assert not term.any()
    assert trunc[-1] and not trunc[:-1].any()


def test_resets_resample():
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    obs, st = jax.jit(jax.vmap(lambda k: ENV.reset(k, PG)))(keys)
    x, y, th = map(np.asarray, (st.x, st.y, st.theta))
    assert len(np.unique(x)) == 64 and len(np.unique(y)) == 64 and len(np.unique(th)) == 64
    assert x.min() >= 0 and x.max() <= float(P.train_x_max)
    assert np.abs(y).max() <= float(P.train_y_max) and np.abs(th).max() <= float(P.train_theta_max)
    assert np.all(np.asarray(st.v) == 0) and np.all(np.asarray(st.t) == 0)
    np.testing.assert_allclose(np.asarray(obs), np.stack([-th, y, float(P.length) - x], 1),
                               atol=1e-5)


def test_evaluation_starts_fixed_and_tiled():
    o1, s1 = ENV.evaluation_starts(jax.random.PRNGKey(0), PG, 25)
    o2, s2 = ENV.evaluation_starts(jax.random.PRNGKey(5), PG, 25)
    assert o1.shape == (25, 3)
    np.testing.assert_array_equal(np.asarray(s1.y), np.asarray(s2.y))
    np.testing.assert_array_equal(np.asarray(s1.y)[:10], EVAL_STARTS[:, 1])
    np.testing.assert_array_equal(np.asarray(s1.theta)[10:20], EVAL_STARTS[:, 2])


def test_jit_vmap_1000_instances_and_params():
    n = 1000
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    obs, st = jax.jit(jax.vmap(lambda k: ENV.reset(k, P)))(keys)
    acts = jax.random.uniform(jax.random.PRNGKey(1), (n, 1), minval=-1, maxval=1)
    step = jax.jit(jax.vmap(lambda k, s, a: ENV.step(k, s, a, P)))
    o2, s2, r, term, trunc, info = step(keys, st, acts)
    assert o2.shape == (n, 3) and o2.dtype == jnp.float32 and r.shape == (n,)
    assert term.dtype == jnp.bool_ and np.all(np.isfinite(np.asarray(o2)))
    # params are a vmappable pytree: a batch of corridor widths
    widths = jnp.linspace(1.6, 2.4, 8)
    pb = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[replace(PG, width=w) for w in widths])
    ob, _ = jax.vmap(lambda pp: ENV.reset_to(keys[0], pp, jnp.array([0.0, 0.5, 0.0])))(pb)
    assert ob.shape == (8, 3)


def test_single_random_action_has_little_effect():
    s = make_state(3.0, 0.1, 0.05, v=float(P.v_cruise))
    key = jax.random.PRNGKey(0)
    _, s0, *_ = ENV.step(key, s, jnp.zeros(1), PG)
    for a in (-1.0, -0.6, 0.4, 1.0):
        _, s1, *_ = ENV.step(key, s, jnp.array([a]), PG)
        assert abs(float(s1.theta - s0.theta)) <= 0.06
        assert abs(float(s1.y - s0.y)) <= 0.01
    # ... whereas holding the command steers the robot
    def body(s, _):
        _, s2, *_ = ENV.step(key, s, jnp.array([1.0]), PG)
        return s2, None
    s10, _ = jax.lax.scan(body, s, None, length=10)
    assert float(s10.theta - s.theta) > 0.5


def test_hand_coded_controller_about_106_steps():
    mean = evaluate_controller(hand_coded_policy(), P, jax.random.PRNGKey(0), n_repeats=2)
    assert 106 * 0.9 <= mean <= 106 * 1.1, mean


def test_best_controller_about_70_steps():
    mean, steps = evaluate_controller(best_policy(), P, jax.random.PRNGKey(0), n_repeats=2,
                                      return_all=True)
    assert 70 * 0.9 <= mean <= 70 * 1.1, mean
    lb = straight_line_lower_bound(P)
    assert np.all(steps >= np.tile(lb, 2))           # nothing beats the straight-line bound
    assert mean <= lb.mean() + 3


def test_search_improves_on_initial_guess():
    res = find_best_controller(jax.random.PRNGKey(0), PG, init_mean=(3.0, 3.0, 1.0),
                               n_iters=2, pop_size=16)
    assert res["steps"] < res["init_steps"]
    assert len(BEST_CONTROLLER_PARAMS) == 3


def test_hand_coded_demonstrations():
    d = hand_coded_demonstrations(seed=0, n_runs=25)
    T = d.valid.shape[1]
    assert T <= 200 and d.env_id == "corridor" and d.source == "hand_coded"
    assert d.obs.shape == (25, T, 3) and d.next_obs.shape == (25, T, 3)
    assert d.action.shape == (25, T, 1) and d.valid.shape == (25, T)
    v = d.valid
    lengths = v.sum(1)
    assert np.all(v[np.arange(25), 0]) and np.all(lengths > 0) and lengths.max() == T
    # valid steps form a prefix; exactly one terminal/truncation per episode, at the end
    assert np.all(v == (np.arange(T)[None] < lengths[:, None]))
    ends = d.terminated | d.truncated
    assert np.all(ends.sum(1) == 1) and np.all(ends[np.arange(25), lengths - 1])
    assert np.all(np.abs(d.action[v]) <= 1.0)
    assert np.all(d.reward[~v] == 0)
    np.testing.assert_array_equal(d.obs[:, 1:][v[:, 1:]], d.next_obs[:, :-1][v[:, 1:]])
    # The hand-coded controller reaches the end in every example run (the paper's 25 runs).
    assert np.all(d.terminated[np.arange(25), lengths - 1])


def test_render_rgb():
    img = ENV.render_rgb(make_state(5.0, 0.2, 0.3), P)
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
    assert img.shape[2] == 3 and img.shape[1] > img.shape[0] > 20
