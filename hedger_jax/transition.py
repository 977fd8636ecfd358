"""``Transition``: one experience, the unit every training function and check reads."""
from __future__ import annotations

from typing import NamedTuple

import jax


class Transition(NamedTuple):
    """One experience (s, a, r, s'); an episode has a leading time axis T on every field.

    obs: float32 (S,); action: float32 (A,); reward: float32 (); next_obs: float32 (S,);
    terminated: bool () true terminal (no bootstrap; a time-limit truncation is *not* one);
    valid: bool () False for padding (the step changes nothing).
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    terminated: jax.Array
    valid: jax.Array
