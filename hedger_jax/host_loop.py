"""The host loop: ``Hedger`` on a Gymnasium env that is not one of the project's JAX envs.

Episodes run on the host (``run_episode``): one jitted epsilon-greedy action per step
(``explore_step``, through an episode's ``Explorer``), the episode's transitions in NumPy
buffers (``EpisodeBuffer``), and after the episode a jitted reverse replay of the buffer
padded to the episode cap (``replay_episode``: compiled once per config and cap) followed by
the neighbour index's refresh. A transition's ``terminated`` is Gymnasium's ``terminated`` only: a truncation (the
env's or the cap's) ends the episode but is never a terminal state.

The env is an ``environments.GymnasiumEnv`` (duck-typed here: ``gym_env``, ``gym_action``),
which states how its actions and observations are presented to HEDGER.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Dict, Iterator, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax import bursts
from hedger_jax.agent import RunConfig, explore_action, explore_action_burst, train_prefix
from hedger_jax.bursts import Burst
from hedger_jax.backup import BackupPlan, backup_plan, backup_sweeps
from hedger_jax.config import HedgerConfig
from hedger_jax.cpu import jit as _jit
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.greedy import greedy_action
from hedger_jax.memory import Memory, refresh_index
from hedger_jax.params import HedgerParams
from hedger_jax.progress import Chunk
from hedger_jax.train import Transition

__all__ = ["Backups", "EpisodeBuffer", "EpisodeResult", "Explorer", "run_episode", "explore_step",
           "greedy_step", "kernel_width", "Width", "replay_episode", "refresh", "seed_from_key",
           "episode_buffer", "training_episodes", "evaluate_greedy"]


# ------------------------------------------------------------------------------------------
# Jitted pieces (module level: compiled once per static settings)
# ------------------------------------------------------------------------------------------
class Width(NamedTuple):
    """A kernel width read from a memory's data: bandwidth (), k_thresh () its radius."""

    bandwidth: jax.Array
    k_thresh: jax.Array


def _step_key(key: jax.Array, t: jax.Array) -> jax.Array:
    """The acting key of step t of an episode keyed ``key`` (as ``agent.rollout`` derives it)."""
    return jax.random.fold_in(jax.random.fold_in(key, t), 0)


@functools.partial(_jit, static_argnames=("config",))
def kernel_width(memory: Memory, *, config: HedgerConfig) -> Optional[Width]:
    """The memory's kernel width (``data_bandwidth.with_data_bandwidth``), None where the
    config's is fixed. An episode reads it once and passes it to each step: the memory does
    not change while the episode acts, and the reading costs more than a step's search."""
    p = with_data_bandwidth(config, memory, None)
    return None if p is None else Width(p.bandwidth, p.k_thresh)


def _at_width(params: HedgerParams, width: Optional[Width]) -> Optional[HedgerParams]:
    """params at a width read by ``kernel_width`` (None: the config's own settings)."""
    if width is None:
        return None
    return params._replace(bandwidth=width.bandwidth, bandwidth_k=0, k_thresh=width.k_thresh)


@functools.partial(_jit, static_argnames=("config", "run"))
def explore_step(memory: Memory, obs: jax.Array, key: jax.Array, t: jax.Array,
                 width: Optional[Width] = None, burst: Optional[Burst] = None, *,
                 config: HedgerConfig, run: RunConfig):
    """The epsilon-greedy action value (A,) for obs (S,) at step t () of an episode keyed
    ``key`` (``agent.explore_action``); ``width``: the memory's ``kernel_width``, or None to
    read it here. With a ``burst`` (``exploration="bursts"``): -> (action, the next step's
    ``Burst``) (``agent.explore_action_burst``)."""
    params = _at_width(HedgerParams.defaults(config, run), width)
    if burst is None:
        return explore_action(config, run, memory, obs, _step_key(key, t), params=params)
    return explore_action_burst(config, run, memory, obs, _step_key(key, t), burst,
                                params=params)


class Explorer:
    """The phase-two policy of one episode, ``act(obs, t)`` for ``run_episode``:
    ``explore_step`` with the memory's width read once, and the episode's ``Burst`` carried
    from step to step under ``exploration="bursts"``."""

    def __init__(self, memory: Memory, key: jax.Array, *, config: HedgerConfig,
                 run: RunConfig):
        self.memory, self.key, self.config, self.run = memory, key, config, run
        self.width = kernel_width(memory, config=config)
        self.burst = bursts.start(config) if run.exploration == "bursts" else None

    def __call__(self, obs: np.ndarray, t: int) -> jax.Array:
        out = explore_step(self.memory, obs, self.key, t, self.width, self.burst,
                           config=self.config, run=self.run)
        if self.burst is None:
            return out
        action, self.burst = out
        return action


@functools.partial(_jit, static_argnames=("config",))
def greedy_step(memory: Memory, obs: jax.Array, key: jax.Array, t: jax.Array,
                width: Optional[Width] = None, *, config: HedgerConfig) -> jax.Array:
    """The greedy action value (A,) for obs (S,) at step t () of an episode keyed ``key``
    (ties and "don't know" resolved with that step's key); ``width`` as ``explore_step``'s."""
    params = _at_width(HedgerParams.defaults(config), width)
    return greedy_action(config, memory, obs, _step_key(key, t), params)[0]


@functools.partial(_jit, static_argnames=("config",), donate_argnames=("memory",))
def replay_episode(memory: Memory, episode: Transition, length: jax.Array, *,
                   config: HedgerConfig) -> Memory:
    """Reverse replay of an episode's first ``length`` () steps (leading axis T, the padded
    cap) then the neighbour index's refresh -> memory (the memory-wide backups are
    ``Backups``')."""
    return refresh_index(config, train_prefix(config, memory, episode, length, backup=False))


@functools.partial(_jit, static_argnames=("config",))
def _plan(memory: Memory, *, config: HedgerConfig) -> BackupPlan:
    return backup_plan(config, memory)


@functools.partial(_jit, static_argnames=("config",), donate_argnames=("memory",))
def _sweeps(memory: Memory, plan: BackupPlan, *, config: HedgerConfig) -> Memory:
    return backup_sweeps(config, memory, plan=plan)


class Backups:
    """The memory-wide backups after each episode (``HedgerConfig.backup_sweeps`` sweeps
    through a ``backup.BackupPlan``), the plan rebuilt once the env steps since it was built
    reach ``RunConfig.replan_fraction`` of the stored points (and before the first sweep)."""

    def __init__(self, config: HedgerConfig, run: RunConfig):
        self.config, self.fraction = config, float(run.replan_fraction)
        self.plan, self.since = None, 0

    def after_episode(self, memory: Memory, steps: int) -> Memory:
        """The memory after an episode of ``steps`` env steps, backed up (donated)."""
        if self.config.backup_sweeps == 0:
            return memory
        self.since += steps
        if self.plan is None or self.since >= self.fraction * int(memory.size):
            self.plan, self.since = _plan(memory, config=self.config), 0
        return _sweeps(memory, self.plan, config=self.config)


@functools.partial(_jit, static_argnames=("config",))
def refresh(memory: Memory, *, config: HedgerConfig) -> Memory:
    """The neighbour index brought up to date (``memory.refresh_index``)."""
    return refresh_index(config, memory)


def seed_from_key(key: Any) -> int:
    """A Gymnasium reset seed (an int in [0, 2**64)) from a raw PRNG key uint32 (2,)."""
    return int.from_bytes(np.asarray(key, np.uint32).astype("<u4").tobytes(), "little")


# ------------------------------------------------------------------------------------------
# Episodes on the host
# ------------------------------------------------------------------------------------------
class EpisodeBuffer:
    """NumPy buffers of one episode, padded to ``length`` steps (reused episode after
    episode): obs (T, S), action (T, A), reward (T,), next_obs (T, S), terminated (T,)."""

    def __init__(self, length: int, obs_dim: int, action_dim: int):
        self.length = int(length)
        self.obs = np.zeros((length, obs_dim), np.float32)
        self.action = np.zeros((length, action_dim), np.float32)
        self.reward = np.zeros((length,), np.float32)
        self.next_obs = np.zeros((length, obs_dim), np.float32)
        self.terminated = np.zeros((length,), bool)

    def transition(self, n: int) -> Transition:
        """The first n steps as a ``Transition`` of leading axis T (later steps invalid)."""
        return Transition(self.obs, self.action, self.reward, self.next_obs, self.terminated,
                          np.arange(self.length) < n)


def episode_buffer(buffer: Optional[EpisodeBuffer], cap: int,
                   config: HedgerConfig) -> EpisodeBuffer:
    """``buffer`` if it holds ``cap`` steps, else a new ``EpisodeBuffer`` for the config."""
    if buffer is not None and buffer.length == cap:
        return buffer
    return EpisodeBuffer(cap, config.state_dim, config.action_dim)


class EpisodeResult(NamedTuple):
    """length: steps taken; ret: sum of rewards; terminated: ended by Gymnasium's
    ``terminated`` (not by a truncation or the cap)."""

    length: int
    ret: float
    terminated: bool


def run_episode(env: Any, act: Callable[[np.ndarray, int], Any], seed: int,
                max_steps: int, buffer: Optional[EpisodeBuffer] = None) -> EpisodeResult:
    """One episode of a ``GymnasiumEnv`` on the host: ``env.reset(seed=seed)``, then
    ``act(obs float32 (S,), t) -> action value (A,)`` and ``env.step`` until terminated,
    truncated or ``max_steps`` steps. ``buffer`` (optional) receives the transitions;
    ``terminated`` there is Gymnasium's ``terminated`` only (a truncation is never a terminal
    state)."""
    gym_env = env.gym_env
    obs, _ = gym_env.reset(seed=seed)
    obs = np.asarray(obs, np.float32)
    total, t, terminated = 0.0, 0, False
    while t < max_steps:
        value = np.asarray(act(obs, t), np.float32)
        next_obs, reward, terminated, truncated, _ = gym_env.step(env.gym_action(value))
        next_obs = np.asarray(next_obs, np.float32)
        terminated = bool(terminated)
        if buffer is not None:
            buffer.obs[t], buffer.action[t], buffer.reward[t] = obs, value, reward
            buffer.next_obs[t], buffer.terminated[t] = next_obs, terminated
        total += float(reward)
        t += 1
        obs = next_obs
        if terminated or truncated:
            break
    return EpisodeResult(t, total, terminated)


# ------------------------------------------------------------------------------------------
# Phase two and evaluation
# ------------------------------------------------------------------------------------------
def training_episodes(memory: Memory, next_key: Callable[[], jax.Array], env: Any,
                      buffer: EpisodeBuffer, *, config: HedgerConfig, run: RunConfig,
                      total: int) -> Iterator[Chunk]:
    """Phase two: epsilon-greedy episodes of at most ``buffer.length`` steps, each replayed in
    reverse and then backed up memory-wide (``Backups``), until ``total`` env steps were
    taken. Each episode's key comes from
    ``next_key()`` (the learner's stream); ``memory`` is donated. Yields one ``Chunk`` per
    episode (``key`` None)."""
    done, backups = 0, Backups(config, run)
    while done < total:
        k_env, k_act = jax.random.split(next_key())
        ep = run_episode(env, Explorer(memory, k_act, config=config, run=run),
                         seed_from_key(k_env), buffer.length, buffer)
        memory = replay_episode(memory, buffer.transition(ep.length), jnp.int32(ep.length),
                                config=config)
        memory = backups.after_episode(memory, ep.length)
        # The replay reads the NumPy buffer, which the next episode overwrites.
        memory = jax.block_until_ready(memory)
        done += ep.length
        yield Chunk(memory, None, ep.length, np.asarray([ep.length], np.int32),
                    np.asarray([ep.ret], np.float32))


def evaluate_greedy(memory: Memory, key: jax.Array, env: Any, *, config: HedgerConfig,
                    n_episodes: int, max_steps: int) -> Dict[str, float]:
    """``n_episodes`` greedy episodes of at most ``max_steps``, learning off, each reset with a
    seed drawn from ``key`` -> {"mean_steps", "mean_return", "terminated_rate" (the fraction
    that *terminated*), and "success_rate" (the same fraction) only where termination is
    the task's goal (``env.goal_on_termination``)}."""
    memory = refresh(memory, config=config)
    width = kernel_width(memory, config=config)
    results = []
    for k in np.asarray(jax.random.split(key, n_episodes)):
        k_env, k_act = jax.random.split(jnp.asarray(k))
        results.append(run_episode(
            env, lambda obs, t: greedy_step(memory, obs, k_act, t, width, config=config),
            seed_from_key(k_env), max_steps))
    out = {"mean_steps": float(np.mean([r.length for r in results])),
           "mean_return": float(np.mean([r.ret for r in results])),
           "terminated_rate": float(np.mean([r.terminated for r in results]))}
    if getattr(env, "goal_on_termination", False):
        out["success_rate"] = out["terminated_rate"]
    return out
