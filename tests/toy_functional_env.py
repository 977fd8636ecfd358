"""A tiny functional env (``envs.base`` contract) for adapter tests, independent of the real envs.

A noisy 1-D cart: state (x, v, t); v <- clip(0.1·a + noise·N(0, 1), ±0.2),
x <- clip(x + v, -1, 1); terminated when x >= 0.9 (reward 1), truncated at ``max_steps``.
obs = (x, v) float32 (2,), inside ``obs_bounds`` = ((-1, -0.2), (1, 0.2)).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.pytree import pytree_dataclass
from envs.spaces import ActionSpace


@pytree_dataclass
class ToyParams:
    noise: jax.Array = 0.01
    goal: jax.Array = 0.9


@pytree_dataclass
class ToyState:
    x: jax.Array
    v: jax.Array
    t: jax.Array


class ToyEnv:
    name = "toy"
    obs_dim = 2
    render_fps = 20

    def __init__(self, continuous: bool = False, max_steps: int = 25):
        self.continuous = continuous
        self.max_steps = max_steps
        self.action_space = (ActionSpace.box(-1.0, 1.0) if continuous
                             else ActionSpace.discrete([-1.0, 0.0, 1.0]))
        self.action_dim = 1

    def default_params(self):
        return ToyParams(noise=jnp.float32(0.01), goal=jnp.float32(0.9))

    def _obs(self, s):
        return jnp.stack([s.x, s.v]).astype(jnp.float32)

    def reset(self, key, params):
        x = jax.random.uniform(key, (), jnp.float32, -0.5, 0.5)
        s = ToyState(x=x, v=jnp.float32(0.0), t=jnp.int32(0))
        return self._obs(s), s

    def reset_to(self, key, params, start):
        start = jnp.asarray(start, jnp.float32)
        s = ToyState(x=start[0], v=start[1], t=jnp.int32(0))
        return self._obs(s), s

    def step(self, key, state, action, params):
        a = jnp.clip(jnp.asarray(action, jnp.float32).reshape(()), -1.0, 1.0)
        v = jnp.clip(0.1 * a + params.noise * jax.random.normal(key, (), jnp.float32), -0.2, 0.2)
        x = jnp.clip(state.x + v, -1.0, 1.0)
        t = state.t + 1
        s = ToyState(x=x, v=v, t=t)
        terminated = x >= params.goal
        truncated = (t >= self.max_steps) & ~terminated
        reward = terminated.astype(jnp.float32)
        return self._obs(s), s, reward, terminated, truncated, {"t": t}

    def evaluation_starts(self, key, params, n):
        keys = jax.random.split(key, n)
        return jax.vmap(self.reset, in_axes=(0, None))(keys, params)

    def obs_bounds(self, params):
        return (jnp.array([-1.0, -0.2], jnp.float32), jnp.array([1.0, 0.2], jnp.float32))

    def render_rgb(self, state, params):
        img = np.full((40, 60, 3), 255, np.uint8)
        col = int(np.clip((float(state.x) + 1.0) / 2.0 * 59, 0, 59))
        img[15:25, max(col - 2, 0):col + 3] = (200, 0, 0)
        return img
