"""Tests of the simulated corridor (envs.corridor) and its controllers (envs.corridor_controllers)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.corridor import (EVAL_STARTS, Corridor, evaluate_controller,
                           geometric_obs, laser_obs, make_state, rollout_steps,
                           straight_line_lower_bound)
from envs.corridor_controllers import (BEST_CONTROLLER_PARAMS, Policy, best_policy,
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


#: Laser observations per (key, state) pair, params traced: one program (for N_LASER pairs)
#: serves the laser tests below, noise on and off.
N_LASER = 1800
_laser_batch = jax.jit(jax.vmap(laser_obs, in_axes=(0, 0, None)))


def test_api_attributes():
    assert ENV.name == "corridor" and ENV.obs_dim == 3 and ENV.action_dim == 1
    assert ENV.max_steps == 200
    assert ENV.action_space.low == (-1.0,) and ENV.action_space.high == (1.0,)
    assert not ENV.action_space.is_discrete
    lo, hi = ENV.obs_bounds(P)
    assert lo.shape == hi.shape == (3,) and lo.dtype == jnp.float32
    assert np.all(np.asarray(hi) > np.asarray(lo))


def test_laser_matches_geometric():
    """200 noisy scans of each of the 9 POSES: within NOISE_TOL of the geometric state and
    unbiased; noise off, within 1e-4."""
    reps = N_LASER // len(POSES)
    states = _states(np.tile(POSES, (reps, 1)))                  # pose i at rows i + 9 j
    geo = np.asarray(jax.vmap(lambda s: geometric_obs(s, P))(_states(POSES)))
    keys = jax.random.split(jax.random.PRNGKey(0), N_LASER)
    las = np.asarray(_laser_batch(keys, states, P)).reshape(reps, len(POSES), 3)
    err = np.abs(las - geo[None])
    assert np.all(err.max(axis=(0, 1)) <= NOISE_TOL), err.max(axis=(0, 1))
    # unbiased to well within the noise
    assert np.all(np.abs((las - geo[None]).mean(0)) < NOISE_TOL / 5)
    # noise off: tight agreement
    las0 = np.asarray(_laser_batch(keys, states, replace(P, range_noise=0.0)))
    np.testing.assert_allclose(las0.reshape(reps, len(POSES), 3)[0], geo, atol=1e-4)
    np.testing.assert_allclose(las0.reshape(reps, len(POSES), 3), np.broadcast_to(
        geo, (reps, len(POSES), 3)), atol=1e-4)


def test_obs_space_bounds_contain_every_observation():
    """Hard observation bounds (the Gymnasium observation_space) hold for poses anywhere:
    any heading, against either wall, behind the start and past the goal."""
    rng = np.random.default_rng(0)
    n = N_LASER
    ylim = float(P.width) / 2 - float(P.robot_radius)
    poses = np.stack([rng.uniform(-3.0, float(P.length) + 0.5, n),
                      rng.uniform(-ylim, ylim, n),
                      rng.uniform(-np.pi, np.pi, n)], axis=1).astype(np.float32)
    poses[:50, 1] = ylim          # touching the left wall
    poses[50:100, 1] = -ylim      # touching the right wall
    poses[100:150, 2] = np.pi     # facing backwards
    states = _states(poses)
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    las = np.asarray(_laser_batch(keys, states, P))
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
    """(The reward and termination come from the dynamics, whatever the observation: the
    geometric one is stepped here, op by op, as it is much cheaper than the laser's.)"""
    x_goal = float(P.length - P.goal_distance)
    s = make_state(x_goal - 0.1, 0.0, 0.0, v=float(P.v_cruise))
    _, s1, r, term, trunc, info = ENV.step(jax.random.PRNGKey(0), s, jnp.zeros(1), PG)
    assert bool(term) and not bool(trunc) and float(r) == 10.0 and bool(info["reached_goal"])
    # short of the goal: reward 0, not terminated
    s = make_state(x_goal - 1.0, 0.0, 0.0, v=float(P.v_cruise))
    _, _, r, term, trunc, _ = ENV.step(jax.random.PRNGKey(0), s, jnp.zeros(1), PG)
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


def _np_dynamics(x, y, th, omega, v, u, p):
    """The module docstring's physics step in float64 NumPy (arrays of robots): dead-band,
    first-order lags, fixed speed policy, mid-point pose update, stop at a side wall.
    -> (x, y, theta, omega, v, reached_goal, hit_wall)."""
    f = lambda name: float(getattr(p, name))  # noqa: E731
    u = np.clip(u, -f("w_max"), f("w_max"))
    u = np.sign(u) * np.maximum(np.abs(u) - f("deadband"), 0.0)
    dt = f("dt")
    omega = omega + (1 - np.exp(-dt / f("tau_omega"))) * (u - omega)
    v_cmd = f("v_cruise") * (1 - f("turn_slowdown") * np.minimum(np.abs(u) / f("w_max"), 1))
    v = v + (1 - np.exp(-dt / f("tau_v"))) * (v_cmd - v)
    mid = th + 0.5 * omega * dt
    x1, y1 = x + v * np.cos(mid) * dt, y + v * np.sin(mid) * dt
    th1 = (th + omega * dt + np.pi) % (2 * np.pi) - np.pi
    ylim = f("width") / 2 - f("robot_radius")
    hit = np.abs(y1) >= ylim
    frac = np.where(hit, (np.sign(y1) * ylim - y) / np.where(hit, y1 - y, 1.0), 1.0)
    x1, y1 = x + frac * (x1 - x), np.where(hit, np.sign(y1) * ylim, y1)
    omega, v = np.where(hit, 0.0, omega), np.where(hit, 0.0, v)
    reached = (f("length") - x1 <= f("goal_distance")) & ~hit
    return x1, y1, th1, omega, v, reached, hit


def _assert_step_matches_numpy(states, actions, out, p, where):
    """One vmapped ``ENV.step`` (geometric observation) against ``_np_dynamics``."""
    o2, s2, r, term, trunc, info = (jax.tree_util.tree_map(np.asarray, x) for x in out)
    st = [np.asarray(getattr(states, k), np.float64) for k in ("x", "y", "theta", "omega", "v")]
    x, y, th, om, v, reached, hit = _np_dynamics(*st, np.asarray(actions, np.float64)[:, 0], p)
    for name, got, want in (("x", s2.x, x), ("y", s2.y, y), ("theta", s2.theta, th),
                            ("omega", s2.omega, om), ("v", s2.v, v)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5, err_msg=f"{where}: {name}")
    np.testing.assert_array_equal(info["hit_wall"], hit, err_msg=where)
    np.testing.assert_array_equal(info["reached_goal"], reached, err_msg=where)
    np.testing.assert_array_equal(term, reached | hit, err_msg=where)
    np.testing.assert_array_equal(r, np.where(reached, 10.0, 0.0), err_msg=where)
    assert not trunc.any() and np.all(s2.t == np.asarray(states.t) + 1), where
    np.testing.assert_allclose(o2, np.stack([-s2.theta, s2.y, float(p.length) - s2.x], 1),
                               atol=1e-6, err_msg=where)


def test_jit_vmap_1000_instances_and_params():
    """1000 robots from random resets, moving at cruise speed and turning, stepped by one
    jitted, vmapped step with random commands: the state, reward and flags are a float64
    NumPy computation of the documented physics. The params are a vmappable pytree: one step
    of a robot near the left wall in corridors of 8 widths hits the wall only in the narrow
    ones, as the same computation says."""
    n = 1000
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    _, st = jax.jit(jax.vmap(lambda k: ENV.reset(k, PG)))(keys)
    st = st._replace(omega=jax.random.uniform(keys[0], (n,), minval=-0.8, maxval=0.8),
                     v=jnp.full((n,), float(P.v_cruise), jnp.float32))
    acts = jax.random.uniform(jax.random.PRNGKey(1), (n, 1), minval=-1.2, maxval=1.2)
    step = jax.jit(jax.vmap(lambda k, s, a: ENV.step(k, s, a, PG)))
    out = step(keys, st, acts)
    assert out[0].shape == (n, 3) and out[0].dtype == jnp.float32 and out[2].shape == (n,)
    _assert_step_matches_numpy(st, acts, out, PG, "random resets")
    # params are a vmappable pytree: a batch of corridor widths, a robot heading left at
    # y = 0.5 (the wall's contact line is at width / 2 - 0.25 = 0.55 ... 0.95).
    widths = jnp.linspace(1.6, 2.4, 8)
    pb = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[replace(PG, width=w) for w in widths])
    s0 = make_state(3.0, 0.5, 0.6, v=float(P.v_cruise))
    out = jax.jit(jax.vmap(lambda pp: ENV.step(keys[0], s0, jnp.array([1.0]), pp)))(pb)
    hit = np.asarray(out[5]["hit_wall"])
    assert hit[0] and not hit[-1]
    for i, w in enumerate(np.asarray(widths)):
        one = jax.tree_util.tree_map(lambda a: a[i:i + 1], out)
        _assert_step_matches_numpy(jax.tree_util.tree_map(lambda a: a[None], s0),
                                   np.ones((1, 1)), one, replace(PG, width=float(w)),
                                   f"width {w:.3f}")


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


def _either_policy(which):
    """The hand-coded controller (which = 0) or the best one (1), which traced: one laser
    rollout program evaluates both."""
    hand, best = hand_coded_policy(), best_policy()

    def act(key, obs, pstate):
        return jax.lax.switch(which, (hand.act, best.act), key, obs, pstate)

    return Policy(hand.init, act)


@jax.jit
def _eval_steps(which):
    """``evaluate_controller(policy, P, PRNGKey(0), n_repeats=2, return_all=True)``'s steps,
    for the policy ``_either_policy(which)``."""
    starts = jnp.asarray(np.tile(EVAL_STARTS, (2, 1)))
    return rollout_steps(ENV, _either_policy(which), P, jax.random.PRNGKey(0), starts)[0]


def test_controllers_calibration_hand_coded_106_best_70_steps():
    """The laser corridor's calibration (module docstring): the hand-coded controller takes
    about 106 steps and the best one about 70 on EVAL_STARTS (x2), and nothing beats the
    straight-line bound. ``evaluate_controller`` (used for the reference lines) is the mean
    of these steps."""
    hand = np.asarray(_eval_steps(jnp.int32(0)))
    assert 106 * 0.9 <= hand.mean() <= 106 * 1.1, hand.mean()
    steps = np.asarray(_eval_steps(jnp.int32(1)))
    mean = steps.astype(np.float32).mean()
    assert 70 * 0.9 <= mean <= 70 * 1.1, mean
    lb = straight_line_lower_bound(P)
    assert np.all(steps >= np.tile(lb, 2))           # nothing beats the straight-line bound
    assert np.all(hand >= np.tile(lb, 2))
    assert mean <= lb.mean() + 3


def test_evaluate_controller_is_the_mean_of_the_rollout_steps():
    """On the geometric observation (cheap to compile): ``evaluate_controller``'s steps are
    ``rollout_steps``' from the tiled EVAL_STARTS, its mean their mean."""
    pol = best_policy()
    mean, steps = evaluate_controller(pol, PG, jax.random.PRNGKey(0), n_repeats=2,
                                      return_all=True)
    want = rollout_steps(ENV, pol, PG, jax.random.PRNGKey(0),
                         jnp.asarray(np.tile(EVAL_STARTS, (2, 1))))[0]
    np.testing.assert_array_equal(steps, np.asarray(want))
    assert mean == pytest.approx(float(np.mean(np.asarray(want, np.float32))), rel=1e-6)
    assert np.all(steps < ENV.max_steps)             # the best controller reaches the end


def test_search_improves_on_initial_guess():
    res = find_best_controller(jax.random.PRNGKey(0), PG, init_mean=(3.0, 3.0, 1.0),
                               n_iters=2, pop_size=16)
    assert res["steps"] < res["init_steps"]
    assert len(BEST_CONTROLLER_PARAMS) == 3


# The laser demonstrations (fig. 5's phase one) in the full suite: their laser pipeline
# compiles ~4x slower; the calibration test above runs the hand-coded controller on the laser.
@pytest.mark.parametrize("observation", ["geometric", pytest.param("laser",
                                                                  marks=pytest.mark.full)])
def test_hand_coded_demonstrations(observation):
    """25 example runs of the hand-coded controller from training starts: a valid
    ``Demonstrations`` (prefix masks, one end per run, the obs chain) in which every run
    reaches the end (the paper's 25 runs)."""
    d = hand_coded_demonstrations(seed=0, n_runs=25, params=replace(P, observation=observation))
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


def _body_centre_px(img):
    """(column, row) centroid of the robot's body colour (40, 80, 220)."""
    rows, cols = np.nonzero(np.all(img == (40, 80, 220), axis=-1))
    assert len(rows) > 50
    return np.array([cols.mean(), rows.mean()])


def test_render_rgb():
    """A top-down picture (corridor along the image's x, 40 px per metre by default): moving
    the robot 3 m along the corridor and 0.5 m to the right moves its body by 120 px right
    and 20 px down (image rows grow downwards)."""
    img = ENV.render_rgb(make_state(5.0, 0.2, 0.3), P)
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
    assert img.shape[2] == 3 and img.shape[1] > img.shape[0] > 20
    moved = ENV.render_rgb(make_state(2.0, -0.3, 0.3), P)
    assert moved.shape == img.shape
    shift = _body_centre_px(moved) - _body_centre_px(img)
    np.testing.assert_allclose(shift, [-120.0, 20.0], atol=1.5)
