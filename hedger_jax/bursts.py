"""Exploratory bursts: ``RunConfig(exploration="bursts")``.

Epsilon-greedy whose exploratory step starts a *burst*: the random action is held for n
steps, n drawn from a zeta distribution, P(n) proportional to n^-2 on 1..``MAX_STEPS``
(temporally-extended epsilon-greedy, Dabney, Ostrovski & Barreto, ICLR 2021). Single
random steps dither in place; held ones travel, which is what an underpowered car needs to
leave the valley. A burst ends with the episode. The acting policy carries a ``Burst`` from
step to step (``rollout``'s ``act_state``, the host loop's per-episode state).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.config import HedgerConfig

__all__ = ["Burst", "MAX_STEPS", "EXPONENT", "start", "duration", "duration_pmf"]

#: The longest burst (the classic-control episodes are 200 to 1,000 steps).
MAX_STEPS = 1000
#: The zeta exponent: heavy-tailed, so long bursts are rare but not vanishing.
EXPONENT = 2.0


class Burst(NamedTuple):
    """action: float32 (A,) the held exploratory action; left: int32 () the steps it is
    still held (0: no burst under way)."""

    action: jax.Array
    left: jax.Array


def start(config: HedgerConfig) -> Burst:
    """No burst under way: the state at the start of an episode."""
    return Burst(jnp.zeros((config.action_dim,), jnp.float32), jnp.zeros((), jnp.int32))


def duration_pmf() -> np.ndarray:
    """float64 (MAX_STEPS,): P(n) for n = 1..MAX_STEPS."""
    w = np.arange(1, MAX_STEPS + 1, dtype=np.float64) ** -EXPONENT
    return w / w.sum()


def duration(u: jax.Array) -> jax.Array:
    """A burst's length int32 () in 1..MAX_STEPS from one U[0, 1) draw u () (inverse CDF)."""
    cdf = jnp.asarray(np.cumsum(duration_pmf()), jnp.float32)
    n = 1 + jnp.searchsorted(cdf, u, side="right")
    return jnp.minimum(n, MAX_STEPS).astype(jnp.int32)   # u above cdf[-1]'s float32 rounding
