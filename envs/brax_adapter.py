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

Brax's own agents: ``train_ppo(env, ...)`` and ``train_sac(env, ...)`` run
``brax.training.agents.{ppo,sac}.train`` on a functional env with the wrappers above and
``brax_compat()``: brax 0.14 calls ``jax.device_put_replicated``, which jax 0.10 removed; the
context restores an equivalent (each device's copy stacked along a leading axis, what brax's
``pmap`` expects) while brax runs, and removes it afterwards. Importing this module hides the
"Failed to import warp" lines MuJoCo prints when its optional warp backend is absent.
"""
from __future__ import annotations

import contextlib
import io
import sys
import warnings
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np


def _import_brax_quietly():
    """brax imports MuJoCo's MJX, whose optional warp backend prints "Failed to import warp"
    when absent; those lines are dropped, anything else printed is passed on."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        from brax.envs.base import Env, State, Wrapper
        from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper
    kept = [line for line in buf.getvalue().splitlines(keepends=True)
            if not line.startswith(("Failed to import warp", "Failed to import mujoco_warp"))]
    sys.stdout.write("".join(kept))
    return Env, State, Wrapper, EpisodeWrapper, VmapWrapper


Env, State, Wrapper, EpisodeWrapper, VmapWrapper = _import_brax_quietly()

from envs.base import FunctionalEnv  # noqa: E402

__all__ = ["BraxEnv", "ResamplingAutoResetWrapper", "wrap_for_training", "brax_compat",
           "train_ppo", "train_sac"]


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
                      action_repeat: int = 1, randomization_fn: Optional[Callable] = None,
                      **brax_env_kwargs) -> Wrapper:
    """Like ``brax.envs.wrappers.training.wrap`` but with real (re-sampled) resets.

    ``VmapWrapper`` -> ``EpisodeWrapper(episode_length, action_repeat)`` ->
    ``ResamplingAutoResetWrapper``. A functional env (or name) is wrapped in
    ``BraxEnv(time_limit=False)`` so that the time limit and ``info["truncation"]`` come from
    ``EpisodeWrapper`` alone; ``episode_length`` defaults to the env's ``max_steps``.
    ``reset(rng)`` takes a batch of keys (B, 2). Usable as brax's ``wrap_env_fn``
    (``randomization_fn``, domain randomisation of MJX models, is refused: no such model).
    """
    if randomization_fn is not None:
        raise ValueError("wrap_for_training: randomization_fn is not supported (the "
                         "functional envs have no MJX model to randomise)")
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


def _device_put_replicated(x: Any, devices) -> Any:
    """``jax.device_put_replicated`` as jax < 0.10 had it: every leaf stacked once per device
    along a new leading axis, one slice on each device (what brax's ``pmap`` takes)."""
    devices = list(devices)
    mesh = jax.sharding.Mesh(np.asarray(devices, dtype=object), ("d",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("d"))
    return jax.tree_util.tree_map(
        lambda leaf: jax.device_put(jnp.stack([jnp.asarray(leaf)] * len(devices)), sharding), x)


@contextlib.contextmanager
def brax_compat():
    """Run brax's training code on this jax: while the context is open,
    ``jax.device_put_replicated`` (removed in jax 0.10, called by brax 0.14's agents) is
    provided by ``_device_put_replicated``; on exit the jax module is as it was. A no-op
    where jax still has it."""
    try:
        jax.device_put_replicated  # noqa: B018
        missing = False
    except AttributeError:
        missing = True
    if missing:
        jax.device_put_replicated = _device_put_replicated
    try:
        yield
    finally:
        if missing:
            del jax.device_put_replicated


def _train(agent: str, env: Any, env_kwargs: Optional[dict], **kwargs):
    import importlib

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        train_fn = importlib.import_module(f"brax.training.agents.{agent}.train").train
    sys.stdout.write("".join(line for line in buf.getvalue().splitlines(keepends=True)
                             if not line.startswith("Failed to import")))
    brax_env = env if isinstance(env, BraxEnv) else BraxEnv(env, time_limit=False,
                                                            **(env_kwargs or {}))
    kwargs.setdefault("episode_length", brax_env.max_steps)
    kwargs.setdefault("wrap_env_fn", wrap_for_training)
    with brax_compat():
        return train_fn(environment=brax_env, **kwargs)


def train_ppo(env: Any, *, env_kwargs: Optional[dict] = None, **kwargs):
    """brax's PPO (``brax.training.agents.ppo.train.train``) on a functional env (or name, or
    ``BraxEnv``): the env behind ``BraxEnv(time_limit=False)`` and ``wrap_for_training``
    (real re-sampled resets), ``episode_length`` the env's ``max_steps`` unless given, inside
    ``brax_compat``. kwargs go to brax's ``train``. Returns what it returns
    (make_policy, params, metrics)."""
    return _train("ppo", env, env_kwargs, **kwargs)


def train_sac(env: Any, *, env_kwargs: Optional[dict] = None, **kwargs):
    """brax's SAC (``brax.training.agents.sac.train.train``) as ``train_ppo`` runs PPO."""
    return _train("sac", env, env_kwargs, **kwargs)
