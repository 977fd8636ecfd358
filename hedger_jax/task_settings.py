"""Settings read from a Gymnasium task, so that ``Hedger(env_id)`` needs no hand-picked ones.

``task_settings(env)`` starts from ``presets.TASK`` (one set for every task; the run's
settings are ``RunConfig``'s defaults) and adds what differs between tasks only through what
the environment declares:

* the discount: gamma = 1 - 2 / T for the time limit T, within [0.9, 0.99] (a horizon of
  about half an episode, never beyond 100 steps);
* a continuous action scaled like the observations: its [low, high] spans 1
  (``action_scale = 1 / (high - low)``), and explored in bursts (``RunConfig(exploration=
  "bursts")``, ``hedger_jax.bursts``): a random action held for a heavy-tailed number of
  steps. One random step of a continuous action barely moves the state; a discrete task's
  random step already changes the action by a whole level, and bursts there hurt
  (docs/classic-control.md).

"Don't know" is worth 0 (``default_value`` in ``TASK``), the value of a future that brings
nothing: optimistic where every step costs (the cars, the acrobot, the pendulum: untried
actions look best until tried), cautious where every step earns (CartPole: the unknown is
treated like the fall that ends the rewards). Observations are scaled to [0, 1] from their
bounds, or from random-action samples where unbounded (``hedger_jax.environments``); the
kernel width is the data-chosen one (``bandwidth_k``); the memory keeps the newest
``capacity`` points (``full_policy`` "overwrite_oldest"), so ``learn`` runs past the
capacity.
"""
from __future__ import annotations

from typing import Any, Dict, Tuple

import numpy as np

from hedger_jax.presets import TASK

__all__ = ["discount", "task_settings"]


def discount(time_limit: int) -> float:
    """gamma from the episode cap T: 1 - 2 / T clipped to [0.9, 0.99]."""
    return float(np.clip(1.0 - 2.0 / max(int(time_limit), 1), 0.9, 0.99))


def task_settings(env: Any) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """(``HedgerConfig.for_env`` overrides, ``RunConfig`` overrides) for a ``GymnasiumEnv``
    (module doc)."""
    hedger = dict(TASK)
    gamma = discount(env.max_steps)
    hedger["gamma"] = gamma
    space = env.action_space
    if space.is_discrete:
        return hedger, {}
    hedger["action_scale"] = 1.0 / float(space.high[0] - space.low[0])
    return hedger, {"exploration": "bursts"}
