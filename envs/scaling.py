"""The scaling range of an observation whose declared bounds are unbounded.

HEDGER scales every observation dimension to [0, 1] by a range (``obs_bounds``) before it
measures distances. Many spaces declare some dimensions unbounded (CartPole's velocities),
with ±inf or with float32's largest value. The rule every adapter here applies:

* a bound is *unbounded* when it is not finite or its magnitude is at least ``UNBOUNDED``
  (1e6: a dimension scaled by a wider range would vanish from the distance anyway);
* a dimension with an unbounded bound takes both of its bounds from observations seen while
  ``SAMPLE_STEPS`` (2,000) uniformly random actions are taken in a copy of the env seeded with
  ``SAMPLE_SEED`` (episodes restart when they end): the observation each step acts from is
  recorded, and the range is the samples' min and max, each widened by ``WIDEN`` (10 %) of
  their span; a dimension that never changed gets a unit range centred on its value;
* every other dimension keeps its declared bounds.

Observations outside the estimated range later are scaled by the same affine map (beyond
[0, 1]); nothing is clipped.
"""
from __future__ import annotations

from typing import Tuple

import jax.numpy as jnp

__all__ = ["UNBOUNDED", "SAMPLE_STEPS", "SAMPLE_SEED", "WIDEN", "unbounded",
           "range_from_samples", "scaling_bounds"]

UNBOUNDED = 1e6
SAMPLE_STEPS = 2000
SAMPLE_SEED = 0
WIDEN = 0.1


def unbounded(low, high):
    """Which dimensions need a range from samples: low, high (S,) -> bool (S,)."""
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    bad_low = ~jnp.isfinite(low) | (jnp.abs(low) >= UNBOUNDED)
    bad_high = ~jnp.isfinite(high) | (jnp.abs(high) >= UNBOUNDED)
    return bad_low | bad_high


def range_from_samples(samples) -> Tuple:
    """The widened range of observed samples: samples (N, S) -> (low, high) float32 (S,).

    min/max widened by ``WIDEN`` of the span on each side; a constant dimension gets
    [value - 0.5, value + 0.5]."""
    x = jnp.asarray(samples, jnp.float32)
    lo, hi = jnp.min(x, axis=0), jnp.max(x, axis=0)
    span = hi - lo
    constant = span <= 0
    low = jnp.where(constant, lo - 0.5, lo - WIDEN * span)
    high = jnp.where(constant, hi + 0.5, hi + WIDEN * span)
    return low, high


def scaling_bounds(low, high, samples) -> Tuple:
    """Declared bounds with the unbounded dimensions' ranges taken from samples.

    low, high (S,); samples (N, S) observations (see the module doc) -> (low, high)
    float32 (S,). Jittable."""
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    mask = unbounded(low, high)
    s_low, s_high = range_from_samples(samples)
    return jnp.where(mask, s_low, low), jnp.where(mask, s_high, high)
