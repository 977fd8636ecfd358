"""``Hedger``: a Stable-Baselines3-style learner around the pure functions of ``agent.py``.

::

    from hedger_jax.learner import Hedger

    model = Hedger("HedgerMountainCar-v0", capacity=20_000, seed=0)
    model.learn_from_demonstrations("demos.npz")          # phase 1 (or a policy + n_episodes)
    model.learn(total_timesteps=50_000, progress_bar=True) # phase 2 (epsilon-greedy)
    action, _ = model.predict(obs, deterministic=True)    # what the Gymnasium env expects
    model.evaluate(n_episodes=200)                         # {"mean_steps": ..., "success_rate": ...}
    model.save("agent.npz"); model = Hedger.load("agent.npz")

Everything numerical runs in jitted functions compiled once per (env, config, run config) and
shared by every learner with equal static settings; the host only loops, shows progress and
checks inputs (``hedger_jax.validation``) and the memory's error flags (``memory_check``
after every chunk: a NaN/inf that tried to enter the memory raises ``NonFiniteValueError``,
a full memory under ``full_policy="error"`` raises ``MemoryFullError``; the stored data are
never corrupted by either).

The memory buffer is *donated* to the jitted training functions: after ``learn`` (or
``learn_from_demonstrations``) an old reference to ``model.memory`` is invalid; always read
``model.memory`` afresh.

Any Gymnasium env works too: ``Hedger("Pendulum-v1")``, ``Hedger(gymnasium.make("CartPole-v1"))``
(a ``Box`` observation space, a ``Discrete`` or one-dimensional ``Box`` action space). The
project's JAX envs run whole episodes in jitted code; any other Gymnasium env runs in a host
loop, one jitted action per step and one jitted reverse replay per episode
(``hedger_jax.environments``, which also states how its actions and observations are scaled).

Actions. The functional envs take action *values* (e.g. -1.0, 0.0, +1.0 for mountain car);
the Gymnasium adapter (``envs.gym_adapter``) takes a ``Discrete`` *index* for a discrete env
and the value vector for a continuous one. ``predict`` returns what the Gymnasium env
expects (SB3 semantics, so a SB3-style ``evaluate_policy(model, gym_env)`` loop works);
``predict_action_value`` returns the action values.
"""
from __future__ import annotations

import functools
import os
from typing import Any, Callable, Dict, Optional, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.agent import (Evaluation, RunConfig, evaluate, explore_action, rollout,
                              train_prefix, training_act, transitions_from_demonstrations)
from hedger_jax.checkpoint import load_checkpoint, save_checkpoint
from hedger_jax.config import HedgerConfig
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.greedy import greedy_action
from hedger_jax.cpu import jit as _jit
from hedger_jax import environments as _envs
from hedger_jax.environments import GYM_IDS, GymnasiumEnv, make_env  # noqa: F401 (re-exported)
from hedger_jax.memory import Memory, init_memory, memory_check, refresh_index
from hedger_jax.prediction import predict as _predict_q
from hedger_jax.validation import (InvalidInputError, check_actions, check_key,
                                   check_observations, check_transitions)

__all__ = ["Hedger", "make_env", "GYM_IDS", "ENV_PRESETS", "HOST_EVAL_EPISODES"]

#: Default settings per env (measured in ``experiments``): ``hedger`` are overrides for
#: ``HedgerConfig.for_env`` (``action_scale`` included), ``run`` for ``RunConfig``.
ENV_PRESETS: Dict[str, Dict[str, Dict[str, Any]]] = {
    "mountain_car_discrete": {"hedger": dict(bandwidth=0.015, alpha=0.8, gamma=0.8), "run": {}},
    "mountain_car_continuous": {"hedger": dict(bandwidth=0.015, alpha=0.8, gamma=0.8,
                                               action_scale=0.1), "run": {}},
    "corridor": {"hedger": dict(bandwidth=0.06, alpha=0.2, gamma=0.99, action_scale=0.25),
                 "run": dict(exploration="gaussian", noise_std=0.3)},
}

#: Default ``RunConfig.eval_episodes`` for a Gymnasium env run by the host loop (its
#: ``eval_max_steps`` defaults to the env's time limit).
HOST_EVAL_EPISODES = 20


# ------------------------------------------------------------------------------------------
# Jitted pieces (module level: compiled once per static settings, shared by all learners)
# ------------------------------------------------------------------------------------------
@functools.partial(_jit, static_argnames=("env", "config", "run", "max_steps", "max_episodes"),
                   donate_argnames=("memory",))
def _learn_chunk(memory: Memory, key: jax.Array, env_params: Any, budget: jax.Array, *, env,
                 config: HedgerConfig, run: RunConfig, max_steps: int, max_episodes: int):
    """Phase two: epsilon-greedy episodes + reverse replay until ``budget`` () steps were taken
    or ``max_episodes`` episodes ran. Returns (memory, key, steps (), n_episodes (),
    lengths int32 (max_episodes,), returns float32 (max_episodes,))."""

    def cond(c):
        _, _, steps, n, _, _ = c
        return (steps < budget) & (n < max_episodes)

    def body(c):
        mem, key, steps, n, lengths, returns = c
        key, k_reset, k_run = jax.random.split(key, 3)
        mem = refresh_index(config, mem)
        obs0, s0 = env.reset(k_reset, env_params)

        params = with_data_bandwidth(config, mem, None)   # once for the rollout and replay
        out = rollout(env, env_params, training_act(config, run, mem, params=params), k_run,
                      max_steps, obs0, s0)
        ep, length = out[0], out[1]
        mem = train_prefix(config, mem, ep, length, *out[2:], params=params)
        ret = jnp.sum(jnp.where(ep.valid, ep.reward, 0.0))
        return (mem, key, steps + length, n + 1, lengths.at[n].set(length),
                returns.at[n].set(ret))

    zero = jnp.zeros((), jnp.int32)
    init = (memory, key, zero, zero, jnp.zeros((max_episodes,), jnp.int32),
            jnp.zeros((max_episodes,), jnp.float32))
    return jax.lax.while_loop(cond, body, init)


@functools.partial(_jit, static_argnames=("config",),
                   donate_argnames=("memory",))
def _train_prefix_jit(memory: Memory, episode: Any, length: jax.Array, *, config: HedgerConfig):
    """Reverse replay of one recorded episode (leading axis T) over its first ``length`` steps."""
    return train_prefix(config, memory, episode, length)


@functools.partial(_jit, static_argnames=("env", "config", "act", "init", "max_steps", "has_start"),
                   donate_argnames=("memory",))
def _policy_episode(memory: Memory, key: jax.Array, env_params: Any, start: Any, *, env,
                    config: HedgerConfig, act, init, max_steps: int, has_start: bool):
    """Phase one with an example policy in control: one episode, then reverse replay.
    Returns (memory, length ())."""
    k_reset, k_init, k_run = jax.random.split(key, 3)
    if has_start:
        obs0, s0 = env.reset_to(k_reset, env_params, start)
    else:
        obs0, s0 = env.reset(k_reset, env_params)
    ep, length = rollout(env, env_params, act, k_run, max_steps, obs0, s0, init(k_init))
    return train_prefix(config, memory, ep, length), length


@functools.partial(_jit, static_argnames=("config",))
def _greedy_batch(memory: Memory, obs: jax.Array, key: jax.Array, *, config: HedgerConfig):
    """Greedy actions for obs (B, S) with the *same* key for every row (so an observation's
    action does not depend on its batch position) -> (actions (B, A), values (B,), known (B,),
    config action index (B,) (0 for continuous))."""
    acts, vals, known = jax.vmap(lambda o: greedy_action(config, memory, o, key))(obs)
    return acts, vals, known, _config_index(config, acts)


@functools.partial(_jit, static_argnames=("config", "run"))
def _explore_batch(memory: Memory, obs: jax.Array, key: jax.Array, *, config: HedgerConfig,
                   run: RunConfig):
    """Epsilon-greedy actions for obs (B, S), one key per row -> (actions (B, A), index (B,))."""
    keys = jax.random.split(key, obs.shape[0])
    acts = jax.vmap(lambda o, k: explore_action(config, run, memory, o, k))(obs, keys)
    return acts, _config_index(config, acts)


@functools.partial(_jit, static_argnames=("config",))
def _q_batch(memory: Memory, obs: jax.Array, actions: jax.Array, *, config: HedgerConfig):
    """Q(s, a) for obs (B, S), actions (B, A) -> (values (B,), known (B,), n_neighbours (B,))."""
    return jax.vmap(lambda o, a: _predict_q(config, memory, o, a))(obs, actions)


@functools.partial(_jit, static_argnames=("env", "config", "n_episodes", "max_steps"))
def _evaluate_jit(memory, key, env_params, *, env, config, n_episodes, max_steps):
    return evaluate(env, env_params, config, memory, key, n_episodes, max_steps)


_MIN_BUCKET, _MAX_BUCKET = 8, 256


def _bucket(n: int) -> int:
    """Padded batch size for n rows: the next power of two in [8, 256] (few compilations)."""
    b = _MIN_BUCKET
    while b < n and b < _MAX_BUCKET:
        b *= 2
    return b


def _bucketed(fn, *arrays: np.ndarray):
    """Apply a jitted batch function to rows (B, ...) in padded buckets of ``_bucket`` rows
    (chunks of at most 256), so that batch sizes share compiled code. fn returns a tuple of
    arrays with leading axis = the bucket; the result is the tuple of NumPy arrays (B, ...)."""
    n = arrays[0].shape[0]
    outs = []
    for start in range(0, n, _MAX_BUCKET):
        rows = [a[start:start + _MAX_BUCKET] for a in arrays]
        m = rows[0].shape[0]
        b = _bucket(m)
        padded = [np.concatenate([r, np.repeat(r[-1:], b - m, axis=0)]) if b > m else r
                  for r in rows]
        res = fn(*(jnp.asarray(p) for p in padded))
        outs.append([np.asarray(x)[:m] for x in res])
    return tuple(np.concatenate(parts) for parts in zip(*outs))


def _config_index(config: HedgerConfig, actions: jax.Array) -> jax.Array:
    if not config.is_discrete:
        return jnp.zeros(actions.shape[:-1], jnp.int32)
    table = jnp.asarray(config.discrete_actions, jnp.float32)              # (n, A)
    d = jnp.sum(jnp.abs(actions[..., None, :] - table), axis=-1)           # (B, n)
    return jnp.argmin(d, axis=-1).astype(jnp.int32)


# ------------------------------------------------------------------------------------------
class Hedger:
    """HEDGER learner with the Stable-Baselines3 surface.

    Args:
      env: one of
        * the project's JAX envs, run whole-episode inside jitted code: a Gymnasium id
          (``"HedgerMountainCar-v0"``, ``"HedgerMountainCarContinuous-v0"``,
          ``"HedgerCorridor-v0"``), an ``envs.make`` name, a ``gymnasium.Env`` whose
          ``unwrapped`` is the project's adapter (its functional env and params are used), or a
          functional env object (``envs.base``; it must be hashable, as it is a static jit
          argument);
        * any other Gymnasium env, by id (``"MountainCar-v0"``, ``"Pendulum-v1"``, ...; made
          with ``gymnasium.make(env, **env_kwargs)``) or as an instance, with a ``Box``
          observation space of shape (S,) and a ``Discrete`` or ``Box`` (1,) action space. It
          runs in a host loop (``hedger_jax.environments``): a ``Discrete(n)`` space gives
          HEDGER the action values (0,), ..., (n-1,); a Box the interval [low, high] scaled to
          a width of 0.2 (unless ``action_scale`` is given); observations are scaled to [0, 1]
          from the Box bounds, an unbounded dimension from 2,000 random-action steps of a
          seeded copy of the env (``envs.scaling``). Other spaces raise ``ValueError``.
      config: a ``HedgerConfig``; default ``HedgerConfig.for_env(env, **ENV_PRESETS[...])``.
      run_config: a ``RunConfig`` (epsilon, exploration, evaluation protocol); default
        ``RunConfig(**ENV_PRESETS[...]["run"])`` (for a host-loop env with
        ``eval_episodes=HOST_EVAL_EPISODES`` and ``eval_max_steps`` the env's time limit).
      seed: the learner's PRNG seed (``jax.random.PRNGKey(seed)``).
      env_params: the env's params pytree (default ``env.default_params()``; none for a
        host-loop env).
      env_kwargs: keyword arguments for ``envs.make`` / ``gymnasium.make`` when ``env`` is an
        id or name.
      chunk_episodes: phase-two episodes per jitted call of ``learn`` (progress and callback
        granularity; the host loop calls the callback after as many episodes).
      **overrides: ``HedgerConfig`` fields (and ``action_scale`` when ``config`` is None),
        e.g. ``capacity=512``.

    Attributes: ``env`` (the functional env, or the ``environments.GymnasiumEnv`` whose
    ``gym_env`` is the Gymnasium env), ``env_id``, ``env_params``, ``config``, ``run_config``,
    ``memory``, ``key`` (raw uint32 (2,)), ``seed``, ``num_timesteps`` (phase-two env steps),
    ``num_demo_timesteps`` (phase-one training points), ``num_episodes`` (phase two),
    ``ep_info_buffer`` (list of {"r": return, "l": length} of the last 100 training episodes),
    ``host_loop`` (whether the env runs in the host loop).
    """

    def __init__(self, env: Any, config: Optional[HedgerConfig] = None,
                 run_config: Optional[RunConfig] = None, *, seed: int = 0,
                 env_params: Any = None, env_kwargs: Optional[Dict[str, Any]] = None,
                 chunk_episodes: int = 10, **overrides: Any):
        self.env_kwargs = dict(env_kwargs or {})
        resolved = _envs.resolve_env(env, self.env_kwargs)
        self.env, self._env_name, self.env_id = resolved.env, resolved.name, resolved.env_id
        self._from_instance = resolved.from_instance
        self.host_loop = isinstance(self.env, GymnasiumEnv)
        if self.host_loop:
            if env_params is not None:
                raise ValueError("env_params: a Gymnasium env run by the host loop has no "
                                 "params pytree")
        else:
            try:
                hash(self.env)
            except TypeError:
                raise TypeError(f"env: must be hashable (a static jit argument); "
                                f"{type(self.env).__name__} is not") from None
        if env_params is None:
            env_params = (self.env.default_params() if resolved.params is None
                          else resolved.params)
        self.env_params = env_params
        preset = ENV_PRESETS.get(self._env_name, {"hedger": {}, "run": {}})
        if config is None:
            kwargs = dict(preset["hedger"])
            if self.host_loop:
                kwargs.setdefault("action_scale", self.env.default_action_scale)
            kwargs.update(overrides)
            config = HedgerConfig.for_env(self.env, self.env_params, **kwargs)
        else:
            if not isinstance(config, HedgerConfig):
                raise TypeError(f"config: expected a HedgerConfig, got {type(config).__name__}")
            if "action_scale" in overrides:
                raise ValueError("action_scale: only applies when config is None "
                                 "(set input_scale in the HedgerConfig instead)")
            if overrides:
                config = config.replace(**overrides)
        self.config = config
        if run_config is None:
            run_kwargs = dict(preset["run"])
            if self.host_loop:
                run_kwargs.setdefault("eval_episodes", HOST_EVAL_EPISODES)
                run_kwargs.setdefault("eval_max_steps", self.env.max_steps)
            run_config = RunConfig(**run_kwargs)
        if not isinstance(run_config, RunConfig):
            raise TypeError(f"run_config: expected a RunConfig, got {type(run_config).__name__}")
        self.run_config = run_config
        if isinstance(seed, bool) or int(seed) != seed:
            raise ValueError(f"seed: must be an integer, got {seed!r}")
        self.seed = int(seed)
        if int(chunk_episodes) < 1:
            raise ValueError(f"chunk_episodes: must be >= 1, got {chunk_episodes}")
        self.chunk_episodes = int(chunk_episodes)
        self._env_index = self._check_env_config()
        self._action_start = self.env.action_start if self.host_loop else 0
        self._buffer: Optional[_envs.EpisodeBuffer] = None
        self.memory = init_memory(config)
        self.key = jax.random.PRNGKey(self.seed)
        self.num_timesteps = 0
        self.num_demo_timesteps = 0
        self.num_episodes = 0
        self.ep_info_buffer: list = []

    # -------------------------------------------------------------------------- helpers
    def _check_env_config(self) -> Optional[np.ndarray]:
        """Check config vs env; return config-index -> env Discrete-index table (discrete)."""
        cfg, space = self.config, self.env.action_space
        if cfg.state_dim != int(self.env.obs_dim):
            raise ValueError(f"config.state_dim {cfg.state_dim} != env obs_dim {self.env.obs_dim}")
        if cfg.action_dim != space.action_dim:
            raise ValueError(f"config.action_dim {cfg.action_dim} != env action_dim "
                             f"{space.action_dim}")
        if cfg.is_discrete != space.is_discrete:
            raise ValueError(f"config is {'discrete' if cfg.is_discrete else 'continuous'} but "
                             f"the env's action space is "
                             f"{'discrete' if space.is_discrete else 'continuous'}")
        if not cfg.is_discrete:
            return None
        env_vals = space.values_array().astype(np.float64)
        table = []
        for a in cfg.discrete_actions:
            match = np.flatnonzero(np.all(np.isclose(env_vals, a, rtol=0, atol=1e-6), axis=1))
            if match.size == 0:
                raise ValueError(f"config.discrete_actions: {a} is not an action of the env "
                                 f"({space.values})")
            table.append(int(match[0]))
        return np.asarray(table, np.int64)

    def _next_key(self) -> jax.Array:
        self.key, sub = jax.random.split(self.key)
        return sub

    def _max_steps(self) -> int:
        return int(self.run_config.train_max_steps or self.env.max_steps)

    @staticmethod
    def _progress(total: int, enabled: bool, desc: str):
        if not enabled:
            return None
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit="step")

    # -------------------------------------------------------------------------- phase two
    def learn(self, total_timesteps: int, progress_bar: bool = False,
              callback: Optional[Callable[[Dict[str, Any]], Any]] = None,
              reset_num_timesteps: bool = False) -> "Hedger":
        """Phase two: the epsilon-greedy policy is in control for ``total_timesteps`` more env
        steps (whole episodes: the last one may overshoot by less than an episode), training
        by reverse replay after every episode.

        callback: called after every chunk with a dict (``num_timesteps``, ``num_episodes``,
        ``memory_size``, ``lengths``, ``returns``); returning ``False`` stops learning.
        reset_num_timesteps: as in SB3, restart the ``num_timesteps`` counter at 0.
        Raises ``NonFiniteValueError`` / ``MemoryFullError`` from ``memory_check`` after the
        chunk in which the memory flagged it. Returns ``self``.
        """
        if isinstance(total_timesteps, bool) or int(total_timesteps) != total_timesteps \
                or total_timesteps < 0:
            raise InvalidInputError(f"total_timesteps: must be an integer >= 0, "
                                    f"got {total_timesteps!r}")
        total = int(total_timesteps)
        if reset_num_timesteps:
            self.num_timesteps = 0
        memory_check(self.memory)
        if self.host_loop:
            return self._learn_host(total, progress_bar, callback)
        bar = self._progress(total, progress_bar, "HEDGER learn")
        done = 0
        try:
            while done < total:
                budget = jnp.asarray(min(total - done, 2**31 - 1), jnp.int32)
                (self.memory, self.key, steps, n_ep, lengths,
                 returns) = _learn_chunk(self.memory, self.key, self.env_params, budget,
                                         env=self.env, config=self.config, run=self.run_config,
                                         max_steps=self._max_steps(),
                                         max_episodes=self.chunk_episodes)
                steps, n_ep = int(steps), int(n_ep)
                lengths, returns = np.asarray(lengths)[:n_ep], np.asarray(returns)[:n_ep]
                done += steps
                self.num_timesteps += steps
                self.num_episodes += n_ep
                self._record_episodes(lengths, returns)
                if bar is not None:
                    bar.update(min(steps, total - bar.n))
                memory_check(self.memory)
                if callback is not None and callback(
                        dict(num_timesteps=self.num_timesteps, num_episodes=self.num_episodes,
                             memory_size=int(self.memory.size), lengths=lengths,
                             returns=returns)) is False:
                    break
        finally:
            if bar is not None:
                bar.close()
        return self

    def _record_episodes(self, lengths: np.ndarray, returns: np.ndarray) -> None:
        self.ep_info_buffer.extend({"r": float(r), "l": int(n)}
                                   for r, n in zip(returns, lengths))
        del self.ep_info_buffer[:-100]

    def _learn_host(self, total: int, progress_bar: bool, callback) -> "Hedger":
        """``learn`` for a Gymnasium env: episodes on the host (``environments.run_episode``,
        one jitted epsilon-greedy action per step), each replayed in reverse by one jitted
        call on the episode padded to the cap (``environments.replay_episode``)."""
        cap = self._max_steps()
        if self._buffer is None or self._buffer.length != cap:
            self._buffer = _envs.EpisodeBuffer(cap, self.config.state_dim,
                                               self.config.action_dim)
        buf, cfg, run = self._buffer, self.config, self.run_config
        self.memory = _envs.refresh(self.memory, config=cfg)   # after demonstrations or load
        bar = self._progress(total, progress_bar, "HEDGER learn")
        done, lengths, returns = 0, [], []
        try:
            while done < total:
                k_env, k_act = jax.random.split(self._next_key())
                memory = self.memory
                ep = _envs.run_episode(
                    self.env, lambda obs, t: _envs.explore_step(memory, obs, k_act, t,
                                                                config=cfg, run=run),
                    _envs.seed_from_key(k_env), cap, buf)
                self.memory = _envs.replay_episode(self.memory, buf.transition(ep.length),
                                                   jnp.int32(ep.length), config=cfg)
                done += ep.length
                self.num_timesteps += ep.length
                self.num_episodes += 1
                lengths.append(ep.length)
                returns.append(ep.ret)
                if bar is not None:
                    bar.update(min(ep.length, total - bar.n))
                # Waits for the replay, so the next episode may overwrite the NumPy buffer.
                memory_check(self.memory)
                if len(lengths) == self.chunk_episodes or done >= total:
                    lengths_a = np.asarray(lengths, np.int32)
                    returns_a = np.asarray(returns, np.float32)
                    self._record_episodes(lengths_a, returns_a)
                    lengths, returns = [], []
                    if callback is not None and callback(
                            dict(num_timesteps=self.num_timesteps,
                                 num_episodes=self.num_episodes,
                                 memory_size=int(self.memory.size), lengths=lengths_a,
                                 returns=returns_a)) is False:
                        break
        finally:
            if lengths:
                self._record_episodes(np.asarray(lengths), np.asarray(returns))
            if bar is not None:
                bar.close()
        return self

    # -------------------------------------------------------------------------- phase one
    def learn_from_demonstrations(self, source: Any, n_episodes: Optional[int] = None, *,
                                  max_steps: int = 1000, start: Any = None,
                                  check_env_id: bool = True,
                                  progress_bar: bool = False) -> "Hedger":
        """Phase one: learn passively from an example policy's experience.

        source:
          * a path to a demonstrations file (``envs.demonstrations.load_demonstrations``);
          * an ``envs.demonstrations.Demonstrations`` (or a ``Transition`` batch with leading
            axes (E, T), valid steps a prefix of each episode): every episode is replayed in
            reverse (``transitions_from_demonstrations`` then ``train_prefix``); ``n_episodes``
            (optional) uses the first ones only;
          * a policy with pure ``init(key) -> pstate`` and ``act(key, obs, pstate) -> (action
            value (A,), pstate)`` (e.g. ``envs.demonstrators.Policy``): it drives
            ``n_episodes`` episodes (required) of at most ``max_steps`` from ``env.reset`` or
            ``env.reset_to(start)``, each replayed in reverse after it ends.
        check_env_id: refuse demonstrations recorded for another env (their ``env_id`` vs the
          functional env's ``name``).
        Inputs are validated (shapes, NaN/inf, actions in the set / bounds). Returns ``self``.
        """
        if hasattr(source, "act") and hasattr(source, "init") and not hasattr(source, "obs"):
            return self._learn_from_policy(source, n_episodes, max_steps, start, progress_bar)
        if isinstance(source, (str, os.PathLike)):
            from envs.demonstrations import load_demonstrations

            source = load_demonstrations(source, obs_dim=self.config.state_dim,
                                         action_dim=self.config.action_dim)
        demo_env = getattr(source, "env_id", None)
        if check_env_id and demo_env is not None and self._env_name is not None \
                and demo_env != self._env_name:
            raise InvalidInputError(f"demonstrations: recorded for env {demo_env!r}, this "
                                    f"learner's env is {self._env_name!r} (pass "
                                    "check_env_id=False to use them anyway)")
        tr = check_transitions(self.config, source, "demonstrations")
        if tr.reward.ndim == 1:                                  # one episode (T,)
            tr = jax.tree_util.tree_map(lambda x: x[None], tr)
        if tr.reward.ndim != 2:
            raise InvalidInputError(f"demonstrations: expected leading axes (episodes, steps), "
                                    f"got reward shape {tr.reward.shape}")
        E = tr.reward.shape[0]
        if n_episodes is not None:
            if int(n_episodes) < 1 or int(n_episodes) > E:
                raise InvalidInputError(f"n_episodes: must be in [1, {E}], got {n_episodes}")
            E = int(n_episodes)
        episodes = transitions_from_demonstrations(tr)
        lengths = np.asarray(tr.valid).sum(axis=1)
        bar = self._progress(int(lengths[:E].sum()), progress_bar, "HEDGER demonstrations")
        try:
            for e in range(E):
                ep = jax.tree_util.tree_map(lambda x: x[e], episodes)
                self.memory = _train_prefix_jit(self.memory, ep, jnp.int32(lengths[e]),
                                                config=self.config)
                self.num_demo_timesteps += int(lengths[e])
                if bar is not None:
                    bar.update(int(lengths[e]))
                memory_check(self.memory)
        finally:
            if bar is not None:
                bar.close()
        return self

    def _learn_from_policy(self, policy, n_episodes, max_steps, start, progress_bar):
        if self.host_loop:
            raise InvalidInputError("a policy in control needs one of the project's JAX envs; "
                                    f"{self.env_id or self.env.name!r} runs in the host loop: "
                                    "pass recorded demonstrations instead")
        if n_episodes is None or isinstance(n_episodes, bool) or int(n_episodes) < 1:
            raise InvalidInputError(f"n_episodes: a policy needs n_episodes >= 1, got "
                                    f"{n_episodes!r}")
        if int(max_steps) < 1:
            raise InvalidInputError(f"max_steps: must be >= 1, got {max_steps}")
        has_start = start is not None
        if has_start:
            if not hasattr(self.env, "reset_to"):
                raise InvalidInputError("start: the env has no reset_to")
            start = jnp.asarray(np.asarray(start, np.float32))
            if not np.all(np.isfinite(np.asarray(start))):
                raise InvalidInputError(f"start: contains NaN or inf: {np.asarray(start)}")
        else:
            start = jnp.zeros((), jnp.float32)
        bar = self._progress(int(n_episodes), progress_bar, "HEDGER demonstrations (episodes)")
        try:
            for _ in range(int(n_episodes)):
                self.memory, length = _policy_episode(
                    self.memory, self._next_key(), self.env_params, start, env=self.env,
                    config=self.config, act=policy.act, init=policy.init,
                    max_steps=int(max_steps), has_start=has_start)
                self.num_demo_timesteps += int(length)
                if bar is not None:
                    bar.update(1)
                memory_check(self.memory)
        finally:
            if bar is not None:
                bar.close()
        return self

    # -------------------------------------------------------------------------- acting
    def _act(self, observation: Any, deterministic: bool, key: Any):
        obs, batched = check_observations(self.config, observation)
        if deterministic:
            k = jax.random.PRNGKey(0) if key is None else jnp.asarray(check_key(key))
            acts, idx = _bucketed(lambda o: _greedy_batch(self.memory, o, k,
                                                          config=self.config)[::3], obs)
        else:
            k = self._next_key() if key is None else jnp.asarray(check_key(key))
            keys = jax.random.split(k, -(-obs.shape[0] // _MAX_BUCKET))
            it = iter(keys)
            acts, idx = _bucketed(lambda o: _explore_batch(self.memory, o, next(it),
                                                           config=self.config,
                                                           run=self.run_config), obs)
        return acts, idx, batched

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True, key: Any = None) -> Tuple[np.ndarray, None]:
        """The action for an observation (S,) or a batch (B, S), SB3-style -> (action, None).

        The action is what the Gymnasium adapter's ``step`` expects: for a discrete env the
        ``Discrete`` index into the env's action values (int64, shape () or (B,)); for a
        continuous env the action vector (float32 (A,) or (B, A)). ``predict_action_value``
        gives the action values instead.

        Batches are evaluated in padded buckets (powers of two from 8 to 256 rows), so any
        batch size reuses a few compiled functions.

        deterministic=True (the default here, unlike SB3: HEDGER's policy *is* the greedy one)
        is the greedy action; ties and "don't know" states are resolved with a fixed key
        (``PRNGKey(0)``, or ``key``) shared by every row, so the action is a function of the
        observation (and the memory) only. deterministic=False is the epsilon-greedy training
        policy, drawing from the learner's key stream (or ``key``).
        ``state``/``episode_start`` are accepted for SB3 compatibility and ignored (HEDGER is
        not recurrent); the returned state is ``None``.
        """
        del state, episode_start
        acts, idx, batched = self._act(observation, deterministic, key)
        if self.config.is_discrete:
            out = self._env_index[idx] + self._action_start
        else:
            out = acts.astype(np.float32)
        return (out if batched else out[0]), None

    def predict_action_value(self, observation: Any, deterministic: bool = True,
                             key: Any = None) -> np.ndarray:
        """Like ``predict`` but the action *value* the functional env's ``step`` takes:
        float32 (A,) for one observation, (B, A) for a batch."""
        acts, _, batched = self._act(observation, deterministic, key)
        return acts if batched else acts[0]

    def action_value(self, action: Any) -> np.ndarray:
        """Gymnasium action (a Discrete index for a discrete env) -> action value float32
        (..., A)."""
        if not self.config.is_discrete:
            return check_actions(self.config, action)
        idx = np.asarray(action)
        if not np.issubdtype(idx.dtype, np.integer):
            raise InvalidInputError(f"action: a discrete env takes integer indices, got dtype "
                                    f"{idx.dtype}")
        idx = idx - self._action_start
        values = self.env.action_space.values_array()
        if np.any((idx < 0) | (idx >= len(values))):
            raise InvalidInputError(f"action: index out of range [0, {len(values)}): {idx}")
        return values[idx]

    def q_value(self, observation: Any, action_value: Any):
        """Q(s, a) from the memory (Algorithm 1): observation (S,) or (B, S), action values
        (A,) or (B, A) -> (value float32, known bool), scalars or (B,)."""
        obs, batched = check_observations(self.config, observation)
        acts = check_actions(self.config, action_value, "action_value")
        want = (obs.shape[0], self.config.action_dim)
        if acts.shape != (want if batched else want[1:]):
            raise InvalidInputError(f"action_value: expected shape "
                                    f"{want if batched else want[1:]}, got {acts.shape}")
        acts = acts.reshape(want)
        vals, known = _bucketed(lambda o, a: _q_batch(self.memory, o, a,
                                                      config=self.config)[:2], obs, acts)
        return (vals, known) if batched else (vals[0], known[0])

    # -------------------------------------------------------------------------- evaluation
    def evaluate(self, n_episodes: Optional[int] = None, *, max_steps: Optional[int] = None,
                 key: Any = None) -> Dict[str, float]:
        """The greedy policy, learning off.

        n_episodes / max_steps: default ``run_config.eval_episodes`` / ``eval_max_steps``.
        key: default ``fold_in(PRNGKey(seed), 1)``: every call without a key uses the same
        evaluation starts (common random numbers across calls).

        A JAX env (``agent.evaluate``, episodes vmapped): returns ``{"mean_steps": float,
        "success_rate": float}``, the mean steps to the goal (failures count ``max_steps``).

        A host-loop Gymnasium env: ``n_episodes`` greedy episodes on the host, each reset with
        a seed drawn from ``key`` and run until Gymnasium's ``terminated`` or ``truncated`` or
        ``max_steps`` steps. Returns ``{"mean_steps": mean episode length, "mean_return":
        mean undiscounted return, "success_rate": fraction of episodes that *terminated*
        (not truncated)}`` -- for an env whose termination is a failure (CartPole's pole
        falling) that is the failure rate, and for one that never terminates (Pendulum) 0.
        """
        n = int(self.run_config.eval_episodes if n_episodes is None else n_episodes)
        m = int(self.run_config.eval_max_steps if max_steps is None else max_steps)
        if n < 1 or m < 1:
            raise InvalidInputError(f"n_episodes and max_steps must be >= 1, got {n}, {m}")
        k = (jax.random.fold_in(jax.random.PRNGKey(self.seed), 1) if key is None
             else jnp.asarray(check_key(key)))
        if self.host_loop:
            return self._evaluate_host(n, m, k)
        ev: Evaluation = _evaluate_jit(self.memory, k, self.env_params, env=self.env,
                                       config=self.config, n_episodes=n, max_steps=m)
        return {"mean_steps": float(ev.mean_steps), "success_rate": float(ev.success_rate)}

    def _evaluate_host(self, n: int, max_steps: int, key: jax.Array) -> Dict[str, float]:
        """``evaluate`` for a host-loop env: n greedy episodes of at most max_steps."""
        cfg = self.config
        memory = _envs.refresh(self.memory, config=cfg)
        keys = np.asarray(jax.random.split(key, n))
        results = []
        for k in keys:
            k_env, k_act = jax.random.split(jnp.asarray(k))
            results.append(_envs.run_episode(
                self.env, lambda obs, t: _envs.greedy_step(memory, obs, k_act, t, config=cfg),
                _envs.seed_from_key(k_env), max_steps))
        return {"mean_steps": float(np.mean([r.length for r in results])),
                "mean_return": float(np.mean([r.ret for r in results])),
                "success_rate": float(np.mean([r.terminated for r in results]))}

    # -------------------------------------------------------------------------- persistence
    def save(self, path: Union[str, os.PathLike]) -> str:
        """Save config, run config, memory, key, counters and env params to one file
        (``hedger_jax.checkpoint``: atomic, checksummed), with the env's id (a Gymnasium id
        for a host-loop env) for ``load``. Returns the path."""
        leaves = jax.tree_util.tree_leaves(self.env_params)
        extra = {"key": np.asarray(self.key),
                 "counters": np.asarray([self.num_timesteps, self.num_demo_timesteps,
                                         self.num_episodes], np.int64)}
        for i, leaf in enumerate(leaves):
            extra[f"env_params/{i}"] = np.asarray(leaf)
        meta = {"env_name": self._env_name, "env_kwargs": self.env_kwargs,
                "env_max_steps": int(self.env.max_steps), "chunk_episodes": self.chunk_episodes,
                "n_env_params": len(leaves), "host_loop": self.host_loop,
                "env_from_instance": self._from_instance}
        return save_checkpoint(path, self.config, self.memory, self.run_config, seed=self.seed,
                               env_id=self.env_id, extra_arrays=extra, metadata=meta)

    @classmethod
    def load(cls, path: Union[str, os.PathLike], env: Any = None, *, env_params: Any = None,
             config: Optional[HedgerConfig] = None) -> "Hedger":
        """Load a learner saved by ``save``.

        env: default: rebuilt from the stored env id (and ``env_kwargs``): ``envs.make`` for
        the project's envs, ``gymnasium.make`` for a Gymnasium id. Pass the env (object, or
        Gymnasium instance) when the learner was built from an env object: a Gymnasium
        instance may carry wrappers or settings its id does not. env_params: default the
        stored ones. config: when given, a file with a different config is refused
        (``CheckpointError`` naming the differing fields).
        """
        from hedger_jax.checkpoint import CheckpointError

        ck = load_checkpoint(path, config=config)
        meta = ck.metadata
        if env is None:
            env_id = meta.get("env_id")
            if meta.get("host_loop") and meta.get("env_from_instance"):
                raise CheckpointError(f"checkpoint {os.fspath(path)!r}: the learner was built "
                                      f"from a Gymnasium env instance ({env_id or 'no id'}); "
                                      "pass env= (an env like it) to load it")
            if env_id is None:
                raise CheckpointError(f"checkpoint {os.fspath(path)!r}: no env id stored; pass "
                                      "env=")
            env = env_id
        kwargs = dict(meta.get("env_kwargs") or {}) if isinstance(env, str) else {}
        if isinstance(env, str) and _envs.is_functional_name(env) and "max_steps" not in kwargs:
            kwargs["max_steps"] = meta.get("env_max_steps")
            if kwargs["max_steps"] is None:
                del kwargs["max_steps"]
        model = cls(env, ck.config, ck.run_config, seed=meta.get("seed") or 0,
                    env_kwargs=kwargs if isinstance(env, str) else None,
                    chunk_episodes=int(meta.get("chunk_episodes", 10)),
                    env_params=env_params)
        if isinstance(env, str):
            model.env_kwargs = dict(meta.get("env_kwargs") or {})
        if env_params is None:
            n = int(meta.get("n_env_params", 0))
            leaves, treedef = jax.tree_util.tree_flatten(model.env_params)
            stored = [ck.extra_arrays.get(f"env_params/{i}") for i in range(n)]
            if n == len(leaves) and all(s is not None and np.shape(s) == np.shape(l)
                                        for s, l in zip(stored, leaves)):
                model.env_params = jax.tree_util.tree_unflatten(
                    treedef, [jnp.asarray(s) for s in stored])
            elif n:
                raise CheckpointError(f"checkpoint {os.fspath(path)!r}: the stored env params "
                                      f"({n} leaves) do not fit the env's params "
                                      f"({len(leaves)} leaves); pass env_params=")
        model.memory = ck.memory
        if "key" in ck.extra_arrays:
            model.key = jnp.asarray(check_key(ck.extra_arrays["key"], "stored key"))
        if "counters" in ck.extra_arrays:
            c = [int(x) for x in ck.extra_arrays["counters"]]
            model.num_timesteps, model.num_demo_timesteps, model.num_episodes = c
        return model

    def __repr__(self) -> str:
        return (f"Hedger(env={self.env_id!r}, capacity={self.config.capacity}, "
                f"memory_size={int(self.memory.size)}, num_timesteps={self.num_timesteps})")
