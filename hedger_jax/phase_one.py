"""Phase one of ``Hedger``: learn passively from an example policy's experience, recorded
(demonstrations) or live (a policy in control of one of the project's JAX envs).

Each episode is replayed in reverse after it ends, by one jitted call; the generators here
yield the memory after every episode so that the learner checks it and shows progress.
"""
from __future__ import annotations

import functools
import os
from typing import Any, Callable, Iterator, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.agent import rollout, train_prefix, transitions_from_demonstrations
from hedger_jax.config import HedgerConfig
from hedger_jax.cpu import jit as _jit
from hedger_jax.memory import Memory
from hedger_jax.train import Transition
from hedger_jax.validation import InvalidInputError, check_transitions

__all__ = ["is_policy", "is_host_policy", "demonstration_episodes", "replay_demonstrations",
           "check_policy_run", "policy_episodes", "host_policy_episodes"]


def is_policy(source: Any) -> bool:
    """Whether ``source`` is a policy (pure ``init`` and ``act``), not recorded data."""
    return hasattr(source, "act") and hasattr(source, "init") and not hasattr(source, "obs")


def is_host_policy(source: Any) -> bool:
    """Whether ``source`` is a plain callable obs -> action (run by the host loop)."""
    return callable(source) and not is_policy(source) and not isinstance(source, type)


# ------------------------------------------------------------------------------------------
# Recorded demonstrations
# ------------------------------------------------------------------------------------------
def demonstration_episodes(config: HedgerConfig, source: Any, n_episodes: Optional[int],
                           env_name: Optional[str],
                           check_env_id: bool) -> Tuple[Transition, np.ndarray]:
    """Checked demonstrations -> (episodes: a ``Transition`` with leading axes (E, T), lengths
    int (E,)), the first ``n_episodes`` only when given.

    source: a path (``envs.demonstrations.load_demonstrations``), an
    ``envs.demonstrations.Demonstrations`` or a ``Transition`` batch (E, T) or (T,) whose
    valid steps are a prefix of each episode. check_env_id: refuse demonstrations recorded
    for another env than ``env_name``. Raises ``InvalidInputError``.
    """
    if isinstance(source, (str, os.PathLike)):
        from envs.demonstrations import load_demonstrations

        source = load_demonstrations(source, obs_dim=config.state_dim,
                                     action_dim=config.action_dim)
    demo_env = getattr(source, "env_id", None)
    if check_env_id and demo_env is not None and env_name is not None and demo_env != env_name:
        raise InvalidInputError(f"demonstrations: recorded for env {demo_env!r}, this "
                                f"learner's env is {env_name!r} (pass "
                                "check_env_id=False to use them anyway)")
    tr = check_transitions(config, source, "demonstrations")
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
    return jax.tree_util.tree_map(lambda x: x[:E], episodes), lengths[:E]


@functools.partial(_jit, static_argnames=("config",), donate_argnames=("memory",))
def _replay_recorded(memory: Memory, episode: Any, length: jax.Array, *, config: HedgerConfig):
    """Reverse replay of one recorded episode (leading axis T) over its first ``length`` steps."""
    return train_prefix(config, memory, episode, length)


def replay_demonstrations(memory: Memory, episodes: Transition, lengths: np.ndarray, *,
                          config: HedgerConfig) -> Iterator[Tuple[Memory, int]]:
    """Replay each episode (leading axes (E, T)) in reverse; ``memory`` is donated. Yields
    (memory, training points of the episode) per episode."""
    for e in range(len(lengths)):
        ep = jax.tree_util.tree_map(lambda x: x[e], episodes)
        memory = _replay_recorded(memory, ep, jnp.int32(lengths[e]), config=config)
        yield memory, int(lengths[e])


# ------------------------------------------------------------------------------------------
# A policy in control
# ------------------------------------------------------------------------------------------
def check_policy_run(env: Any, host_loop: bool, n_episodes: Any, max_steps: int,
                     start: Any) -> Tuple[Any, bool]:
    """Check a policy run's arguments -> (start float32 array, or a placeholder (), has_start).
    Raises ``InvalidInputError``."""
    if host_loop:
        raise InvalidInputError("a policy in control needs one of the project's JAX envs; "
                                f"{env.env_id or env.name!r} runs in the host loop: pass "
                                "recorded demonstrations instead")
    if n_episodes is None or isinstance(n_episodes, bool) or int(n_episodes) < 1:
        raise InvalidInputError(f"n_episodes: a policy needs n_episodes >= 1, got "
                                f"{n_episodes!r}")
    if int(max_steps) < 1:
        raise InvalidInputError(f"max_steps: must be >= 1, got {max_steps}")
    if start is None:
        return jnp.zeros((), jnp.float32), False
    if not hasattr(env, "reset_to"):
        raise InvalidInputError("start: the env has no reset_to")
    start = jnp.asarray(np.asarray(start, np.float32))
    if not np.all(np.isfinite(np.asarray(start))):
        raise InvalidInputError(f"start: contains NaN or inf: {np.asarray(start)}")
    return start, True


@functools.partial(_jit, static_argnames=("env", "config", "act", "init", "max_steps", "has_start"),
                   donate_argnames=("memory",))
def _policy_episode(memory: Memory, key: jax.Array, env_params: Any, start: Any, *, env,
                    config: HedgerConfig, act, init, max_steps: int, has_start: bool):
    """One episode with the policy in control, then reverse replay -> (memory, length ())."""
    k_reset, k_init, k_run = jax.random.split(key, 3)
    if has_start:
        obs0, s0 = env.reset_to(k_reset, env_params, start)
    else:
        obs0, s0 = env.reset(k_reset, env_params)
    ep, length = rollout(env, env_params, act, k_run, max_steps, obs0, s0, init(k_init))
    return train_prefix(config, memory, ep, length), length


def policy_episodes(memory: Memory, next_key: Callable[[], jax.Array], env: Any,
                    env_params: Any, policy: Any, start: Any, *, config: HedgerConfig,
                    n_episodes: int, max_steps: int,
                    has_start: bool) -> Iterator[Tuple[Memory, int]]:
    """``n_episodes`` episodes of at most ``max_steps`` with ``policy`` (pure ``init(key)``,
    ``act(key, obs, pstate)``) in control, from ``env.reset`` or ``env.reset_to(start)``, each
    keyed by ``next_key()`` (the learner's stream); ``memory`` is donated. Yields (memory,
    episode length)."""
    for _ in range(int(n_episodes)):
        memory, length = _policy_episode(memory, next_key(), env_params, start, env=env,
                                         config=config, act=policy.act, init=policy.init,
                                         max_steps=int(max_steps), has_start=has_start)
        yield memory, int(length)


def host_policy_episodes(memory: Memory, next_key: Callable[[], jax.Array], env: Any,
                         buffer: Any, policy: Callable[[np.ndarray], Any],
                         action_value: Callable[[Any], np.ndarray], *, config: HedgerConfig,
                         n_episodes: Any) -> Iterator[Tuple[Memory, int]]:
    """Phase one on a Gymnasium env run by the host loop: ``n_episodes`` episodes of at most
    ``buffer.length`` steps with ``policy(obs float32 (S,)) -> the env's action`` in control
    (``action_value`` maps it to HEDGER's action value (A,), checking it), each reset with a
    seed from ``next_key()`` and replayed in reverse after it ends; ``memory`` is donated.
    Yields (memory, episode length). Raises ``InvalidInputError`` for a bad ``n_episodes``."""
    from hedger_jax.host_loop import replay_episode, run_episode, seed_from_key

    if n_episodes is None or isinstance(n_episodes, bool) or int(n_episodes) < 1:
        raise InvalidInputError(f"n_episodes: a policy needs n_episodes >= 1, got "
                                f"{n_episodes!r}")

    def episodes(memory):
        for _ in range(int(n_episodes)):
            ep = run_episode(env, lambda obs, t: action_value(policy(obs)),
                             seed_from_key(next_key()), buffer.length, buffer)
            memory = replay_episode(memory, buffer.transition(ep.length), jnp.int32(ep.length),
                                    config=config)
            memory = jax.block_until_ready(memory)      # the buffer is reused next episode
            yield memory, ep.length

    return episodes(memory)
