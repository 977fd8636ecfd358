"""Static configuration of a HEDGER learner: ``HedgerConfig``.

``HedgerConfig`` is a frozen, hashable dataclass: pass it as a static argument to ``jax.jit``
(or close over it). It fixes shapes, loop lengths and the default hyperparameters; the
hyperparameters a sweep varies are traced in ``HedgerParams`` (``hedger_jax.params``), and
everything that changes during learning lives in pytrees (``Memory``). Every field is
validated on construction: a bad value raises ``ValueError`` naming the field, a traced one
``StaticFieldError``.
"""
from __future__ import annotations

import dataclasses
import math
import types
import warnings
from typing import Any, Optional, Tuple

#: ``full_policy`` choices: drop and flag new points, or overwrite the oldest (ring buffer).
FULL_POLICIES = ("error", "overwrite_oldest")
#: ``neighbour_index`` choices.
NEIGHBOUR_INDEXES = ("auto", "brute", "grid")
#: Inputs of at most this many dimensions are "low-dimensional" for ``neighbour_index="auto"``.
AUTO_GRID_LOW_DIM = 4
#: "auto" uses the grid index from this capacity up for low-dimensional inputs ...
AUTO_GRID_CAPACITY_LOW_DIM = 512
#: ... and from this one for more dimensions (a query scans 3^(d-1) rows of cells) ...
AUTO_GRID_CAPACITY = 16_384
#: ... when, for more dimensions, a query's rows cover at most this fraction of a uniformly
#: filled memory (``index.scanned_fraction``). Low-dimensional inputs use the grid at any
#: kernel width: its finer levels keep wide kernels cheap (docs/performance.md).
AUTO_GRID_MAX_FRACTION = 0.02
#: Largest capacity of the grid index (int32 positions with a flag at bit 30); above it
#: "auto" uses brute force and "grid" is refused.
GRID_MAX_CAPACITY = 1 << 29


class StaticFieldError(TypeError):
    """A static setting (a ``HedgerConfig`` or ``RunConfig`` field) was given a traced value,
    e.g. by ``jax.vmap`` over a function that builds the config."""


def reject_traced(owner: str, name: str, value: Any) -> None:
    """Raise ``StaticFieldError`` if ``value`` (or an element of it, nested tuples and lists
    included) is a JAX tracer; the message says where a traced field belongs instead."""
    import jax

    items = value if isinstance(value, (tuple, list)) else (value,)
    for item in items:
        if isinstance(item, (tuple, list)):
            reject_traced(owner, name, item)
        elif isinstance(item, jax.core.Tracer):
            traced = name in _TRACED_FIELDS
            hint = (f"put it in HedgerParams instead (HedgerParams.create(config, {name}=...)), "
                    "whose fields are traced" if traced else
                    "it fixes shapes or loop lengths; sweep it with one program per value")
            raise StaticFieldError(f"{name}: {owner} fields are static and cannot be traced "
                                   f"or vmapped; {hint}")


#: Stored points the data-chosen width (``bandwidth_k``) counts neighbours among
#: (``hedger_jax.data_bandwidth``): ``bandwidth_k`` is at most this.
BANDWIDTH_POOL = 1024
#: The adaptive kernel (beyond the paper): one kernel width read from the stored data once
#: per episode (the median width that gives a stored point its 4th nearest neighbour among
#: 1024 stored points spread over the memory the weight ``min_weight``: the kernel spans a
#: fixed fraction of the data; at most 2x ``bandwidth``), fitting log-scale values; the
#: continuous greedy search breaks ties at random (``random_ties``). Use as
#: ``HedgerConfig(..., **ADAPTIVE)`` or ``HedgerParams.create(config, **ADAPTIVE)``; see
#: docs/adaptive-kernel.md for how it was chosen.
ADAPTIVE = types.MappingProxyType({"bandwidth_k": 4, "kernel_range": 2.0, "value_eps": 1e-6,
                                   "random_ties": True})
#: For continuous actions: the same settings, and the width narrowed at the local-linear rate
#: beyond 16,384 stored points (``bandwidth_shrink``: it helps continuous actions from random
#: starts and hurts discrete ones, docs/adaptive-kernel.md). The per-query width of
#: ``kernel_k`` collapses there; the width read from the memory does not. Scale the action
#: from its bounds (``HedgerConfig.for_env(..., action_scale="bounds")``).
ADAPTIVE_CONTINUOUS = types.MappingProxyType({**ADAPTIVE, "bandwidth_shrink": True})


def warn_data_chosen_width_with_continuous_actions(config: "HedgerConfig") -> None:
    """A ``UserWarning`` for a data-chosen kernel width (``kernel_k`` > 0) with continuous
    actions, where it was measured to make the greedy policy collapse."""
    warnings.warn(
        "kernel_k > 0 (a per-query kernel width) with continuous actions: measured to make "
        "the greedy policy collapse to random-policy level on mountain car and the corridor "
        "(docs/adaptive-kernel.md); for continuous actions use one width for the memory "
        "(bandwidth_k, hedger_jax.ADAPTIVE_CONTINUOUS) and scale the action from its bounds",
        UserWarning, stacklevel=3)


#: The ``HedgerConfig`` and ``RunConfig`` fields that ``HedgerParams`` carries as traced values.
_TRACED_FIELDS = ("bandwidth", "min_weight", "kernel_k", "kernel_range", "bandwidth_k",
                  "bandwidth_shrink", "region_scale",
                  "value_eps",
                  "k_thresh", "k_min", "alpha", "gamma",
                  "default_value", "ridge", "ivh_tol", "input_offset", "input_scale", "use_ivh",
                  "region_update", "random_ties", "guess_unknown", "greedy_temperature",
                  "clip_to_neighbours", "replay_floor", "epsilon", "noise_std")


def selection_radius(bandwidth, min_weight, kernel_k=0, kernel_range=1.0, bandwidth_k=0):
    """The default k_thresh: where the widest kernel's weight falls to ``min_weight``,
    bandwidth sqrt(ln(1 / min_weight)), times ``kernel_range`` with a data-chosen width
    (``kernel_k`` or ``bandwidth_k`` > 0). NumPy in, NumPy out (Python floats for Python
    floats)."""
    import numpy as np

    h = np.asarray(bandwidth, np.float64) * np.where(
        (np.asarray(kernel_k) > 0) | (np.asarray(bandwidth_k) > 0),
        np.asarray(kernel_range, np.float64), 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = h * np.sqrt(np.log(1.0 / np.asarray(min_weight, np.float64)))
    return float(out) if np.ndim(out) == 0 else out


def _tuple_of_floats(name: str, value: Any, length: int) -> Tuple[float, ...]:
    """``value`` (a scalar, broadcast, or a sequence) as ``length`` finite floats, else
    ``ValueError`` naming the field."""
    try:
        out = tuple(float(v) for v in value)
    except TypeError:
        out = (float(value),) * length
    if len(out) != length:
        raise ValueError(f"{name}: expected {length} values, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name}: values must be finite, got {out}")
    return out


@dataclasses.dataclass(frozen=True)
class HedgerConfig:
    """All static settings of HEDGER (Smart & Kaelbling 2000, Algorithms 1 and 2).

    Shapes: S = ``state_dim``, A = ``action_dim``, d = S + A (``dim``).

    Input scaling: a query is ``z = (concat(state, action) - input_offset) * input_scale``
    (each a length-d tuple; default 0 and 1) so that no dimension dominates the Euclidean
    distance. ``HedgerConfig.for_env`` scales observations to [0, 1] from the environment's
    bounds and multiplies actions by ``action_scale``.

    Prediction: neighbours are the stored points within ``k_thresh`` of the query (default
    ``bandwidth * sqrt(ln(1/min_weight))``: the distance where the Gaussian weight
    ``exp(-d^2/h^2)`` falls to ``min_weight``), at most ``max_neighbours`` (the nearest).
    Fewer than ``k_min`` (default d + 1, the number of local-linear parameters) or a query
    outside the independent-variable hull (``use_ivh``) gives ``default_value`` ("don't know").

    Kernel width chosen from the data (beyond the paper; off by default): with ``kernel_k``
    = m > 0 each query's kernel width is the one that gives its m-th nearest neighbour the
    weight ``min_weight``, kept within [bandwidth / kernel_range, bandwidth * kernel_range];
    neighbours are then searched within the widest kernel's radius (the default k_thresh is
    ``kernel_range`` times the paper's). With ``bandwidth_k`` = m > 0 instead, one width for
    the whole memory: the median over stored points of the width giving their m-th nearest
    neighbour among ``BANDWIDTH_POOL`` stored points ``min_weight`` (with
    ``bandwidth_shrink``, narrowed at the local-linear rate size^(-1/(d+4)) beyond 16 pools;
    no effect with ``bandwidth_k`` = 0), at most bandwidth * kernel_range, read once per
    episode (``hedger_jax.data_bandwidth``); at most one of the
    two is > 0.

    Continuous greedy search: the best of its samples, ties to the first (the paper's search
    names no rule); with ``random_ties`` (beyond the paper) equal best values at two or more
    of the initial samples are broken at random, as the discrete set's ties always are.
    Where no candidate is known the greedy action is random (the paper); with
    ``guess_unknown`` (beyond the paper) it is first chosen by the same local fits without
    the hull check, and is random only where those too know nothing (too few neighbours);
    its value stays ``default_value`` and ``known`` False, so training targets do not change.
    With ``greedy_temperature`` = T > 0 (beyond the paper; continuous actions only) the
    greedy action is the mean of the search's samples weighted by exp((y - y_best) / T), y
    the values as the fit sees them (log-scale with ``value_eps``): where the actions' values
    differ by less than T the action is their weighted mean, not the pick of the fits'
    noise; the value (the training target) is the samples' values averaged with the same
    weights.

    With ``clip_to_neighbours`` (beyond the paper) a known prediction is clipped to the
    range of its neighbours' stored values (as the fit sees them): the fit interpolates
    and never extrapolates a value, so a backup's max cannot feed on its own overshoots.

    Training: ``alpha``/``gamma`` of Q-learning; ``region_update`` moves every neighbour
    towards the new value by its kernel weight (Algorithm 2 lines 7-8), scaled by
    ``region_scale`` (1: the paper). With ``replay_floor`` (beyond the paper) the reverse
    replay of an episode takes max_a' Q(s', a') to be at least the value it has just stored
    for s' with the action the episode took there (a max is at least any one of its terms),
    so a "don't know" or a low fit on the way cannot cut the reward off from the earlier
    steps.

    Traced settings: bandwidth, min_weight, k_thresh, k_min, alpha, gamma, default_value,
    ridge, ivh_tol, input_offset, input_scale, use_ivh, region_update, random_ties,
    guess_unknown, greedy_temperature, clip_to_neighbours, replay_floor and bandwidth_shrink are
    the defaults of ``HedgerParams`` (``hedger_jax.params``), which carries them as traced
    values; with ``params=None`` these values are compile-time constants. ``max_bandwidth`` (default
    ``bandwidth``) is the largest bandwidth a ``HedgerParams`` may use: the grid index is
    built for its radius.

    Actions: ``discrete_actions`` (a tuple of length-A tuples) or, when ``None``, the box
    [``action_low``, ``action_high``] searched by ``greedy_samples`` evenly spaced samples and
    at most ``greedy_iters`` quadratic-fit refinements stopping at ``greedy_tol``.

    Memory: ``capacity`` preallocated points; when full, ``full_policy="error"`` drops the new
    point, sets a flag and ``memory_check`` raises ``MemoryFullError`` on the host (stored data
    is never corrupted); ``"overwrite_oldest"`` replaces the oldest point (a ring buffer).

    Neighbour search: ``neighbour_index`` "brute" (scan every slot), "grid" (the exact grid
    index of ``hedger_jax.index``: the same neighbour sets) or "auto" (``index_kind``: the
    grid from ``AUTO_GRID_CAPACITY_LOW_DIM`` slots up for inputs of at most
    ``AUTO_GRID_LOW_DIM`` dimensions, from ``AUTO_GRID_CAPACITY`` for more, unless the kernel
    is wide against the input ranges with more dimensions, ``AUTO_GRID_MAX_FRACTION``; the
    grid holds at most
    ``GRID_MAX_CAPACITY`` slots). Grid settings: ``index_chunk`` candidates per step of the
    scan (None: ``index.chunk_width``); ``index_bounds`` the scaled range ((lo, hi) per
    dimension) the grid covers (default: [0, 1] per state dimension and the scaled action
    range; points outside are clamped to the border cells, never dropped); ``index_levels``
    the number of grid levels (finer levels keep the search cost independent of the density;
    None: as many as the capacity makes useful); ``index_recent`` the length of the sorted
    list of points written since the last merge of the grid tables (merged once three
    quarters of it are used, ``index.merge_threshold``; None: ``index.recent_length``).

    Numerics: ``ridge`` is a relative ridge added to the equilibrated normal equations;
    ``ivh_tol`` a relative tolerance on the hull test (so a stored point is inside its own hull
    despite float32 round-off).
    """

    state_dim: int
    action_dim: int = 1
    input_offset: Optional[Tuple[float, ...]] = None
    input_scale: Optional[Tuple[float, ...]] = None
    capacity: int = 20_000
    bandwidth: float = 0.015
    k_thresh: Optional[float] = None
    min_weight: float = 0.01
    kernel_k: int = 0
    kernel_range: float = 4.0
    bandwidth_k: int = 0
    bandwidth_shrink: bool = False
    region_scale: float = 1.0
    value_eps: float = 0.0
    k_min: Optional[int] = None
    max_neighbours: int = 32
    default_value: float = 0.0
    alpha: float = 0.8
    gamma: float = 0.8
    use_ivh: bool = True
    region_update: bool = True
    random_ties: bool = False
    guess_unknown: bool = False
    greedy_temperature: float = 0.0
    clip_to_neighbours: bool = False
    replay_floor: bool = False
    discrete_actions: Optional[Tuple[Tuple[float, ...], ...]] = None
    action_low: Tuple[float, ...] = (-1.0,)
    action_high: Tuple[float, ...] = (1.0,)
    greedy_samples: int = 11
    greedy_iters: int = 8
    greedy_tol: float = 1e-3
    full_policy: str = "error"
    ridge: float = 1e-6
    ivh_tol: float = 1e-3
    neighbour_index: str = "auto"
    index_chunk: Optional[int] = None
    index_bounds: Optional[Tuple[Tuple[float, float], ...]] = None
    index_levels: Optional[int] = None
    index_recent: Optional[int] = None
    max_bandwidth: Optional[float] = None

    def __post_init__(self):
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        for field in dataclasses.fields(self):
            reject_traced("HedgerConfig", field.name, getattr(self, field.name))
        for name in ("state_dim", "action_dim", "capacity", "max_neighbours",
                     "greedy_samples", "greedy_iters"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value:
                raise ValueError(f"{name}: must be an integer, got {value!r}")
            set_(name, int(value))
        if self.state_dim < 1:
            raise ValueError(f"state_dim: must be >= 1, got {self.state_dim}")
        if self.action_dim < 1:
            raise ValueError(f"action_dim: must be >= 1, got {self.action_dim}")
        if self.capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {self.capacity}")
        if self.capacity > 2 ** 31 - 1 - max(int(self.max_neighbours), 0):
            # int32 slots, with K's padding keyed above every slot (hedger_jax.canonical).
            raise ValueError(f"capacity: must be below 2**31 - max_neighbours (int32 slot "
                             f"indices), got {self.capacity}")
        d = self.dim
        set_("input_offset", _tuple_of_floats("input_offset", 0.0 if self.input_offset is None
                                              else self.input_offset, d))
        set_("input_scale", _tuple_of_floats("input_scale", 1.0 if self.input_scale is None
                                             else self.input_scale, d))
        if any(s <= 0 for s in self.input_scale):
            raise ValueError(f"input_scale: every entry must be > 0, got {self.input_scale}")
        if not (math.isfinite(self.bandwidth) and self.bandwidth > 0):
            raise ValueError(f"bandwidth: must be a finite number > 0, got {self.bandwidth}")
        if not (0.0 < self.min_weight < 1.0):
            raise ValueError(f"min_weight: must be in (0, 1), got {self.min_weight}")
        if isinstance(self.kernel_k, bool) or int(self.kernel_k) != self.kernel_k \
                or self.kernel_k < 0:
            raise ValueError(f"kernel_k: must be an integer >= 0, got {self.kernel_k!r}")
        set_("kernel_k", int(self.kernel_k))
        if self.kernel_k > 0 and self.discrete_actions is None:
            warn_data_chosen_width_with_continuous_actions(self)
        if not (math.isfinite(self.kernel_range) and self.kernel_range >= 1.0):
            raise ValueError(f"kernel_range: must be a finite number >= 1, got "
                             f"{self.kernel_range}")
        set_("kernel_range", float(self.kernel_range))
        if isinstance(self.bandwidth_k, bool) or int(self.bandwidth_k) != self.bandwidth_k \
                or not 0 <= self.bandwidth_k <= BANDWIDTH_POOL:
            raise ValueError(f"bandwidth_k: must be an integer in [0, {BANDWIDTH_POOL}] (the "
                             f"pool the width is read from), got {self.bandwidth_k!r}")
        set_("bandwidth_k", int(self.bandwidth_k))
        if self.bandwidth_k > 0 and self.kernel_k > 0:
            raise ValueError("bandwidth_k and kernel_k: choose one data-chosen width (one for "
                             "the memory, or one per query), got both > 0")
        if not (0.0 <= self.region_scale <= 1.0):
            raise ValueError(f"region_scale: must be in [0, 1], got {self.region_scale}")
        set_("region_scale", float(self.region_scale))
        if not (math.isfinite(self.value_eps) and self.value_eps >= 0.0):
            raise ValueError(f"value_eps: must be a finite number >= 0, got {self.value_eps}")
        set_("value_eps", float(self.value_eps))
        if not (math.isfinite(self.greedy_temperature) and self.greedy_temperature >= 0.0):
            raise ValueError(f"greedy_temperature: must be a finite number >= 0, got "
                             f"{self.greedy_temperature}")
        set_("greedy_temperature", float(self.greedy_temperature))
        if self.k_thresh is None:
            set_("k_thresh", selection_radius(self.bandwidth, self.min_weight, self.kernel_k,
                                              self.kernel_range, self.bandwidth_k))
        if not (math.isfinite(self.k_thresh) and self.k_thresh > 0):
            raise ValueError(f"k_thresh: must be a finite number > 0, got {self.k_thresh}")
        set_("k_thresh", float(self.k_thresh))
        if self.max_bandwidth is None:
            set_("max_bandwidth", float(self.bandwidth))
        if not (math.isfinite(self.max_bandwidth) and self.max_bandwidth >= self.bandwidth):
            raise ValueError(f"max_bandwidth: must be a finite number >= bandwidth "
                             f"({self.bandwidth}), got {self.max_bandwidth}")
        set_("max_bandwidth", float(self.max_bandwidth))
        if self.k_min is None:
            set_("k_min", d + 1)
        if isinstance(self.k_min, bool) or int(self.k_min) != self.k_min:
            raise ValueError(f"k_min: must be an integer, got {self.k_min!r}")
        set_("k_min", int(self.k_min))
        if self.k_min < d + 1:
            raise ValueError(f"k_min: must be >= the number of regression parameters "
                             f"(dim + 1 = {d + 1}), got {self.k_min}")
        if self.max_neighbours < self.k_min:
            raise ValueError(f"max_neighbours: must be >= k_min ({self.k_min}), "
                             f"got {self.max_neighbours}")
        for name in ("alpha", "gamma"):
            value = float(getattr(self, name))
            if not (0.0 <= value <= 1.0):
                raise ValueError(f"{name}: must be in [0, 1], got {value}")
            set_(name, value)
        if not math.isfinite(self.default_value):
            raise ValueError(f"default_value: must be finite, got {self.default_value}")
        set_("default_value", float(self.default_value))
        set_("action_low", _tuple_of_floats("action_low", self.action_low, self.action_dim))
        set_("action_high", _tuple_of_floats("action_high", self.action_high, self.action_dim))
        if any(lo >= hi for lo, hi in zip(self.action_low, self.action_high)):
            raise ValueError(f"action_low/action_high: need low < high, got "
                             f"{self.action_low} / {self.action_high}")
        if self.discrete_actions is not None:
            try:
                acts = tuple(tuple(float(x) for x in (a if hasattr(a, "__len__") else (a,)))
                             for a in self.discrete_actions)
            except TypeError as err:
                raise ValueError(f"discrete_actions: not a sequence of actions ({err})") from None
            if len(acts) < 1 or any(len(a) != self.action_dim for a in acts):
                raise ValueError(f"discrete_actions: need >= 1 actions of length "
                                 f"action_dim={self.action_dim}, got {acts}")
            if not all(math.isfinite(x) for a in acts for x in a):
                raise ValueError("discrete_actions: values must be finite")
            set_("discrete_actions", acts)
            if self.greedy_temperature > 0:
                raise ValueError("greedy_temperature: must be 0 with discrete actions (a "
                                 "weighted mean of them is not one of them), got "
                                 f"{self.greedy_temperature}")
        if self.greedy_samples < 3:
            raise ValueError(f"greedy_samples: must be >= 3, got {self.greedy_samples}")
        if self.greedy_iters < 0:
            raise ValueError(f"greedy_iters: must be >= 0, got {self.greedy_iters}")
        if not (self.greedy_tol > 0):
            raise ValueError(f"greedy_tol: must be > 0, got {self.greedy_tol}")
        if self.full_policy not in FULL_POLICIES:
            raise ValueError(f"full_policy: must be one of {FULL_POLICIES}, got {self.full_policy!r}")
        if not (0.0 < self.ridge < 1.0):
            raise ValueError(f"ridge: must be in (0, 1), got {self.ridge}")
        if not (0.0 <= self.ivh_tol < 1.0):
            raise ValueError(f"ivh_tol: must be in [0, 1), got {self.ivh_tol}")
        for name in ("use_ivh", "region_update", "random_ties", "guess_unknown",
                     "bandwidth_shrink", "clip_to_neighbours", "replay_floor"):
            set_(name, bool(getattr(self, name)))
        if self.neighbour_index not in NEIGHBOUR_INDEXES:
            raise ValueError(f"neighbour_index: must be one of {NEIGHBOUR_INDEXES}, "
                             f"got {self.neighbour_index!r}")
        if self.neighbour_index == "grid" and self.capacity > GRID_MAX_CAPACITY:
            raise ValueError(f"capacity: the grid index holds at most {GRID_MAX_CAPACITY} slots, "
                             f"got {self.capacity}; use neighbour_index='brute'")
        if self.index_chunk is not None:
            if isinstance(self.index_chunk, bool) or int(self.index_chunk) != self.index_chunk \
                    or int(self.index_chunk) < 1:
                raise ValueError(f"index_chunk: must be None or an integer >= 1, "
                                 f"got {self.index_chunk!r}")
            set_("index_chunk", int(self.index_chunk))
        if self.index_levels is not None:
            if isinstance(self.index_levels, bool) or int(self.index_levels) != self.index_levels \
                    or int(self.index_levels) < 1:
                raise ValueError(f"index_levels: must be None or an integer >= 1, "
                                 f"got {self.index_levels!r}")
            set_("index_levels", int(self.index_levels))
        if self.index_recent is not None:
            if isinstance(self.index_recent, bool) \
                    or int(self.index_recent) != self.index_recent or int(self.index_recent) < 0:
                raise ValueError(f"index_recent: must be None or an integer >= 0, "
                                 f"got {self.index_recent!r}")
            set_("index_recent", int(self.index_recent))
        if self.index_bounds is not None:
            try:
                bounds = tuple((float(lo), float(hi)) for lo, hi in self.index_bounds)
            except (TypeError, ValueError):
                raise ValueError("index_bounds: expected one (lo, hi) pair per input "
                                 f"dimension, got {self.index_bounds!r}") from None
            if len(bounds) != d or not all(math.isfinite(lo) and math.isfinite(hi) and lo <= hi
                                           for lo, hi in bounds):
                raise ValueError(f"index_bounds: expected {d} finite (lo, hi) pairs with "
                                 f"lo <= hi, got {self.index_bounds!r}")
            set_("index_bounds", bounds)
        if self.discrete_actions is None and self.action_dim != 1:
            raise ValueError("action_dim: the continuous greedy search supports action_dim == 1; "
                             "use discrete_actions for multi-dimensional actions")

    # ------------------------------------------------------------------ derived
    @property
    def dim(self) -> int:
        """Dimension d of a query (state_dim + action_dim)."""
        return self.state_dim + self.action_dim

    @property
    def n_params(self) -> int:
        """Parameters of the local linear model (intercept + d slopes)."""
        return self.dim + 1

    @property
    def max_k_thresh(self) -> float:
        """The largest selection radius a ``HedgerParams`` may use with this config: k_thresh
        scaled up to ``max_bandwidth`` (what the grid index's cells are sized for)."""
        return self.k_thresh * self.max_bandwidth / self.bandwidth

    @property
    def index_kind(self) -> str:
        """The neighbour search in use: "brute" or "grid" ("auto" resolved by capacity and
        dimension, and above ``AUTO_GRID_LOW_DIM`` dimensions by the scanned fraction: see
        the AUTO_GRID_* constants)."""
        if self.neighbour_index == "auto":
            low_dim = self.dim <= AUTO_GRID_LOW_DIM
            threshold = AUTO_GRID_CAPACITY_LOW_DIM if low_dim else AUTO_GRID_CAPACITY
            if self.capacity < threshold or self.capacity > GRID_MAX_CAPACITY:
                return "brute"
            if low_dim:
                return "grid"
            from hedger_jax.index import scanned_fraction

            return "grid" if scanned_fraction(self) <= AUTO_GRID_MAX_FRACTION else "brute"
        return self.neighbour_index

    @property
    def is_discrete(self) -> bool:
        """Whether the actions are a discrete set (else the continuous box)."""
        return self.discrete_actions is not None

    def replace(self, **changes: Any) -> "HedgerConfig":
        """A copy with some fields changed, re-validated. Unless given, k_thresh is derived
        again when bandwidth or min_weight changes, k_min when state_dim or action_dim
        changes, and max_bandwidth when bandwidth changes and it equalled bandwidth."""
        if {"bandwidth", "min_weight", "kernel_k", "kernel_range"} & set(changes):
            changes.setdefault("k_thresh", None)
        if "bandwidth" in changes and self.max_bandwidth == self.bandwidth:
            changes.setdefault("max_bandwidth", None)
        if "state_dim" in changes or "action_dim" in changes:
            changes.setdefault("k_min", None)
        return dataclasses.replace(self, **changes)

    @classmethod
    def for_env(cls, env: Any, params: Any = None, *, action_scale: Any = 1.0,
                **overrides: Any) -> "HedgerConfig":
        """A config for a functional environment (see ``envs.base``).

        Observations are scaled to [0, 1] by ``env.obs_bounds(params)``; actions are
        multiplied by ``action_scale``: a number or one per action dimension (raw by default,
        as in the paper's discrete set {-1, 0, 1}), or ``"bounds"`` for 1 / (high - low) of
        the action space, so that the action range spans 1 like the states'. The action
        space (discrete set or box) comes from ``env.action_space``.
        """
        import numpy as np

        if params is None:
            params = env.default_params()
        low, high = (np.asarray(b, dtype=np.float64) for b in env.obs_bounds(params))
        space = env.action_space
        a_dim = space.action_dim
        if isinstance(action_scale, str):
            if action_scale != "bounds":
                raise ValueError(f"action_scale: a number, one per action dimension, or "
                                 f"'bounds', got {action_scale!r}")
            span = np.asarray(space.high, np.float64) - np.asarray(space.low, np.float64)
            if not np.all(np.isfinite(span) & (span > 0)):
                raise ValueError(f"action_scale='bounds': the action bounds must be finite "
                                 f"with high > low, got low={space.low}, high={space.high}")
            action_scale = 1.0 / span
        a_scale = np.broadcast_to(np.asarray(action_scale, dtype=np.float64), (a_dim,))
        kwargs = dict(
            state_dim=int(low.shape[0]),
            action_dim=a_dim,
            input_offset=tuple(low.tolist()) + (0.0,) * a_dim,
            input_scale=tuple((1.0 / (high - low)).tolist()) + tuple(a_scale.tolist()),
            discrete_actions=space.values,
            action_low=space.low,
            action_high=space.high,
        )
        kwargs.update(overrides)
        return cls(**kwargs)
