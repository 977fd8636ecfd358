"""Phase two and evaluation of ``Hedger`` on the project's JAX envs: whole episodes inside
jitted code, many episodes per call.

The jitted functions are module level: compiled once per (env, config, run config) and shared
by every learner with equal static settings.
"""
from __future__ import annotations

import functools
from typing import Any, Dict, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.agent import RunConfig, evaluate, rollout, train_prefix, training_act
from hedger_jax.config import HedgerConfig
from hedger_jax.cpu import jit as _jit
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.memory import Memory, refresh_index
from hedger_jax.progress import Chunk

__all__ = ["learn_chunk", "training_chunks", "evaluate_greedy"]

#: Largest step budget of one call (its counter is int32).
_MAX_BUDGET = 2**31 - 1


@functools.partial(_jit, static_argnames=("env", "config", "run", "max_steps", "max_episodes"),
                   donate_argnames=("memory",))
def learn_chunk(memory: Memory, key: jax.Array, env_params: Any, budget: jax.Array, *, env,
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


def training_chunks(memory: Memory, key: jax.Array, env: Any, env_params: Any, *,
                    config: HedgerConfig, run: RunConfig, total: int, max_steps: int,
                    max_episodes: int) -> Iterator[Chunk]:
    """Phase two until ``total`` env steps were taken (whole episodes: the last may overshoot):
    one ``learn_chunk`` call of at most ``max_episodes`` episodes per yielded ``Chunk``.
    ``memory`` is donated; ``key`` (raw uint32 (2,)) is threaded through the chunks."""
    done = 0
    while done < total:
        budget = jnp.asarray(min(total - done, _MAX_BUDGET), jnp.int32)
        memory, key, steps, n_ep, lengths, returns = learn_chunk(
            memory, key, env_params, budget, env=env, config=config, run=run,
            max_steps=max_steps, max_episodes=max_episodes)
        steps, n_ep = int(steps), int(n_ep)
        done += steps
        yield Chunk(memory, key, steps, np.asarray(lengths)[:n_ep], np.asarray(returns)[:n_ep])


@functools.partial(_jit, static_argnames=("env", "config", "n_episodes", "max_steps"))
def _evaluate_jit(memory, key, env_params, *, env, config, n_episodes, max_steps):
    return evaluate(env, env_params, config, memory, key, n_episodes, max_steps)


def evaluate_greedy(memory: Memory, key: jax.Array, env: Any, env_params: Any, *,
                    config: HedgerConfig, n_episodes: int, max_steps: int) -> Dict[str, float]:
    """The greedy policy, learning off (``agent.evaluate``, episodes vmapped) ->
    {"mean_steps", "success_rate"} (failures count ``max_steps``)."""
    ev = _evaluate_jit(memory, key, env_params, env=env, config=config, n_episodes=n_episodes,
                       max_steps=max_steps)
    return {"mean_steps": float(ev.mean_steps), "success_rate": float(ev.success_rate)}
