"""Mountain car (Singh & Sutton 1996; Smart & Kaelbling 2000, section 3.1) as a functional env.

Dynamics are those of Gymnasium's ``MountainCar-v0`` (classic Sutton & Barto)::

    v <- clip(v + force * a - gravity * cos(3 x), -max_speed, max_speed)
    x <- clip(x + v, min_position, max_position)
    v <- 0            if x hit the left wall (x == min_position) while v < 0
    terminated = x >= goal_position and v >= goal_velocity

with ``a`` the action *value*: one of {-1, 0, +1} (discrete variant) or any value in
[-1, 1] (continuous variant; both use ``force * a`` with force = 0.001, so the continuous
variant equals the discrete one at a in {-1, 0, +1}; this is *not* Gymnasium's
MountainCarContinuous, which uses a different power and reward).

Differences from Gymnasium, all deliberate:
  * the position is clipped at ``max_position = 0.5`` (Gymnasium clips at 0.6). The goal is at
    0.5, so this only changes the reported position of the terminal state (it never changes a
    trajectory or ``terminated``) and keeps every observation inside ``obs_bounds``.
  * reward (the paper's): 0 on every step except the one that reaches the goal, where it is
    ``1 - |v| / max_speed`` with ``v`` the velocity after the step (1 at zero speed, 0 at max).
  * starts: uniform ``x in [-1.2, 0.5)``, ``v in [-0.07, 0.07]``, re-sampled on every reset.
  * time limit ``max_steps`` (200 by default): ``truncated = time >= max_steps and not
    terminated``.

``step`` is branch-free (``jnp.where``/``clip``) and therefore jittable and vmappable over
states, actions and params. The continuous variant clips ``a`` to [-1, 1] inside ``step``;
rejecting out-of-range actions at the host level (e.g. Gymnasium's action-space check) is the
job of the adapters (``envs.gym_adapter``), not of this module. The discrete variant does not
snap a value to {-1, 0, 1}: it applies ``force * clip(a, -1, 1)`` as well.
"""
from __future__ import annotations

from typing import Any, Dict, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.pytree import pytree_dataclass
from envs.spaces import ActionSpace

__all__ = ["MountainCar", "MountainCarParams", "MountainCarState", "bottom_start",
           "BOTTOM_POSITION", "BOTTOM_VELOCITY"]

#: The bottom of the hill, where the paper's demonstrations start (x = -0.5, v = 0).
BOTTOM_POSITION = -0.5
BOTTOM_VELOCITY = 0.0


def bottom_start() -> jax.Array:
    """The start at the bottom of the hill: float32 array ``[x, v] = [-0.5, 0.0]``, shape (2,).

    Pure and trivially vmappable (broadcast it, or vmap a function that calls it)."""
    return jnp.array([BOTTOM_POSITION, BOTTOM_VELOCITY], dtype=jnp.float32)


@pytree_dataclass
class MountainCarParams:
    """Every constant of the task (all leaves: vmappable). Scalars, float32."""
    min_position: Any = -1.2
    max_position: Any = 0.5
    max_speed: Any = 0.07
    goal_position: Any = 0.5
    goal_velocity: Any = 0.0
    force: Any = 0.001
    gravity: Any = 0.0025
    # Range of the uniform training / evaluation starts (high end of x exclusive).
    start_position_low: Any = -1.2
    start_position_high: Any = 0.5
    start_velocity_low: Any = -0.07
    start_velocity_high: Any = 0.07


@pytree_dataclass
class MountainCarState:
    """position, velocity: float32 (); time: int32 () steps taken since the reset."""
    position: jax.Array
    velocity: jax.Array
    time: jax.Array


def _f32(x) -> jax.Array:
    return jnp.asarray(x, dtype=jnp.float32)


class MountainCar:
    """Mountain car, discrete ({-1, 0, +1}) or continuous ([-1, 1]) actions.

    Args:
      continuous: continuous action box instead of the discrete set.
      max_steps: episode time limit (static), 200 in the paper's protocol.
    """

    obs_dim = 2
    action_dim = 1

    def __init__(self, continuous: bool = False, max_steps: int = 200):
        self.continuous = bool(continuous)
        self.max_steps = int(max_steps)
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.name = "mountain_car_continuous" if self.continuous else "mountain_car_discrete"
        self.action_space = (ActionSpace.box(-1.0, 1.0) if self.continuous
                             else ActionSpace.discrete([-1.0, 0.0, 1.0]))

    # Hashable by value, so that equal envs share compiled code as static jit arguments.
    def __eq__(self, other) -> bool:
        return (isinstance(other, MountainCar) and self.continuous == other.continuous
                and self.max_steps == other.max_steps)

    def __hash__(self) -> int:
        return hash((MountainCar, self.continuous, self.max_steps))

    def __repr__(self) -> str:
        return f"MountainCar(continuous={self.continuous}, max_steps={self.max_steps})"

    # -- parameters -----------------------------------------------------------------------
    def default_params(self) -> MountainCarParams:
        return jax.tree_util.tree_map(_f32, MountainCarParams())

    # -- observation helpers ----------------------------------------------------------------
    @staticmethod
    def get_obs(state: MountainCarState) -> jax.Array:
        """float32 (2,) = [position, velocity]."""
        return jnp.stack([state.position, state.velocity]).astype(jnp.float32)

    def obs_bounds(self, params: MountainCarParams) -> Tuple[jax.Array, jax.Array]:
        """([min_position, -max_speed], [max_position, max_speed]), float32 (2,) each."""
        low = jnp.stack([_f32(params.min_position), -_f32(params.max_speed)])
        high = jnp.stack([_f32(params.max_position), _f32(params.max_speed)])
        return low, high

    # -- resets -----------------------------------------------------------------------------
    def reset_to(self, key: jax.Array, params: MountainCarParams, start) -> Tuple[jax.Array, MountainCarState]:
        """Start from ``start = [x, v]`` (array-like, shape (2,)); ``key`` is unused.

        Returns (obs float32 (2,), state)."""
        del key
        start = _f32(start)
        state = MountainCarState(position=start[0], velocity=start[1],
                                 time=jnp.zeros((), jnp.int32))
        return self.get_obs(state), state

    def reset(self, key: jax.Array, params: MountainCarParams) -> Tuple[jax.Array, MountainCarState]:
        """A fresh uniform random start: x in [start_position_low, start_position_high),
        v in [start_velocity_low, start_velocity_high]. Returns (obs float32 (2,), state)."""
        kx, kv = jax.random.split(key)
        x = jax.random.uniform(kx, (), jnp.float32, _f32(params.start_position_low),
                               _f32(params.start_position_high))
        v = jax.random.uniform(kv, (), jnp.float32, _f32(params.start_velocity_low),
                               _f32(params.start_velocity_high))
        return self.reset_to(key, params, jnp.stack([x, v]))

    def evaluation_starts(self, key: jax.Array, params: MountainCarParams, n: int):
        """``n`` independent uniform random starts (the paper's evaluation protocol).

        Returns (obs float32 (n, 2), state with leaves of leading axis n)."""
        keys = jax.random.split(key, n)
        return jax.vmap(self.reset, in_axes=(0, None))(keys, params)

    # -- dynamics ---------------------------------------------------------------------------
    def step(self, key: jax.Array, state: MountainCarState, action, params: MountainCarParams):
        """One step. ``action`` float32 (1,) (or a scalar): the action value.

        Returns (obs float32 (2,), next_state, reward float32 (), terminated bool (),
        truncated bool (), info dict). ``key`` is unused (the dynamics are deterministic)."""
        del key
        a = jnp.clip(jnp.reshape(_f32(action), (-1,))[0], -1.0, 1.0)
        x, v = _f32(state.position), _f32(state.velocity)
        max_speed = _f32(params.max_speed)
        min_pos = _f32(params.min_position)
        v = v + a * _f32(params.force) - jnp.cos(3.0 * x) * _f32(params.gravity)
        v = jnp.clip(v, -max_speed, max_speed)
        x = jnp.clip(x + v, min_pos, _f32(params.max_position))
        v = jnp.where((x <= min_pos) & (v < 0.0), jnp.zeros_like(v), v)
        terminated = (x >= _f32(params.goal_position)) & (v >= _f32(params.goal_velocity))
        reward = jnp.where(terminated, 1.0 - jnp.abs(v) / max_speed, 0.0).astype(jnp.float32)
        time = state.time + 1
        truncated = (time >= self.max_steps) & jnp.logical_not(terminated)
        next_state = MountainCarState(position=x, velocity=v, time=time)
        info: Dict[str, jax.Array] = {}
        return self.get_obs(next_state), next_state, reward, terminated, truncated, info

    # -- rendering (host side) --------------------------------------------------------------
    def render_rgb(self, state: MountainCarState, params: MountainCarParams | None = None,
                   width: int = 360, height: int = 240) -> np.ndarray:
        """A picture of one (unbatched) state: np.uint8 (height, width, 3).

        Hill ``y = 0.45 sin(3x) + 0.55`` (Gymnasium's drawing), the car on it, tilted along the
        slope, and the goal flag at ``goal_position``. Plain numpy rasterisation."""
        if params is None:
            params = self.default_params()
        return render_mountain_car(float(np.asarray(state.position)),
                                   float(np.asarray(params.min_position)),
                                   float(np.asarray(params.max_position)),
                                   float(np.asarray(params.goal_position)),
                                   width=width, height=height)


def _hill(x):
    return 0.45 * np.sin(3.0 * x) + 0.55


def render_mountain_car(position: float, min_position: float = -1.2, max_position: float = 0.5,
                        goal_position: float = 0.5, width: int = 360,
                        height: int = 240) -> np.ndarray:
    """Rasterise the scene for a car at ``position``. Returns np.uint8 (height, width, 3)."""
    # World window: x in [min_position - 0.05, max(max_position, goal) + 0.15], y in [-0.02, 1.25].
    pad = 0.05
    x0, x1 = min_position - pad, max(max_position, goal_position) + 0.15
    y0, y1 = -0.02, 1.25
    px = np.linspace(x0, x1, width)[None, :]                 # (1, W)
    py = np.linspace(y1, y0, height)[:, None]                # (H, 1), top row = y1
    img = np.empty((height, width, 3), np.uint8)
    img[:] = (235, 242, 250)                                 # sky
    ground = py <= _hill(px)
    img[np.broadcast_to(ground, (height, width))] = (120, 170, 90)
    # Hill outline (thick line): distance in pixels to the curve along y.
    dy = (y1 - y0) / max(height - 1, 1)
    outline = np.abs(py - _hill(px)) <= 1.5 * dy
    img[np.broadcast_to(outline, (height, width))] = (40, 80, 30)
    # Flag at the goal.
    fx = goal_position
    fy = _hill(fx)
    dx = (x1 - x0) / max(width - 1, 1)
    pole = (np.abs(px - fx) <= 1.0 * dx) & (py >= fy) & (py <= fy + 0.18)
    img[np.broadcast_to(pole, (height, width))] = (60, 60, 60)
    tri = ((px >= fx) & (px <= fx + 0.12) & (py <= fy + 0.18)
           & (py >= fy + 0.10 + (px - fx) * (0.08 / 0.12) * 0.5)
           & (py <= fy + 0.18 - (px - fx) * (0.08 / 0.12) * 0.5))
    img[np.broadcast_to(tri, (height, width))] = (230, 200, 30)
    # Car: a rectangle in the local frame (tangent u, normal n) sitting on the hill.
    cx = float(np.clip(position, min_position, max(max_position, goal_position)))
    slope = 0.45 * 3.0 * np.cos(3.0 * cx)
    ang = np.arctan(slope)
    ux, uy = np.cos(ang), np.sin(ang)
    nx, ny = -uy, ux
    half_len, body_h, clearance = 0.07, 0.05, 0.015
    base = np.array([cx, _hill(cx)])
    rx, ry = px - base[0], py - base[1]
    along = rx * ux + ry * uy
    up = rx * nx + ry * ny
    body = (np.abs(along) <= half_len) & (up >= clearance) & (up <= clearance + body_h)
    img[body] = (200, 40, 40)
    for s in (-0.65, 0.65):                                  # wheels
        wx = base[0] + s * half_len * ux + 0.018 * nx
        wy = base[1] + s * half_len * uy + 0.018 * ny
        wheel = (px - wx) ** 2 + (py - wy) ** 2 <= 0.018 ** 2
        img[wheel] = (30, 30, 30)
    return img
