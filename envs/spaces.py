"""Action spaces as HEDGER sees them: a finite set of action vectors, or a box."""
from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import numpy as np


@dataclasses.dataclass(frozen=True)
class ActionSpace:
    """Static (hashable) description of an environment's action space.

    Actions are always passed to ``step`` as float32 vectors of shape ``(action_dim,)``
    holding the action *value* (for a discrete space: one of ``values``), so that HEDGER
    can concatenate them with the state.

    Attributes:
      low, high: per-dimension bounds, tuples of length ``action_dim``.
      values: for a discrete space, the allowed action vectors, a tuple of ``n_actions``
        tuples of length ``action_dim``; ``None`` for a continuous box.
    """

    low: Tuple[float, ...]
    high: Tuple[float, ...]
    values: Optional[Tuple[Tuple[float, ...], ...]] = None

    def __post_init__(self):
        if len(self.low) != len(self.high) or len(self.low) == 0:
            raise ValueError("ActionSpace: low and high must be non-empty and the same length")
        if any(not (lo < hi) for lo, hi in zip(self.low, self.high)):
            raise ValueError(f"ActionSpace: need low < high, got {self.low} / {self.high}")
        if self.values is not None:
            if len(self.values) < 1 or any(len(v) != len(self.low) for v in self.values):
                raise ValueError("ActionSpace: each discrete value must have length action_dim")

    @property
    def action_dim(self) -> int:
        return len(self.low)

    @property
    def is_discrete(self) -> bool:
        return self.values is not None

    @property
    def n_actions(self) -> int:
        if self.values is None:
            raise ValueError("continuous action space has no finite action count")
        return len(self.values)

    def values_array(self) -> np.ndarray:
        """Discrete action values as a float32 array of shape (n_actions, action_dim)."""
        if self.values is None:
            raise ValueError("continuous action space has no finite value set")
        return np.asarray(self.values, dtype=np.float32)

    @staticmethod
    def discrete(values, action_dim: int = 1) -> "ActionSpace":
        vals = tuple(tuple(float(x) for x in np.atleast_1d(v)) for v in values)
        arr = np.asarray(vals, dtype=np.float64)
        return ActionSpace(tuple(arr.min(0)), tuple(arr.max(0)), vals)

    @staticmethod
    def box(low, high) -> "ActionSpace":
        return ActionSpace(tuple(float(x) for x in np.atleast_1d(low)),
                           tuple(float(x) for x in np.atleast_1d(high)), None)
