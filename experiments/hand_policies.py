"""A simple hand-written control policy per classic-control task, for HEDGER's phase 1.

Each maps a Gymnasium observation (NumPy (S,)) to the env's action (a ``Discrete`` index, or
a float32 (1,) vector), as ``Hedger.learn_from_demonstrations(policy, n_episodes=...)``
takes it on any Gymnasium env. They are deliberately crude -- the paper's point is that
phase 1 needs only a policy that reaches the reward sometimes, not a good one:

* the cars and the acrobot pump energy: push (or torque) along the (second joint's)
  velocity;
* the pendulum swings up by energy (torque along the velocity while below the upright
  energy) and balances by a PD law near the top;
* the cart-pole balances by a PD law on the pole angle (plus a little on the cart).
"""
from __future__ import annotations

from typing import Callable, Dict

import numpy as np

__all__ = ["HAND_POLICIES", "mountain_car", "mountain_car_continuous", "acrobot", "pendulum",
           "cart_pole"]


def mountain_car(obs: np.ndarray) -> int:
    """Push (2) while moving right, else push left (0): obs (position, velocity)."""
    return 2 if obs[1] >= 0 else 0


def mountain_car_continuous(obs: np.ndarray) -> np.ndarray:
    """Full force along the velocity."""
    return np.asarray([1.0 if obs[1] >= 0 else -1.0], np.float32)


def acrobot(obs: np.ndarray) -> int:
    """Torque (+1: index 2, -1: index 0) along the second joint's angular velocity:
    obs (cos t1, sin t1, cos t2, sin t2, dt1, dt2)."""
    return 2 if obs[5] >= 0 else 0


def pendulum(obs: np.ndarray) -> np.ndarray:
    """Energy swing-up, PD balance near the top: obs (cos t, sin t, dt), t = 0 upright.

    Energy per unit inertia E = dt^2 / 2 - 15 (1 - cos t) (the env's g = 10, l = 1: the
    upright at rest is E = 0). Below it, torque along the velocity; near the top,
    u = -(10 t + 2 dt); clipped to the env's [-2, 2]."""
    cos_t, sin_t, dt = (float(v) for v in obs)
    theta = np.arctan2(sin_t, cos_t)
    if cos_t > 0.85:
        u = -(10.0 * theta + 2.0 * dt)
    else:
        energy = 0.5 * dt ** 2 - 15.0 * (1.0 - cos_t)
        u = 2.0 * np.sign(dt if dt != 0 else 1.0) if energy < 0 else -0.5 * dt
    return np.asarray([np.clip(u, -2.0, 2.0)], np.float32)


def cart_pole(obs: np.ndarray) -> int:
    """Push right (1) when the pole, its velocity and (a little) the cart's drift say so:
    obs (x, dx, angle, dangle)."""
    x, dx, angle, dangle = (float(v) for v in obs)
    return 1 if 10.0 * angle + 2.0 * dangle + 0.1 * x + 0.5 * dx > 0 else 0


#: Gymnasium id -> hand policy.
HAND_POLICIES: Dict[str, Callable[[np.ndarray], object]] = {
    "MountainCar-v0": mountain_car,
    "MountainCarContinuous-v0": mountain_car_continuous,
    "Acrobot-v1": acrobot,
    "Pendulum-v1": pendulum,
    "CartPole-v1": cart_pole,
}
