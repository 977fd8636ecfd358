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
(``hedger_jax.host_loop``; ``hedger_jax.environments`` states how its actions and observations
are scaled).

Actions. The functional envs take action *values* (e.g. -1.0, 0.0, +1.0 for mountain car);
the Gymnasium adapter (``envs.gym_adapter``) takes a ``Discrete`` *index* for a discrete env
and the value vector for a continuous one. ``predict`` returns what the Gymnasium env
expects (SB3 semantics, so a SB3-style ``evaluate_policy(model, gym_env)`` loop works);
``predict_action_value`` returns the action values.

``Hedger`` is a thin shell; each of its jobs is a module of its own: ``learner_setup`` (the
env, its preset from ``presets``, the checked configs), ``phase_one`` (demonstrations),
``jax_loop`` and ``host_loop`` (phase two and evaluation on the project's JAX envs and on any
other Gymnasium env), ``batching`` (SB3-style ``predict`` and ``q_value``), ``progress``
(counters, progress bar, callbacks) and ``persistence`` (``save``/``load``).
"""
from __future__ import annotations

import os
from typing import Any, Callable, Dict, Optional, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax import (batching, host_loop, jax_loop, learner_setup, persistence, phase_one,
                        progress)
from hedger_jax.agent import RunConfig
from hedger_jax.config import HedgerConfig
from hedger_jax.environments import GYM_IDS, make_env  # noqa: F401 (re-exported)
from hedger_jax.memory import Memory, init_memory, memory_check
from hedger_jax.presets import ENV_PRESETS, HOST_EVAL_EPISODES  # noqa: F401 (re-exported)
from hedger_jax.validation import InvalidInputError, check_actions, check_key

__all__ = ["Hedger", "make_env", "GYM_IDS", "ENV_PRESETS", "HOST_EVAL_EPISODES"]


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
          runs in a host loop (``hedger_jax.host_loop``; ``hedger_jax.environments`` states
          how its actions and observations are scaled). Other spaces raise ``ValueError``.
      config: a ``HedgerConfig``; default ``HedgerConfig.for_env`` with the env's preset
        (``ENV_PRESETS``, ``hedger_jax.presets``: its ``hedger`` settings, then its
        ``state_scale_factors`` on the observation scaling).
      run_config: a ``RunConfig``, or a dict of fields overriding the default (e.g.
        ``{"exploration": "random"}``); default ``RunConfig(**ENV_PRESETS[...]["run"])``
        (a host-loop env: ``eval_episodes=HOST_EVAL_EPISODES``, ``eval_max_steps`` its limit).
      seed: the learner's PRNG seed (``jax.random.PRNGKey(seed)``).
      env_params: the env's params pytree (default ``env.default_params()`` with the preset's
        ``env_params`` overrides; none for a host-loop env).
      env_kwargs: keyword arguments for ``envs.make`` / ``gymnasium.make`` when ``env`` is an
        id or name.
      preset: where ``config``'s and ``run_config``'s defaults come from: "auto" (the
        project's JAX envs: ``ENV_PRESETS``; other Gymnasium envs: "task"), "task" (read
        from the task, ``hedger_jax.task_settings``) or "paper" (the paper's algorithm:
        ``HedgerConfig``'s and ``RunConfig``'s own defaults).
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
                 run_config: Union[RunConfig, Dict[str, Any], None] = None, *, seed: int = 0,
                 env_params: Any = None, env_kwargs: Optional[Dict[str, Any]] = None,
                 chunk_episodes: int = 10, preset: str = "auto", **overrides: Any):
        self.env_kwargs = dict(env_kwargs or {})
        s = learner_setup.build(env, config, run_config, seed=seed, env_params=env_params,
                                env_kwargs=self.env_kwargs, chunk_episodes=chunk_episodes,
                                overrides=overrides, preset_name=preset)
        self.env, self._env_name, self.env_id = s.env, s.name, s.env_id
        self._from_instance, self.host_loop = s.from_instance, s.host_loop
        self.env_params, self.config, self.run_config = s.env_params, s.config, s.run_config
        self.seed, self.chunk_episodes = s.seed, s.chunk_episodes
        self._actions = s.actions
        self._buffer: Optional[host_loop.EpisodeBuffer] = None     # reused by the host loop
        self.memory: Memory = init_memory(self.config)
        self.key = jax.random.PRNGKey(self.seed)
        self.num_timesteps = 0
        self.num_demo_timesteps = 0
        self.num_episodes = 0
        self.ep_info_buffer: list = []

    def _next_key(self) -> jax.Array:
        """A fresh key from the learner's stream (``key`` advances)."""
        self.key, sub = jax.random.split(self.key)
        return sub

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
        total, cfg, run = int(total_timesteps), self.config, self.run_config
        if reset_num_timesteps:
            self.num_timesteps = 0
        memory_check(self.memory)
        cap = int(run.train_max_steps or self.env.max_steps)
        if self.host_loop:
            self._buffer = host_loop.episode_buffer(self._buffer, cap, cfg)
            self.memory = host_loop.refresh(self.memory, config=cfg)  # after demos or load
            chunks = host_loop.training_episodes(self.memory, self._next_key, self.env,
                                                 self._buffer, config=cfg, run=run, total=total)
        else:
            chunks = jax_loop.training_chunks(self.memory, self.key, self.env, self.env_params,
                                              config=cfg, run=run, total=total, max_steps=cap,
                                              max_episodes=self.chunk_episodes)
        progress.follow_phase_two(self, chunks, total, progress_bar, callback)
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
            ``env.reset_to(start)``, each replayed in reverse after it ends;
          * on a host-loop Gymnasium env, any callable obs -> the env's action (e.g.
            ``experiments.hand_policies``), for ``n_episodes`` episodes, likewise.
        check_env_id: refuse demonstrations recorded for another env than this one.
        Inputs are validated (shapes, NaN/inf, actions in the set / bounds). Returns self.
        """
        if self.host_loop and phase_one.is_host_policy(source):
            cap = min(int(max_steps), int(self.run_config.train_max_steps or self.env.max_steps))
            self._buffer = host_loop.episode_buffer(self._buffer, cap, self.config)
            steps = phase_one.host_policy_episodes(
                self.memory, self._next_key, self.env, self._buffer, source, self.action_value,
                config=self.config, n_episodes=n_episodes)
            progress.follow_phase_one(self, steps, int(n_episodes), progress_bar,
                                      "HEDGER demonstrations (episodes)", count_episodes=True)
            return self
        if phase_one.is_policy(source):
            start, has_start = phase_one.check_policy_run(self.env, self.host_loop, n_episodes,
                                                          max_steps, start)
            steps = phase_one.policy_episodes(
                self.memory, self._next_key, self.env, self.env_params, source, start,
                config=self.config, n_episodes=int(n_episodes), max_steps=int(max_steps),
                has_start=has_start)
            progress.follow_phase_one(self, steps, int(n_episodes), progress_bar,
                                      "HEDGER demonstrations (episodes)", count_episodes=True)
            return self
        episodes, lengths = phase_one.demonstration_episodes(self.config, source, n_episodes,
                                                             self._env_name, check_env_id)
        steps = phase_one.replay_demonstrations(self.memory, episodes, lengths,
                                                config=self.config)
        progress.follow_phase_one(self, steps, int(lengths.sum()), progress_bar,
                                  "HEDGER demonstrations", count_episodes=False)
        return self

    # -------------------------------------------------------------------------- acting
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
        acts, idx, batched = batching.act(self.memory, observation, key, self._next_key,
                                          config=self.config, run=self.run_config,
                                          deterministic=deterministic)
        out = self._actions.env_actions(acts, idx)
        return (out if batched else out[0]), None

    def predict_action_value(self, observation: Any, deterministic: bool = True,
                             key: Any = None) -> np.ndarray:
        """Like ``predict`` but the action *value* the functional env's ``step`` takes:
        float32 (A,) for one observation, (B, A) for a batch."""
        acts, _, batched = batching.act(self.memory, observation, key, self._next_key,
                                        config=self.config, run=self.run_config,
                                        deterministic=deterministic)
        return acts if batched else acts[0]

    def action_value(self, action: Any) -> np.ndarray:
        """Gymnasium action (a Discrete index for a discrete env) -> action value float32
        (..., A)."""
        if not self.config.is_discrete:
            return check_actions(self.config, action)
        return self._actions.action_values(action)

    def q_value(self, observation: Any, action_value: Any):
        """Q(s, a) from the memory (Algorithm 1): observation (S,) or (B, S), action values
        (A,) or (B, A) -> (value float32, known bool), scalars or (B,)."""
        return batching.q_value(self.memory, observation, action_value, config=self.config)

    # -------------------------------------------------------------------------- evaluation
    def evaluate(self, n_episodes: Optional[int] = None, *, max_steps: Optional[int] = None,
                 key: Any = None) -> Dict[str, float]:
        """The greedy policy, learning off.

        n_episodes / max_steps: default ``run_config.eval_episodes`` / ``eval_max_steps``;
        key: default ``fold_in(PRNGKey(seed), 1)`` (the same starts on every call).

        A JAX env (``agent.evaluate``, episodes vmapped): ``{"mean_steps", "success_rate"}``,
        the mean steps to the goal (failures count ``max_steps``). A host-loop Gymnasium env
        (``host_loop.evaluate_greedy``): ``{"mean_steps", "mean_return", "terminated_rate"}``
        and, where termination is the goal (``environments.GOAL_TASKS``), "success_rate".
        """
        n = int(self.run_config.eval_episodes if n_episodes is None else n_episodes)
        m = int(self.run_config.eval_max_steps if max_steps is None else max_steps)
        if n < 1 or m < 1:
            raise InvalidInputError(f"n_episodes and max_steps must be >= 1, got {n}, {m}")
        k = (jax.random.fold_in(jax.random.PRNGKey(self.seed), 1) if key is None
             else jnp.asarray(check_key(key)))
        if self.host_loop:
            return host_loop.evaluate_greedy(self.memory, k, self.env, config=self.config,
                                             n_episodes=n, max_steps=m)
        return jax_loop.evaluate_greedy(self.memory, k, self.env, self.env_params,
                                        config=self.config, n_episodes=n, max_steps=m)

    # -------------------------------------------------------------------------- persistence
    def save(self, path: Union[str, os.PathLike]) -> str:
        """Save everything ``load`` needs to one file (``hedger_jax.persistence``) -> path."""
        return persistence.save(self, path)

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
        return persistence.load(cls, path, env, env_params=env_params, config=config)

    def __repr__(self) -> str:
        return (f"Hedger(env={self.env_id!r}, capacity={self.config.capacity}, "
                f"memory_size={int(self.memory.size)}, num_timesteps={self.num_timesteps})")
