"""Simulated corridor following (Smart & Kaelbling 2000, section 3.2), functional JAX env.

The paper steered a real robot down a corridor towards a dead end; this module simulates that
robot faithfully enough that the same learning problem arises.

Geometry (corridor frame, metres)
---------------------------------
* Straight corridor along +x, side walls at ``y = +width/2`` (left) and ``y = -width/2``
  (right), extending indefinitely towards -x (the corridor is open behind the start), and a dead
  end: the *end wall* at ``x = length``. The robot is a disc of radius ``robot_radius``;
  its pose is ``(x, y, theta)`` with ``theta`` the heading measured counter-clockwise from +x
  (``theta = 0``: facing the dead end; ``y > 0``: left of the centreline).
* The goal is reached when the robot's centre is within ``goal_distance`` of the end wall
  (``length - x <= goal_distance``).

Dynamics (one step = ``dt`` = 0.3 s)
------------------------------------
Unicycle kinematics with the mechanical realities the paper names:

* Action: commanded rotation velocity ``u`` (rad/s, float32 (1,)), clipped to
  ``[-w_max, w_max]``. A **dead-band** (slop) removes ``deadband`` rad/s from its magnitude
  (``u_eff = sign(u) * max(|u| - deadband, 0)``).
* **Actuator lag / momentum**: the actual rotation rate ``omega`` follows ``u_eff`` through a
  first-order lag with time constant ``tau_omega``; the forward speed ``v`` follows its command
  through a first-order lag with time constant ``tau_v``. A single step of full command
  therefore changes the heading by at most ``(1 - exp(-dt/tau_omega)) * w_max * dt``
  (~0.05 rad with the defaults) and the lateral offset by under a centimetre: one random
  action has little visible effect, only sustained commands steer the robot.
* Forward speed is set by a **fixed policy** (not learned): cruise at ``v_cruise`` but slow down
  when asked to turn hard, ``v_cmd = v_cruise * (1 - turn_slowdown * min(|u_eff| / w_max, 1))``
  (on the commanded rotation; the speed itself then follows ``v_cmd`` through its lag)
  (the robot does not slow down near the end: the episode ends at the goal line, well before
  the end wall). The robot starts every episode at rest (``v = omega = 0``).
* Pose update: ``theta' = theta + omega' dt``, ``(x, y) += v' dt (cos, sin)(theta + omega' dt/2)``.

Termination, reward, truncation
-------------------------------
* Reaching the goal: ``terminated = True``, **reward 10**. All other steps give reward 0.
* **Touching a side wall** (the body disc touches ``|y| = width/2``): the robot is stopped at the
  point of contact (its body never goes beyond the wall; ``v = omega = 0``) and the episode
  ends with ``terminated = True`` and **reward 0**. Wall contact takes precedence over the goal
  if both happen in the same step.
* ``truncated = True`` when the step counter reaches ``max_steps`` (200) without termination;
  truncation is never a terminal for bootstrapping.

Observation (float32 (3,))
--------------------------
``(angle, offset, dist)``:

* ``angle`` (rad): the corridor's direction relative to the robot's heading (``= -theta``
  noise-free). Positive means the corridor axis lies to the robot's left, i.e. a positive
  (counter-clockwise) rotation aligns the robot with the corridor.
* ``offset`` (m): the robot's lateral position relative to the centreline (``= y``), positive
  to the left.
* ``dist`` (m): distance from the robot's centre to the end wall along the corridor
  (``= length - x``).

With ``params.observation == "laser"`` (default) the observation is derived **from a simulated
laser scan**, as on the real robot: ``n_beams`` beams over a ``fov`` fan centred on the heading
are ray-cast against the two side walls and the end wall, each range gets Gaussian noise
(std ``range_noise``, drawn from the step key), beams beyond ``max_range`` return nothing.
The scan (ordered right to left) is segmented into right wall / end wall / left wall runs (from
inside the convex corridor they always appear in that order) by an exhaustive, jittable search
over the two break points minimising the total least-squares line-fit residual (prefix sums, so
O(n_beams^2)); the two side walls are then fitted as parallel lines (the end wall, rotated by
90 degrees, also informs the direction), giving the corridor angle and the offset; the end-wall
points projected onto the corridor axis give ``dist`` (the farthest point when no end wall is
seen). The laser angle lies in (-pi/2, pi/2] (a line fit cannot tell which way the corridor
runs), so it is only meaningful while the robot faces the dead end (|theta| < pi/2), which
covers every state a sensible policy visits. Measured errors with 2 cm range noise: angle
within 0.015 rad, offset within 0.013 m, dist within 0.04 m (unbiased); noise-free, they agree
with the geometric state to 1e-6. ``geometric_obs(state, params)`` gives the noise-free
geometric state and
``observation="geometric"`` makes the env return it.

Starts
------
* Training (``reset``): re-sampled on every call, at rest, uniformly
  ``x in [0, train_x_max]`` (default 0..6 m), ``y in [-train_y_max, train_y_max]`` (0.45 m),
  ``theta in [-train_theta_max, train_theta_max]`` (0.45 rad).
* Evaluation (``evaluation_starts``): a fixed list of 10 pre-specified poses
  ``EVAL_STARTS`` at the start of the evaluated section (``x = 0``), tiled to ``n``; see below.
* Evaluation metric: steps to reach the end; a wall crash or a timeout counts ``max_steps``
  (``evaluate_controller``).

Calibration (``CorridorParams()`` defaults, measured on ``EVAL_STARTS`` with the laser observation)
------------------------------------------------------------------------------------------------
Corridor 11 m long (10 m from the start line to the goal line), 2.0 m wide, robot radius 0.25 m,
cruise speed 0.5 m/s (0.15 m per step), |u| <= 1 rad/s, tau_omega = 1.6 s, tau_v = 0.5 s,
dead-band 0.05 rad/s, turn slow-down 0.4 (60% of cruise speed at a full-rate turn command).
Laser: 61 beams over 180 degrees, 20 m max range, 2 cm range noise. Measured: hand-coded
controller about 107 steps (target 106), best-achievable controller 68.7 steps (target 70),
hard lower bound for any policy 68 steps (``straight_line_lower_bound``). See
``envs.corridor_controllers`` for the controllers and how the best one was found.
"""
from __future__ import annotations

from typing import NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.pytree import pytree_dataclass, static_field
from envs.spaces import ActionSpace

F32 = jnp.float32

# Fixed evaluation starts: (x [m], y [m], theta [rad]) in the corridor frame, robot at rest.
# Centred and parallel, offset to either side, angled either way, and combinations of offset
# and heading (including heading towards the near wall), all at the start line x = 0.
EVAL_STARTS = np.array([
    [0.0, 0.00, 0.00],
    [0.0, 0.40, 0.00],
    [0.0, -0.40, 0.00],
    [0.0, 0.00, 0.35],
    [0.0, 0.00, -0.35],
    [0.0, 0.30, 0.25],
    [0.0, -0.30, -0.25],
    [0.0, 0.50, -0.20],
    [0.0, -0.50, 0.20],
    [0.0, 0.20, -0.40],
], dtype=np.float32)

GOAL_REWARD = 10.0


@pytree_dataclass
class CorridorParams:
    """Every constant of the corridor simulation (leaves can be vmapped).

    Lengths in metres, angles in radians, times in seconds.
    """
    length: float = 11.0          # x of the end wall (start line at x = 0)
    width: float = 2.0            # distance between the side walls
    robot_radius: float = 0.25    # body disc radius
    goal_distance: float = 1.0    # goal when length - x <= goal_distance
    dt: float = 0.3               # control period
    v_cruise: float = 0.5         # forward cruise speed (m/s)
    turn_slowdown: float = 0.4    # fractional slow-down at full rotation rate
    w_max: float = 1.0            # rotation-rate bound (rad/s); action bound
    deadband: float = 0.05        # slop on the commanded rotation (rad/s)
    tau_omega: float = 1.6        # rotation actuator lag time constant
    tau_v: float = 0.5            # forward speed lag time constant
    # laser range-finder
    fov: float = float(np.pi)     # fan width (rad), centred on the heading
    max_range: float = 20.0       # beams beyond return nothing (m)
    range_noise: float = 0.02     # Gaussian range noise std (m)
    seg_penalty: float = 0.05     # cost (m^2) of declaring an end-wall segment (segmentation)
    # training start distribution
    train_x_max: float = 6.0
    train_y_max: float = 0.45
    train_theta_max: float = 0.45
    # static
    n_beams: int = static_field(default=61)
    observation: str = static_field(default="laser")   # "laser" | "geometric"


class CorridorState(NamedTuple):
    """Physical state of one robot (all float32 scalars except ``t``, int32 scalar).

    x, y (m), theta (rad, wrapped to [-pi, pi]), omega (rad/s, actual rotation rate),
    v (m/s, actual forward speed), t (steps taken in this episode).
    """
    x: jax.Array
    y: jax.Array
    theta: jax.Array
    omega: jax.Array
    v: jax.Array
    t: jax.Array


def _wrap(a):
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


def make_state(x, y, theta, omega=0.0, v=0.0, t=0) -> CorridorState:
    """Build a ``CorridorState`` from numbers (float32 / int32 scalars)."""
    return CorridorState(jnp.asarray(x, F32), jnp.asarray(y, F32), jnp.asarray(theta, F32),
                         jnp.asarray(omega, F32), jnp.asarray(v, F32), jnp.asarray(t, jnp.int32))


def geometric_obs(state: CorridorState, params: CorridorParams) -> jax.Array:
    """Noise-free observation (angle, offset, dist): float32 (3,) = (-theta, y, length - x)."""
    return jnp.stack([_wrap(-state.theta), state.y, params.length - state.x]).astype(F32)


def beam_angles(params: CorridorParams) -> jax.Array:
    """Beam angles relative to the heading, right to left: float32 (n_beams,) rad."""
    return jnp.linspace(-0.5, 0.5, params.n_beams, dtype=F32) * params.fov


def ray_cast(state: CorridorState, params: CorridorParams) -> jax.Array:
    """True ranges of every beam: float32 (n_beams,) m, ``max_range`` where nothing is hit."""
    alpha = state.theta + beam_angles(params)
    c, s = jnp.cos(alpha), jnp.sin(alpha)
    big = F32(1e6)
    eps = F32(1e-6)
    half = params.width / 2
    t_left = jnp.where(s > eps, (half - state.y) / jnp.where(s > eps, s, 1.0), big)
    t_right = jnp.where(s < -eps, (-half - state.y) / jnp.where(s < -eps, s, -1.0), big)
    t_end = jnp.where(c > eps, (params.length - state.x) / jnp.where(c > eps, c, 1.0), big)
    r = jnp.minimum(jnp.minimum(t_left, t_right), t_end)
    r = jnp.maximum(r, 0.0)
    return jnp.minimum(r, params.max_range).astype(F32)


def laser_scan(key: jax.Array, state: CorridorState, params: CorridorParams):
    """Noisy scan: (ranges float32 (n_beams,) m, valid bool (n_beams,)).

    Gaussian noise of std ``range_noise`` on every range; beams whose true range reaches
    ``max_range`` are invalid (no return).
    """
    r = ray_cast(state, params)
    valid = r < params.max_range
    noisy = r + params.range_noise * jax.random.normal(key, r.shape, F32)
    noisy = jnp.clip(noisy, 0.0, params.max_range)
    return noisy, valid


def _seg_residuals(px, py, w):
    """Total-least-squares line residual of every beam-index segment [a, b).

    px, py, w: float32 (N,). Returns (R, n) with R float32 (N+1, N+1) the smallest eigenvalue
    of the scatter matrix of the points in [a, b) (inf where a > b) and n their count.
    """
    def cums(v):
        return jnp.concatenate([jnp.zeros((1,), F32), jnp.cumsum(v)])
    # centre the coordinates to reduce float32 cancellation
    n_all = jnp.maximum(w.sum(), 1.0)
    cx = (w * px).sum() / n_all
    cy = (w * py).sum() / n_all
    x = (px - cx) * w
    y = (py - cy) * w
    P = [cums(v) for v in (w, x, y, x * (px - cx), x * (py - cy), y * (py - cy))]
    S = [p[None, :] - p[:, None] for p in P]   # S[a, b] = sum over [a, b)
    n, sx, sy, sxx, sxy, syy = S
    ns = jnp.maximum(n, 1.0)
    cxx = sxx - sx * sx / ns
    cxy = sxy - sx * sy / ns
    cyy = syy - sy * sy / ns
    lam = 0.5 * (cxx + cyy) - jnp.sqrt(0.25 * (cxx - cyy) ** 2 + cxy ** 2)
    lam = jnp.maximum(lam, 0.0)
    idx = jnp.arange(px.shape[0] + 1)
    lam = jnp.where(idx[:, None] <= idx[None, :], lam, jnp.inf)
    return lam, n


def _masked_scatter(px, py, m):
    n = m.sum()
    ns = jnp.maximum(n, 1.0)
    mx = (m * px).sum() / ns
    my = (m * py).sum() / ns
    dx, dy = (px - mx) * m, (py - my) * m
    return n, mx, my, (dx * dx).sum(), (dx * dy).sum(), (dy * dy).sum()


def scan_to_obs(ranges: jax.Array, valid: jax.Array, params: CorridorParams) -> jax.Array:
    """Derive (angle, offset, dist) float32 (3,) from a laser scan, as the real robot did.

    ranges float32 (n_beams,) m, valid bool (n_beams,). Segments the scan into right wall /
    end wall / left wall (contiguous runs in that order, break points by exhaustive search
    minimising the sum of line-fit residuals + ``seg_penalty`` if an end wall is declared),
    fits the side walls as two parallel lines (least squares, pooled scatter; the end wall's
    scatter rotated by 90 degrees is pooled in too), and reads off the corridor angle, the
    offset from the centreline (mid-way between the two fitted lines; with one wall only, from
    the known width) and the distance to the end wall (mean projection of the end-wall points
    on the corridor axis; farthest projection of any point when no end wall is seen).
    """
    N = params.n_beams
    phi = beam_angles(params)
    w = valid.astype(F32)
    px = ranges * jnp.cos(phi)
    py = ranges * jnp.sin(phi)
    R, cnt = _seg_residuals(px, py, w)
    # cost[b1, b2] = right [0, b1) + end [b1, b2) + left [b2, N)
    cost = R[0][:, None] + R + R[:, N][None, :] + params.seg_penalty * (cnt > 0.5)
    flat = jnp.argmin(cost.reshape(-1))
    b1, b2 = flat // (N + 1), flat % (N + 1)
    idx = jnp.arange(N)
    m_right = w * (idx < b1)
    m_end = w * ((idx >= b1) & (idx < b2))
    m_left = w * (idx >= b2)
    nR, mxR, myR, rxx, rxy, ryy = _masked_scatter(px, py, m_right)
    nL, mxL, myL, lxx, lxy, lyy = _masked_scatter(px, py, m_left)
    nE, mxE, myE, exx, exy, eyy = _masked_scatter(px, py, m_end)
    # pooled scatter of the parallel side walls, plus the end wall rotated by 90 degrees
    cxx = rxx + lxx + eyy
    cyy = ryy + lyy + exx
    cxy = rxy + lxy - exy
    psi = 0.5 * jnp.arctan2(2 * cxy, cxx - cyy)       # corridor axis angle in robot frame
    dx, dy = jnp.cos(psi), jnp.sin(psi)
    nx, ny = -dy, dx
    sL = nx * mxL + ny * myL       # = width/2 - offset
    sR = nx * mxR + ny * myR       # = -(width/2 + offset)
    half = params.width / 2
    hasL, hasR = nL >= 2, nR >= 2
    off_both = -(sL + sR) / 2
    offset = jnp.where(hasL & hasR, off_both,
                       jnp.where(hasL, half - sL, jnp.where(hasR, -half - sR, 0.0)))
    proj = px * dx + py * dy
    far = jnp.max(jnp.where(valid, proj, -jnp.inf))
    far = jnp.where(jnp.any(valid), far, params.max_range)
    dist_end = jnp.where(nE >= 1, (m_end * proj).sum() / jnp.maximum(nE, 1.0), far)
    obs = jnp.stack([psi, jnp.clip(offset, -params.width, params.width),
                     jnp.clip(dist_end, 0.0, params.max_range)])
    return obs.astype(F32)


def laser_obs(key: jax.Array, state: CorridorState, params: CorridorParams) -> jax.Array:
    """Observation derived from a noisy laser scan: float32 (3,)."""
    ranges, valid = laser_scan(key, state, params)
    return scan_to_obs(ranges, valid, params)


def observe(key: jax.Array, state: CorridorState, params: CorridorParams) -> jax.Array:
    """The env's observation per ``params.observation`` ("laser" or "geometric")."""
    if params.observation == "geometric":
        return geometric_obs(state, params)
    if params.observation == "laser":
        return laser_obs(key, state, params)
    raise ValueError(f"observation must be 'laser' or 'geometric', got {params.observation!r}")


def dynamics(state: CorridorState, action: jax.Array, params: CorridorParams):
    """One deterministic physics step (branch-free).

    Returns (next_state, reached_goal bool (), hit_wall bool ()). ``next_state.t`` is
    incremented. On wall contact the robot is stopped where its body touches the wall.
    """
    u = jnp.clip(jnp.reshape(action, (-1,))[0].astype(F32), -params.w_max, params.w_max)
    u = jnp.sign(u) * jnp.maximum(jnp.abs(u) - params.deadband, 0.0)
    bw = 1.0 - jnp.exp(-params.dt / params.tau_omega)
    bv = 1.0 - jnp.exp(-params.dt / params.tau_v)
    omega = state.omega + bw * (u - state.omega)
    v_cmd = params.v_cruise * (1.0 - params.turn_slowdown
                               * jnp.minimum(jnp.abs(u) / params.w_max, 1.0))
    v = state.v + bv * (v_cmd - state.v)
    th_mid = state.theta + 0.5 * omega * params.dt
    x1 = state.x + v * jnp.cos(th_mid) * params.dt
    y1 = state.y + v * jnp.sin(th_mid) * params.dt
    theta1 = _wrap(state.theta + omega * params.dt)
    ylim = params.width / 2 - params.robot_radius
    hit = jnp.abs(y1) >= ylim
    # fraction of the move until contact (the start is strictly inside)
    target = jnp.sign(y1) * ylim
    dy = y1 - state.y
    frac = jnp.clip((target - state.y) / jnp.where(jnp.abs(dy) > 1e-9, dy, 1e-9), 0.0, 1.0)
    frac = jnp.where(hit, frac, 1.0)
    x1 = state.x + frac * (x1 - state.x)
    y1 = jnp.where(hit, jnp.clip(state.y + frac * dy, -ylim, ylim), y1)
    omega = jnp.where(hit, 0.0, omega)
    v = jnp.where(hit, 0.0, v)
    reached = (params.length - x1 <= params.goal_distance) & ~hit
    nxt = CorridorState(x1.astype(F32), y1.astype(F32), theta1.astype(F32), omega.astype(F32),
                        v.astype(F32), state.t + 1)
    return nxt, reached, hit


class Corridor:
    """Functional corridor-following environment (see module docstring).

    Attributes: ``name = "corridor"``, ``obs_dim = 3``, ``action_dim = 1``,
    ``action_space = ActionSpace.box(-w_max, w_max)`` (static; built from the default
    ``w_max``), ``max_steps = 200``.
    """

    name = "corridor"
    obs_dim = 3
    action_dim = 1

    def __init__(self, max_steps: int = 200, observation: str = "laser", **param_overrides):
        self.max_steps = int(max_steps)
        self._default = CorridorParams(observation=observation, **param_overrides)
        self.action_space = ActionSpace.box(-float(self._default.w_max),
                                            float(self._default.w_max))

    def default_params(self) -> CorridorParams:
        return self._default

    # --- starts -------------------------------------------------------------------------
    def sample_start(self, key: jax.Array, params: CorridorParams) -> CorridorState:
        """A random training start (at rest), see module docstring for the ranges."""
        kx, ky, kt = jax.random.split(key, 3)
        x = jax.random.uniform(kx, (), F32, 0.0, params.train_x_max)
        y = jax.random.uniform(ky, (), F32, -params.train_y_max, params.train_y_max)
        th = jax.random.uniform(kt, (), F32, -params.train_theta_max, params.train_theta_max)
        return make_state(x, y, th)

    def reset(self, key: jax.Array, params: CorridorParams):
        """Fresh training start: (obs float32 (3,), state)."""
        ks, ko = jax.random.split(key)
        state = self.sample_start(ks, params)
        return observe(ko, state, params), state

    def reset_to(self, key: jax.Array, params: CorridorParams, start):
        """Start from a given pose ``start`` = float32 (3,) (x, y, theta) at rest, or a
        ``CorridorState``. Returns (obs, state)."""
        if isinstance(start, CorridorState):
            state = start
        else:
            start = jnp.asarray(start, F32)
            state = make_state(start[0], start[1], start[2])
        return observe(key, state, params), state

    def evaluation_starts(self, key: jax.Array, params: CorridorParams, n: int):
        """The fixed evaluation starts ``EVAL_STARTS`` (10 poses) tiled to ``n``.

        Returns (obs float32 (n, 3), state batched with leading axis n); ``key`` only seeds
        the laser noise of the first observation.
        """
        starts = jnp.asarray(np.resize(EVAL_STARTS, (n, 3)))
        keys = jax.random.split(key, n)
        return jax.vmap(lambda k, s: self.reset_to(k, params, s))(keys, starts)

    # --- step ---------------------------------------------------------------------------
    def step(self, key: jax.Array, state: CorridorState, action: jax.Array,
             params: CorridorParams):
        """(obs (3,), state, reward (), terminated (), truncated (), info dict).

        ``key`` seeds the laser noise of the new observation. info: ``reached_goal``,
        ``hit_wall`` (bool ()).
        """
        nxt, reached, hit = dynamics(state, action, params)
        obs = observe(key, nxt, params)
        reward = jnp.where(reached, F32(GOAL_REWARD), F32(0.0))
        terminated = reached | hit
        truncated = (nxt.t >= self.max_steps) & ~terminated
        info = {"reached_goal": reached, "hit_wall": hit}
        return obs, nxt, reward, terminated, truncated, info

    def obs_bounds(self, params: CorridorParams):
        """Scaling ranges: angle [-pi/4, pi/4] rad, offset [-width/2, width/2] m,
        dist [0, length] m. float32 (3,) each."""
        low = jnp.stack([F32(-np.pi / 4), -params.width / 2, F32(0.0)]).astype(F32)
        high = jnp.stack([F32(np.pi / 4), params.width / 2, params.length + 0.0]).astype(F32)
        return low, high

    def obs_space_bounds(self, params: CorridorParams):
        """Hard bounds that contain every observation the env can emit: float32 (3,) each.

        Laser: the corridor-axis angle is half an ``arctan2`` (within [-pi/2, pi/2]), the
        offset is clipped to [-width, width] and the distance to [0, max_range]. Geometric:
        the wrapped heading within [-pi, pi], the offset within the walls, and the distance
        to the end unbounded (the robot may drive backwards past the start line).
        """
        if params.observation == "geometric":
            half = params.width / 2
            low = np.array([-np.pi, -half, -np.inf], np.float32)
            high = np.array([np.pi, half, np.inf], np.float32)
        else:
            low = np.array([-np.pi / 2, -params.width, 0.0], np.float32)
            high = np.array([np.pi / 2, params.width, params.max_range], np.float32)
        return low, high

    # --- rendering ----------------------------------------------------------------------
    def render_rgb(self, state: CorridorState, params: CorridorParams,
                   scale: float = 40.0, beams: bool = True) -> np.ndarray:
        """Top-down picture of ``state``: numpy uint8 (H, W, 3), corridor along the image x.

        Walls black, goal line green, robot blue disc with a red heading tick, noise-free
        laser endpoints orange (``beams=True``).
        """
        L = float(params.length)
        Wd = float(params.width)
        x0, x1 = -1.0, L + 0.5
        y0, y1 = -Wd / 2 - 0.4, Wd / 2 + 0.4
        Wp = int(round((x1 - x0) * scale))
        Hp = int(round((y1 - y0) * scale))
        img = np.full((Hp, Wp, 3), 235, np.uint8)

        def to_px(x, y):
            return (np.asarray((x - x0) * scale), np.asarray((y1 - y) * scale))

        X, Y = np.meshgrid(np.arange(Wp) + 0.5, np.arange(Hp) + 0.5)
        wx = X / scale + x0
        wy = y1 - Y / scale
        inside = (np.abs(wy) <= Wd / 2) & (wx <= L)
        img[inside] = (255, 255, 255)
        t = 2.5 / scale
        walls = ((np.abs(np.abs(wy) - Wd / 2) <= t) & (wx <= L + t)) | \
                ((np.abs(wx - L) <= t) & (np.abs(wy) <= Wd / 2 + t))
        img[walls] = (0, 0, 0)
        goal = (np.abs(wx - (L - float(params.goal_distance))) <= 1.0 / scale) & \
            (np.abs(wy) < Wd / 2)
        img[goal] = (0, 170, 0)
        sx, sy, th = float(state.x), float(state.y), float(state.theta)
        if beams:
            r = np.asarray(ray_cast(jax.tree_util.tree_map(jnp.asarray, state), params))
            phi = np.asarray(beam_angles(params))
            ok = r < float(params.max_range)
            ex = sx + r * np.cos(th + phi)
            ey = sy + r * np.sin(th + phi)
            for bx, by in zip(ex[ok], ey[ok]):
                m = (wx - bx) ** 2 + (wy - by) ** 2 <= (2.0 / scale) ** 2
                img[m] = (255, 140, 0)
        body = (wx - sx) ** 2 + (wy - sy) ** 2 <= float(params.robot_radius) ** 2
        img[body] = (40, 80, 220)
        s = np.linspace(0.0, float(params.robot_radius) * 1.3, 40)
        hx, hy = to_px(sx + s * np.cos(th), sy + s * np.sin(th))
        hx = np.clip(hx.astype(int), 0, Wp - 1)
        hy = np.clip(hy.astype(int), 0, Hp - 1)
        for dd in (-1, 0, 1):
            img[np.clip(hy + dd, 0, Hp - 1), hx] = (220, 30, 30)
        return img


# ------------------------------------------------------------------------------------------
# evaluation
# ------------------------------------------------------------------------------------------

def rollout_steps(env: Corridor, controller, params: CorridorParams, key: jax.Array,
                  starts: jax.Array) -> Tuple[jax.Array, jax.Array, jax.Array]:
    """Run ``controller`` (``init(key)``, ``act(key, obs, pstate)``) from each start pose.

    starts float32 (B, 3). Returns (steps int32 (B,) -- steps to reach the end, ``max_steps``
    for a crash or timeout --, reached bool (B,), crashed bool (B,)). Jittable when
    ``controller`` is built from jax functions.
    """
    B = starts.shape[0]
    k0, k1, k2 = jax.random.split(key, 3)
    obs, state = jax.vmap(lambda k, s: env.reset_to(k, params, s))(jax.random.split(k0, B),
                                                                   starts)
    pstate = jax.vmap(controller.init)(jax.random.split(k1, B))

    def one(carry, k):
        obs, state, pstate, done, steps, reached, crashed = carry
        ka, ks = jax.random.split(k)
        a, pstate2 = jax.vmap(controller.act)(jax.random.split(ka, B), obs, pstate)
        obs2, state2, r, term, trunc, info = jax.vmap(
            lambda kk, s, aa: env.step(kk, s, aa, params))(jax.random.split(ks, B), state, a)
        newly = ~done
        reached = reached | (newly & info["reached_goal"])
        crashed = crashed | (newly & info["hit_wall"])
        steps = jnp.where(newly & info["reached_goal"], state2.t, steps)
        done = done | term | trunc
        keep = lambda new, old: jax.tree_util.tree_map(
            lambda n_, o_: jnp.where(jnp.reshape(newly, (-1,) + (1,) * (n_.ndim - 1)), n_, o_),
            new, old)
        return (keep(obs2, obs), keep(state2, state), keep(pstate2, pstate), done, steps,
                reached, crashed), None

    init = (obs, state, pstate, jnp.zeros(B, bool), jnp.full(B, env.max_steps, jnp.int32),
            jnp.zeros(B, bool), jnp.zeros(B, bool))
    carry, _ = jax.lax.scan(one, init, jax.random.split(k2, env.max_steps))
    return carry[4], carry[5], carry[6]


def evaluate_controller(controller, params: CorridorParams | None = None,
                        key: jax.Array | None = None, n_repeats: int = 1,
                        env: Corridor | None = None, return_all: bool = False):
    """Mean steps to reach the end over ``EVAL_STARTS`` x ``n_repeats`` (crash/timeout =
    ``max_steps``), vmapped. Returns a Python float (or the per-episode int array (n,) too
    when ``return_all``)."""
    env = env or Corridor()
    params = params if params is not None else env.default_params()
    key = jax.random.PRNGKey(0) if key is None else key
    starts = jnp.asarray(np.tile(EVAL_STARTS, (n_repeats, 1)))
    steps, _, _ = jax.jit(lambda k: rollout_steps(env, controller, params, k, starts))(key)
    mean = float(jnp.mean(steps.astype(F32)))
    return (mean, np.asarray(steps)) if return_all else mean


def straight_line_lower_bound(params: CorridorParams | None = None,
                              env: Corridor | None = None) -> np.ndarray:
    """Lower bound on the steps from each ``EVAL_STARTS`` pose: float (10,) steps.

    No policy can beat driving straight along the corridor from rest at the fixed-policy
    cruise speed (the speed never exceeds the no-turn profile, and the robot must cover at
    least ``length - goal_distance - x0`` along the corridor). Computed by simulating that
    speed profile.
    """
    env = env or Corridor()
    params = params if params is not None else env.default_params()
    out = []
    for x0, _, _ in EVAL_STARTS:
        s = make_state(x0, 0.0, 0.0)
        n = 0
        while n < env.max_steps:
            s, reached, _ = dynamics(s, jnp.zeros(1), params)
            n += 1
            if bool(reached):
                break
        out.append(n)
    return np.asarray(out)
