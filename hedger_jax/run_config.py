"""``RunConfig``: the settings of one learning run (phases, blocks, evaluation, exploration).

Declared like ``HedgerConfig`` (``hedger_jax.settings``): ``epsilon`` and ``noise_std`` are
traced (the defaults of the ``HedgerParams`` fields of the same names); the rest is static.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from hedger_jax.settings import (TRACED_KINDS, choice, fields_of, first_failure, integer,
                                 positive_float,
                                 python_value, reject_traced, setting, spec)

#: ``RunConfig.exploration`` choices.
EXPLORATION = ("random", "gaussian", "bursts")


def _fraction(name, value, owner):
    """A float in (0, 1]."""
    value = positive_float(name, value, owner)
    if value > 1:
        raise ValueError(f"{name}: must be in (0, 1], got {value}")
    return value


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Static settings of one learning run (the HEDGER settings live in ``HedgerConfig``).

    epsilon: probability of an exploratory action (traced).
    exploration: "random" (a uniformly random action, the mountain-car protocol) or
      "gaussian" (the greedy action plus N(0, noise_std) noise, clipped to the bounds; the
      corridor protocol). noise_std is traced. Or "bursts" (beyond the paper;
      ``hedger_jax.bursts``): an exploratory step holds its random action for a
      heavy-tailed number of steps; the default for a continuous-action Gymnasium task
      (``hedger_jax.task_settings``). A single-step ``predict(deterministic=False)`` starts
      no burst: it is epsilon-greedy with one random step.
    n_blocks: number of evaluation blocks of phase two.
    episodes_per_block / points_per_block: the length of a block (exactly one must be set).
    eval_episodes: greedy evaluation episodes per evaluation (learning off).
    eval_max_steps: cap of an evaluation episode (a failure counts as this many steps).
    train_max_steps: cap of a phase-two training episode (None: the env's ``max_steps``).
    replan_fraction: on a Gymnasium env run by the host loop, the memory-wide backups'
      plan (``hedger_jax.backup``) is rebuilt after an episode once the env steps since it
      was built reach this fraction of the stored points (so its cost per step stays
      constant as the memory grows); the JAX envs' loops build one every episode.
    reuse_neighbours: the replay reuses the neighbour sets the rollout's greedy searches
      found (``hedger_jax.replay_cache``): the same sets, so the same run up to float32
      rounding. None (default): for memories of at least
      ``replay_cache.REUSE_MIN_CAPACITY`` slots, where searches are dear. False: every
      query searches.
    """

    epsilon: float = setting(0.2, "number", ok=lambda v: (v >= 0) & (v <= 1),
                             rule="must be in [0, 1]")
    exploration: str = setting("random", "static", convert=choice(EXPLORATION))
    noise_std: float = setting(0.2, "number", ok=lambda v: v >= 0, rule="must be >= 0")
    n_blocks: int = setting(20, "static", convert=integer(0))
    episodes_per_block: Optional[int] = setting(10, "static", convert=integer(1, optional=True))
    points_per_block: Optional[int] = setting(None, "static",
                                              convert=integer(1, optional=True))
    eval_episodes: int = setting(2500, "static", convert=integer(1))
    eval_max_steps: int = setting(200, "static", convert=integer(1))
    train_max_steps: Optional[int] = setting(None, "static", convert=integer(1, optional=True))
    replan_fraction: float = setting(0.1, "static", convert=_fraction)
    reuse_neighbours: Optional[bool] = setting(None, "static",
                                               convert=lambda n, v, o: None if v is None
                                               else bool(v))

    def __post_init__(self):
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        for f in dataclasses.fields(self):
            s = spec(self, f.name)
            reject_traced("RunConfig", f.name, getattr(self, f.name), s.kind in TRACED_KINDS)
        for name in fields_of(self):
            set_(name, python_value(spec(self, name).kind, name, getattr(self, name)))
        failure = first_failure(fields_of(self), {n: np.asarray(getattr(self, n))
                                                  for n in fields_of(self)},
                                {n: spec(self, n) for n in fields_of(self)})
        if failure:
            raise ValueError(failure)
        for f in dataclasses.fields(self):
            s = spec(self, f.name)
            if s.kind == "static":
                set_(f.name, s.convert(f.name, getattr(self, f.name), self))
        if (self.episodes_per_block is None) == (self.points_per_block is None):
            raise ValueError("episodes_per_block / points_per_block: set exactly one of them")
