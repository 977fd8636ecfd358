"""Brax adapter: any functional env of ``envs.base`` as a ``brax.envs.base.Env``.

This is the only module of the project that imports brax (``import envs`` never does).

``BraxEnv`` maps the functional API onto brax's ``State(pipeline_state, obs, reward, done,
metrics, info)`` for one environment instance (batch it with brax's ``VmapWrapper``):

  * ``pipeline_state``: the functional env's state pytree.
  * ``obs`` float32 (obs_dim,), ``reward`` float32 (), ``done`` float32 () (1.0 = finished).
  * ``info["rng"]``: the PRNG key (raw uint32 (2,)) that feeds the env's step noise; every step
    splits it: ``rng, k = split(info["rng"])``, ``env.step(k, ...)``. ``reset(rng)`` does
    ``rng, k = split(rng)``, ``env.reset(k, params)`` and stores ``rng``.
  * ``info["truncation"]`` float32 (): 1.0 when the episode ended by the time limit and not by a
    true terminal (the same key and meaning as brax's ``EpisodeWrapper``).
  * ``info["terminated"]`` float32 (): 1.0 on a true terminal (goal, wall).

Actions: brax agents emit continuous vectors of shape (action_size,) = (action_dim,), usually
in [-1, 1]. With ``normalize_actions=True`` (default) the action is clipped to [-1, 1] and
mapped affinely onto the env's [low, high]; with ``False`` it is clipped to [low, high]. For a
discrete env the resulting vector is then replaced by the *nearest* allowed action value
(Euclidean distance; ties go to the first value in ``ActionSpace.values``). For mountain car
({-1, 0, +1}, low/high = ±1): a < -0.5 -> -1, -0.5 <= a <= 0.5 -> 0, a > 0.5 -> +1.

Time limit (``time_limit``):
  * ``True`` (default): the functional env's own truncation (at ``env.max_steps``) ends the
    episode: ``done = terminated | truncated``, ``info["truncation"] = truncated & ~terminated``.
  * ``False``: the env's truncation flag is ignored (``done = terminated``, truncation 0) and the
    time limit is left to brax's ``EpisodeWrapper``. Use this under
    ``brax.envs.wrappers.training.wrap``/``EpisodeWrapper``: that wrapper *overwrites*
    ``info["truncation"]`` and computes it as ``1 - done`` at the limit, so an adapter that
    already reported ``done = 1`` there would be mislabelled as a true terminal.
    ``wrap_for_training`` below does this for you.

Resets: brax's ``AutoResetWrapper`` restores the *first* state cached at ``reset`` (the same
start every episode of a batch slot). The functional envs draw a fresh random start on every
reset, so use ``ResamplingAutoResetWrapper`` (or ``wrap_for_training``), which calls the inner
``reset`` with a fresh key for the finished slots. ``BraxEnv.reset`` itself always re-samples.
"""
from __future__ import annotations

import warnings
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State, Wrapper
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper

from envs.base import FunctionalEnv

__all__ = ["BraxEnv", "ResamplingAutoResetWrapper", "wrap_for_training"]


class BraxEnv(Env):
    """A functional env behind brax's ``Env`` interface (see module doc).

    Args:
      env: functional env instance, or an ``envs.make`` name.
      params: the env's params pytree (default ``env.default_params()``); closed over as a
        constant under jit.
      time_limit: use the env's own truncation (True) or leave it to ``EpisodeWrapper`` (False).
      normalize_actions: map actions from [-1, 1] onto [low, high] (True) or clip (False).
    """

    def __init__(self, env: FunctionalEnv | str, params: Any = None, *,
                 time_limit: bool = True, normalize_actions: bool = True,
                 env_kwargs: Optional[dict] = None):
        if isinstance(env, str):
            import envs as _envs

            env = _envs.make(env, **(env_kwargs or {}))
        self.env = env
        self.params = env.default_params() if params is None else params
        self.time_limit = bool(time_limit)
        self.normalize_actions = bool(normalize_actions)
        aspace = env.action_space
        self._low = np.asarray(aspace.low, np.float32)
        self._high = np.asarray(aspace.high, np.float32)
        self._values = aspace.values_array() if aspace.is_discrete else None

    # ---- brax Env properties -----------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return int(self.env.obs_dim)

    @property
    def action_size(self) -> int:
        return int(self.env.action_space.action_dim)

    @property
    def backend(self) -> str:
        return "jax"

    @property
    def max_steps(self) -> int:
        return int(self.env.max_steps)

    # ---- actions -----------------------------------------------------------------------
    def action_value(self, action: jax.Array) -> jax.Array:
        """Brax action (action_dim,) -> the functional env's action value (action_dim,).

        Works on any leading batch shape (..., action_dim)."""
        a = jnp.asarray(action, jnp.float32)
        low, high = jnp.asarray(self._low), jnp.asarray(self._high)
        if self.normalize_actions:
            # centre + a * half-range: exact (a itself) for a [-1, 1] box.
            a = 0.5 * (low + high) + jnp.clip(a, -1.0, 1.0) * (0.5 * (high - low))
        else:
            a = jnp.clip(a, low, high)
        if self._values is None:
            return a
        values = jnp.asarray(self._values)                               # (n, d)
        d2 = jnp.sum((a[..., None, :] - values) ** 2, axis=-1)          # (..., n)
        return values[jnp.argmin(d2, axis=-1)]

    # ---- dynamics ----------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        """rng: raw PRNG key (2,). Returns the first State (done = 0, reward = 0)."""
        rng, sub = jax.random.split(rng)
        obs, env_state = self.env.reset(sub, self.params)
        zero = jnp.zeros((), jnp.float32)
        info = {"rng": rng, "truncation": zero, "terminated": zero}
        return State(pipeline_state=env_state, obs=jnp.asarray(obs, jnp.float32), reward=zero,
                     done=zero, metrics={}, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """One step of the functional env; action (action_size,) (see module doc)."""
        rng, sub = jax.random.split(state.info["rng"])
        obs, env_state, reward, terminated, truncated, _ = self.env.step(
            sub, state.pipeline_state, self.action_value(action), self.params)
        terminated = jnp.asarray(terminated, bool)
        if self.time_limit:
            truncation = jnp.asarray(truncated, bool) & ~terminated
        else:
            truncation = jnp.zeros((), bool)
        done = terminated | truncation
        info = dict(state.info)
        info.update(rng=rng, truncation=truncation.astype(jnp.float32),
                    terminated=terminated.astype(jnp.float32))
        return state.replace(pipeline_state=env_state, obs=jnp.asarray(obs, jnp.float32),
                             reward=jnp.asarray(reward, jnp.float32),
                             done=done.astype(jnp.float32), info=info)


def _split_keys(rng: jax.Array):
    """Split a (..., 2) batch of raw keys into two (..., 2) batches."""
    flat = rng.reshape((-1, rng.shape[-1]))
    pairs = jax.vmap(jax.random.split)(flat)                            # (B, 2, 2)
    return pairs[:, 0].reshape(rng.shape), pairs[:, 1].reshape(rng.shape)


class ResamplingAutoResetWrapper(Wrapper):
    """Auto-reset with a *fresh* start for every finished episode.

    Drop-in for brax's ``AutoResetWrapper`` (same position: outermost, above ``EpisodeWrapper``
    and ``VmapWrapper``), but instead of restoring the first state cached at ``reset`` it calls
    the inner ``reset`` with new keys split from ``info["rng"]`` (which ``BraxEnv`` maintains)
    and takes ``pipeline_state``, ``obs`` and ``info["rng"]`` from that new start for the
    finished slots. The other ``info`` entries (``steps``, ``truncation``, episode metrics) keep
    brax's semantics: ``done``/``truncation`` describe the step just taken, ``obs`` is already
    the next episode's first observation. Skips the reset computation (``lax.cond``) when no
    slot is done.
    """

    def step(self, state: State, action: jax.Array) -> State:
        if "steps" in state.info:
            steps = jnp.where(state.done, jnp.zeros_like(state.info["steps"]),
                              state.info["steps"])
            state = state.replace(info={**state.info, "steps": steps})
        state = state.replace(done=jnp.zeros_like(state.done))
        state = self.env.step(state, action)
        done = state.done.astype(bool)

        def _with_resets(st):
            rng, reset_key = _split_keys(st.info["rng"])
            fresh = self.env.reset(reset_key)

            def pick(new, old):
                d = done
                if d.shape:
                    d = jnp.reshape(d, d.shape + (1,) * (old.ndim - d.ndim))
                return jnp.where(d, new, old)

            pipeline_state = jax.tree_util.tree_map(pick, fresh.pipeline_state,
                                                    st.pipeline_state)
            obs = jax.tree_util.tree_map(pick, fresh.obs, st.obs)
            info = dict(st.info)
            info["rng"] = pick(fresh.info["rng"], rng)
            return st.replace(pipeline_state=pipeline_state, obs=obs, info=info)

        def _no_resets(st):
            rng, _ = _split_keys(st.info["rng"])
            info = dict(st.info)
            info["rng"] = rng
            return st.replace(info=info)

        return jax.lax.cond(jnp.any(done), _with_resets, _no_resets, state)


def wrap_for_training(env: FunctionalEnv | BraxEnv | str, episode_length: Optional[int] = None,
                      action_repeat: int = 1, **brax_env_kwargs) -> Wrapper:
    """Like ``brax.envs.wrappers.training.wrap`` but with real (re-sampled) resets.

    ``VmapWrapper`` -> ``EpisodeWrapper(episode_length, action_repeat)`` ->
    ``ResamplingAutoResetWrapper``. A functional env (or name) is wrapped in
    ``BraxEnv(time_limit=False)`` so that the time limit and ``info["truncation"]`` come from
    ``EpisodeWrapper`` alone; ``episode_length`` defaults to the env's ``max_steps``.
    ``reset(rng)`` takes a batch of keys (B, 2).
    """
    if not isinstance(env, BraxEnv):
        brax_env_kwargs.setdefault("time_limit", False)
        env = BraxEnv(env, **brax_env_kwargs)
    elif env.time_limit:
        warnings.warn("wrap_for_training: BraxEnv(time_limit=True) under EpisodeWrapper reports "
                      "its own time limit as a terminal; build it with time_limit=False")
    if episode_length is None:
        episode_length = env.max_steps
    wrapped = VmapWrapper(env)
    wrapped = EpisodeWrapper(wrapped, episode_length, action_repeat)
    return ResamplingAutoResetWrapper(wrapped)
