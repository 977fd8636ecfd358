"""The functional environment interface (gymnax-like) shared by every environment here.

An environment is a small object of *pure* functions; all numbers that define it live in a
``params`` pytree (so they can be vmapped) and all mutable quantities in a ``state`` pytree.

Contract (every method jittable and vmappable; shapes are for one instance):

  reset(key, params) -> (obs, state)
      obs float32 (obs_dim,). Draws a *fresh* training start on every call.
  step(key, state, action, params) -> (obs, state, reward, terminated, truncated, info)
      action float32 (action_dim,), the action *value*. reward float32 (), terminated and
      truncated bool (). ``terminated`` is a true terminal (goal reached, wall hit);
      ``truncated`` is the time limit (never a terminal for bootstrapping). No auto-reset:
      the returned obs is the real next observation. Stepping a finished episode is the
      caller's business (the agent masks those steps).
  evaluation_starts(key, params, n) -> (obs, state) batched with leading axis n
      The evaluation protocol's start states (random or a fixed list, tiled to n).
  reset_to(key, params, start) -> (obs, state)  (optional) start from a given physical state.
  obs_bounds(params) -> (low, high) float32 (obs_dim,) each: the range used to scale
      observations to [0, 1] before distances.
  action_space: envs.spaces.ActionSpace (static).
  max_steps: int (static) time-limit of an episode.
  obs_dim, action_dim: ints.
  render_rgb(state, params) -> np.uint8 (H, W, 3)  (host side, numpy) a picture of a state.

Environments never import ``hedger_jax``.
"""
from __future__ import annotations

from typing import Any, Protocol, Tuple, runtime_checkable

import jax

from envs.spaces import ActionSpace


@runtime_checkable
class FunctionalEnv(Protocol):
    name: str
    action_space: ActionSpace
    obs_dim: int
    max_steps: int

    def default_params(self) -> Any: ...

    def reset(self, key: jax.Array, params: Any) -> Tuple[jax.Array, Any]: ...

    def step(self, key: jax.Array, state: Any, action: jax.Array, params: Any): ...

    def evaluation_starts(self, key: jax.Array, params: Any, n: int): ...

    def obs_bounds(self, params: Any) -> Tuple[jax.Array, jax.Array]: ...

    def render_rgb(self, state: Any, params: Any): ...
