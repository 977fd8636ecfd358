"""Per-environment settings, declared once: ``Hedger``'s defaults and the figures' lines
(``experiments.figures``) both read them from here.

The paper-protocol settings (measured in ``experiments``; docs/reproduction.md):

* ``MOUNTAIN_CAR``, ``MOUNTAIN_CAR_CONTINUOUS``, ``CORRIDOR``: keyword overrides for
  ``HedgerConfig.for_env`` (``action_scale`` included);
* ``CORRIDOR_RUN``: ``RunConfig`` overrides; ``CORRIDOR_SCALE_FACTORS``: multipliers (S,) on
  the [0, 1] observation scaling; ``CORRIDOR_ENV_PARAMS``: overrides of the env's params.

``ENV_PRESETS`` collects them per ``envs.make`` name as ``Hedger`` applies them (see
``learner_setup``). The adaptive kernel's lines (beyond the paper) are the
``*_ADAPTIVE_*`` dicts: ``HedgerParams`` overrides.

Every settings dict is read-only (a ``MappingProxyType``): copy it with ``dict(...)`` to change
it, so that no caller changes another's defaults.
"""
from __future__ import annotations

import types
from typing import Any, Dict, Mapping


__all__ = ["ADAPTIVE", "ADAPTIVE_CONTINUOUS", "MOUNTAIN_CAR", "MOUNTAIN_CAR_CONTINUOUS",
           "CORRIDOR", "CORRIDOR_RUN", "CORRIDOR_SCALE_FACTORS", "CORRIDOR_ENV_PARAMS", "ADAPTIVE_PARAMS",
           "ADAPTIVE_CONTINUOUS_PARAMS", "CORRIDOR_ADAPTIVE_PARAMS", "ENV_PRESETS",
           "HOST_EVAL_EPISODES", "TASK", "preset"]

_frozen = types.MappingProxyType

#: The adaptive preset (beyond the paper; docs/adaptive-kernel.md), one for every task: a
#: kernel width read from the stored data once per episode (at most 2x ``bandwidth``), fitting
#: log-scale values; ties of the continuous search broken at random; a guess from the fits
#: where no action is known; the replay's max at least the value just stored for the next
#: step, with every fit clipped to its neighbours' values (the floor alone diverges); a hull
#: check widened by half; alpha = 1 (the kernel does the averaging). Chosen on seeds >= 100.
#: ``HedgerConfig(..., **ADAPTIVE)`` or ``HedgerParams.create(config, **ADAPTIVE)``.
ADAPTIVE = _frozen({"bandwidth_k": 4, "kernel_range": 2.0, "value_eps": 1e-6,
                    "random_ties": True, "guess_unknown": True, "replay_floor": True,
                    "clip_to_neighbours": True, "ivh_tol": 0.5, "alpha": 1.0})
#: For continuous actions: the same, with the width narrowed at the local-linear rate beyond
#: 16,384 stored points (``bandwidth_shrink``: it helps continuous actions, hurts discrete
#: ones). Scale the action from its bounds.
ADAPTIVE_CONTINUOUS = _frozen({**ADAPTIVE, "bandwidth_shrink": True})

#: Mountain car, discrete actions {-1, 0, 1} kept raw: h = 0.015 is the narrow window in which
#: HEDGER learns it at all.
MOUNTAIN_CAR = _frozen(dict(bandwidth=0.015, alpha=0.8, gamma=0.8))
#: Continuous actions scaled by 0.1: the range [-1, 1] spans 0.2, about 6 neighbour radii.
MOUNTAIN_CAR_CONTINUOUS = _frozen(dict(MOUNTAIN_CAR, action_scale=0.1))
#: Corridor (experiments/CORRIDOR_NOTES.md): h = 0.05, actions raw (rad/s).
CORRIDOR = _frozen(dict(bandwidth=0.05, alpha=0.2, gamma=0.99, action_scale=1.0))
#: The corridor explores around the greedy action (a random turn command crashes the robot).
CORRIDOR_RUN = _frozen(dict(exploration="gaussian", noise_std=0.3))
#: Distance-to-end weighted 10x less than its [0, 1] scaling: the value changes smoothly
#: along the corridor, the steering decision does not depend on it.
CORRIDOR_SCALE_FACTORS = (1.0, 1.0, 0.1)
#: Training runs start at the beginning of the evaluated section, as the robot's runs did.
CORRIDOR_ENV_PARAMS = _frozen(dict(train_x_max=0.5))

#: The adaptive lines: one kernel width read from the stored data, log-scale values
#: (``hedger_jax.ADAPTIVE``); continuous actions scaled from their bounds like the states
#: ([-1, 1] -> x0.5: no hand-picked factor).
ADAPTIVE_PARAMS = _frozen(dict(ADAPTIVE))
ADAPTIVE_CONTINUOUS_PARAMS = _frozen(dict(ADAPTIVE_CONTINUOUS, action_scale=0.5))
#: The corridor's adaptive line: the adaptive preset with its one per-task number, a wider
#: span (24 of the 1024 pooled points: m = 4 leaves its 4-D inputs "don't know" almost
#: everywhere; 24 of 24 / 48 / 96 on seeds 100-104). The observation is scaled only from its
#: bounds.
CORRIDOR_ADAPTIVE_PARAMS = _frozen(dict(ADAPTIVE_CONTINUOUS, bandwidth_k=24))

#: Any other Gymnasium task (beyond the paper; docs/classic-control.md): the adaptive preset
#: with room for its data-chosen width (at most 2 x 0.1 of the [0, 1] scaled ranges: 4-D
#: states are sparse), plain values (the task's own reward keeps them within 1 / (1 - gamma)
#: of it), "don't know" worth 0, five memory-wide sweeps after every episode through a plan
#: (``hedger_jax.backup``) rebuilt as the memory grows (``RunConfig.replan_fraction``), and
#: room for 150,000 points (every point of the classic-control budgets: once a ring buffer
#: overwrites old points, what they taught is lost), the newest kept beyond it.
#: ``hedger_jax.task_settings`` adds what it reads from the task (the discount, the action's
#: scale).
TASK = _frozen(dict(ADAPTIVE, bandwidth=0.1, value_eps=0.0, default_value=0.0,
                    backup_sweeps=5, capacity=150_000, full_policy="overwrite_oldest"))

#: ``Hedger``'s defaults per ``envs.make`` name: ``hedger`` (``HedgerConfig.for_env``
#: overrides), ``run`` (``RunConfig`` overrides), and optionally ``state_scale_factors`` (S,)
#: and ``env_params`` (overrides of the env's default params).
ENV_PRESETS: Dict[str, Dict[str, Any]] = {
    "mountain_car_discrete": {"hedger": MOUNTAIN_CAR, "run": _frozen({})},
    "mountain_car_continuous": {"hedger": MOUNTAIN_CAR_CONTINUOUS, "run": _frozen({})},
    "corridor": {"hedger": CORRIDOR, "run": CORRIDOR_RUN,
                 "state_scale_factors": CORRIDOR_SCALE_FACTORS,
                 "env_params": CORRIDOR_ENV_PARAMS},
}

#: Default ``RunConfig.eval_episodes`` for a Gymnasium env run by the host loop (its
#: ``eval_max_steps`` defaults to the env's time limit).
HOST_EVAL_EPISODES = 20

_NO_PRESET: Mapping[str, Any] = _frozen({"hedger": _frozen({}), "run": _frozen({})})


def preset(name: Any) -> Mapping[str, Any]:
    """``ENV_PRESETS[name]``, or empty settings for an env without a preset."""
    return ENV_PRESETS.get(name, _NO_PRESET)
