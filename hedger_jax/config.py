"""Static configuration of a HEDGER learner: ``HedgerConfig``.

``HedgerConfig`` is a frozen, hashable dataclass: pass it as a static argument to ``jax.jit``
(or close over it). Each field is declared once with its kind (``hedger_jax.settings``):
static fields fix shapes and loop lengths; traced fields are the defaults of
``HedgerParams`` (``hedger_jax.params``), which carries them as traced values so that a sweep
over settings is one program. Every field is validated on construction: a bad value raises
``ValueError`` naming the field, a traced one ``StaticFieldError``.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict, Optional, Tuple

import numpy as np

from hedger_jax.errors import StaticFieldError  # noqa: F401 (re-exported)
from hedger_jax.index import GRID_MAX_CAPACITY, scanned_fraction
from hedger_jax.settings import (TRACED_KINDS, choice, fields_of, first_failure, floats,
                                 integer, positive_float, python_value, reject_traced, setting,
                                 spec)

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
#: Stored points the data-chosen width (``bandwidth_k``) counts neighbours among
#: (``hedger_jax.data_bandwidth``): ``bandwidth_k`` is at most this.
BANDWIDTH_POOL = 1024

def selection_radius(bandwidth, min_weight, kernel_range=1.0, bandwidth_k=0):
    """The default k_thresh: where the widest kernel's weight falls to ``min_weight``,
    bandwidth sqrt(ln(1 / min_weight)), times ``kernel_range`` with a data-chosen width
    (``bandwidth_k`` > 0). NumPy in (float64 arithmetic), NumPy out (a Python float for
    scalars)."""
    h = np.asarray(bandwidth, np.float64) * np.where(
        np.asarray(bandwidth_k) > 0, np.asarray(kernel_range, np.float64), 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = h * np.sqrt(np.log(1.0 / np.asarray(min_weight, np.float64)))
    return float(out) if np.ndim(out) == 0 else out


def _between(lo, hi, lo_open=False, hi_open=False):
    """(ok, rule) for a value in [lo, hi] (brackets per ``*_open``)."""
    ok = lambda v: ((v > lo) if lo_open else (v >= lo)) & ((v < hi) if hi_open else (v <= hi))  # noqa: E731
    return dict(ok=ok, rule=f"must be in {'(' if lo_open else '['}{lo:g}, {hi:g}"
                            f"{')' if hi_open else ']'}")


_POSITIVE = dict(ok=lambda v: v > 0, rule="must be a finite number > 0")
_NONNEG = dict(ok=lambda v: v >= 0, rule="must be a finite number >= 0")


def _actions(name, value, cfg):
    """``discrete_actions`` as a tuple of action_dim-tuples of finite floats (or None)."""
    if value is None:
        return None
    try:
        acts = tuple(tuple(float(x) for x in (a if hasattr(a, "__len__") else (a,)))
                     for a in value)
    except TypeError as err:
        raise ValueError(f"{name}: not a sequence of actions ({err})") from None
    if len(acts) < 1 or any(len(a) != cfg.action_dim for a in acts):
        raise ValueError(f"{name}: need >= 1 actions of length action_dim={cfg.action_dim}, "
                         f"got {acts}")
    if not all(math.isfinite(x) for a in acts for x in a):
        raise ValueError(f"{name}: values must be finite")
    return acts


def _bounds(name, value, cfg):
    """``index_bounds``: one finite (lo, hi) pair per input dimension, lo <= hi (or None)."""
    if value is None:
        return None
    try:
        out = tuple((float(lo), float(hi)) for lo, hi in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected one (lo, hi) pair per input dimension, "
                         f"got {value!r}") from None
    if len(out) != cfg.dim or not all(math.isfinite(lo) and math.isfinite(hi) and lo <= hi
                                      for lo, hi in out):
        raise ValueError(f"{name}: expected {cfg.dim} finite (lo, hi) pairs with lo <= hi, "
                         f"got {value!r}")
    return out


def _action_bound(name, value, cfg):
    return floats(name, value, cfg.action_dim)


def _max_bandwidth(name, value, cfg):
    """Default: ``bandwidth``; never below it."""
    value = cfg.bandwidth if value is None else value
    if not (positive_float(name, value, cfg) >= cfg.bandwidth):
        raise ValueError(f"{name}: must be a finite number >= bandwidth ({cfg.bandwidth}), "
                         f"got {value}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class HedgerConfig:
    """All settings of HEDGER (Smart & Kaelbling 2000, Algorithms 1 and 2); the static ones
    fix the program, the traced ones are ``HedgerParams``' defaults.

    Shapes: S = ``state_dim``, A = ``action_dim``, d = S + A (``dim``). A query is
    z = (concat(state, action) - ``input_offset``) * ``input_scale`` ((d,) each);
    ``for_env`` scales observations to [0, 1] from the env's bounds.

    Prediction (Algorithm 1): neighbours are the stored points within ``k_thresh`` (default
    bandwidth sqrt(ln(1 / min_weight)), where the weight exp(-d^2/h^2) falls to
    ``min_weight``), at most ``max_neighbours``; fewer than ``k_min`` (default d + 1) or a
    query outside the hull (``use_ivh``, tolerance ``ivh_tol``) gives ``default_value``.
    Training (Algorithm 2): ``alpha``, ``gamma``; ``region_update`` moves the neighbours too.
    Actions: ``discrete_actions``, or the box [``action_low``, ``action_high``] searched by
    ``greedy_samples`` samples and ``greedy_iters`` refinements to ``greedy_tol``.
    Memory: ``capacity`` points; ``full_policy`` "error" (drop and flag) or
    "overwrite_oldest". Neighbour search: ``neighbour_index`` and the ``index_*`` settings
    (``hedger_jax.index``); ``max_bandwidth`` the widest bandwidth a ``HedgerParams`` may use.

    Beyond the paper (off by default; docs/adaptive-kernel.md): ``bandwidth_k``,
    ``kernel_range`` and ``bandwidth_shrink`` (a width read from the stored data,
    ``hedger_jax.data_bandwidth``); ``value_eps`` (log-scale values); ``random_ties``,
    ``guess_unknown`` (the greedy choice, ``hedger_jax.greedy``);
    ``clip_to_neighbours`` (``hedger_jax.prediction``); ``replay_floor``
    (``hedger_jax.train``); ``backup_sweeps`` (memory-wide backups after every episode,
    ``hedger_jax.backup``; the memory then keeps each point's transition). ``ridge`` is the
    fit's relative ridge.
    """

    state_dim: int = setting(None, "static", convert=integer(1))
    action_dim: int = setting(1, "static", convert=integer(1))
    capacity: int = setting(20_000, "static", convert=integer(1))
    bandwidth: float = setting(0.015, "number", **_POSITIVE)
    k_thresh: Optional[float] = setting(
        None, "number", **_POSITIVE,
        derived_from=("bandwidth", "min_weight", "kernel_range", "bandwidth_k"))
    min_weight: float = setting(0.01, "number", **_between(0, 1, True, True))
    kernel_range: float = setting(4.0, "number", ok=lambda v: v >= 1,
                                 rule="must be a finite number >= 1")
    bandwidth_k: int = setting(0, "integer", **_between(0, BANDWIDTH_POOL))
    bandwidth_shrink: bool = setting(False, "switch")
    value_eps: float = setting(0.0, "number", **_NONNEG)
    k_min: Optional[int] = setting(None, "integer", derived_from=("state_dim", "action_dim"))
    max_neighbours: int = setting(32, "static", convert=integer(1))
    default_value: float = setting(0.0, "number")
    alpha: float = setting(0.8, "number", **_between(0, 1))
    gamma: float = setting(0.8, "number", **_between(0, 1))
    use_ivh: bool = setting(True, "switch")
    region_update: bool = setting(True, "switch")
    random_ties: bool = setting(False, "switch")
    guess_unknown: bool = setting(False, "switch")
    clip_to_neighbours: bool = setting(False, "switch")
    replay_floor: bool = setting(False, "switch")
    discrete_actions: Optional[Tuple[Tuple[float, ...], ...]] = setting(
        None, "static", convert=_actions)
    action_low: Tuple[float, ...] = setting((-1.0,), "static", convert=_action_bound)
    action_high: Tuple[float, ...] = setting((1.0,), "static", convert=_action_bound)
    greedy_samples: int = setting(11, "static", convert=integer(3))
    greedy_iters: int = setting(8, "static", convert=integer(0))
    greedy_tol: float = setting(1e-3, "static", convert=positive_float)
    full_policy: str = setting("error", "static", convert=choice(FULL_POLICIES))
    backup_sweeps: int = setting(0, "static", convert=integer(0))
    ridge: float = setting(1e-6, "number", **_between(0, 1, True, True))
    ivh_tol: float = setting(1e-3, "number", **_between(0, 1, hi_open=True))
    input_offset: Optional[Tuple[float, ...]] = setting(
        None, "vector", derived_from=("state_dim", "action_dim"))
    input_scale: Optional[Tuple[float, ...]] = setting(
        None, "vector", ok=lambda v: v > 0, rule="every entry must be > 0",
        derived_from=("state_dim", "action_dim"))
    neighbour_index: str = setting("auto", "static", convert=choice(NEIGHBOUR_INDEXES))
    index_chunk: Optional[int] = setting(None, "static", convert=integer(1, optional=True))
    index_bounds: Optional[Tuple[Tuple[float, float], ...]] = setting(
        None, "static", convert=_bounds)
    index_levels: Optional[int] = setting(None, "static", convert=integer(1, optional=True))
    index_recent: Optional[int] = setting(None, "static", convert=integer(0, optional=True))
    max_bandwidth: Optional[float] = setting(None, "static", convert=_max_bandwidth,
                                             derived_from=("bandwidth",))

    def __post_init__(self):
        for f in dataclasses.fields(self):
            reject_traced("HedgerConfig", f.name, getattr(self, f.name),
                          spec(self, f.name).kind in TRACED_KINDS)
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        set_("state_dim", integer(1)("state_dim", self.state_dim, self))
        set_("action_dim", integer(1)("action_dim", self.action_dim, self))
        values = self._traced_values()
        failure = first_failure(fields_of(self), {n: np.asarray(v) for n, v in values.items()},
                                {n: spec(self, n) for n in values})
        if failure:
            raise ValueError(failure)
        for name, value in values.items():
            set_(name, value)
        for f in dataclasses.fields(self):
            s = spec(self, f.name)
            if s.kind == "static" and f.name not in ("state_dim", "action_dim"):
                set_(f.name, s.convert(f.name, getattr(self, f.name), self))
        self._check_across_fields()

    def _traced_values(self) -> Dict[str, np.ndarray]:
        """The traced fields as Python values (the ``None`` defaults derived) in float64
        NumPy arrays, for the declared checks."""
        out = {}
        for name in fields_of(self):
            value = getattr(self, name)
            if value is None:
                value = {"input_offset": 0.0, "input_scale": 1.0, "k_min": self.dim + 1,
                         "k_thresh": 0.0}[name]
            out[name] = python_value(spec(self, name).kind, name, value, self.dim)
        if self.k_thresh is None:
            out["k_thresh"] = selection_radius(out["bandwidth"], out["min_weight"],
                                               out["kernel_range"], out["bandwidth_k"])
        return out

    def _check_across_fields(self) -> None:
        """The rules that tie fields together."""
        if self.capacity > 2 ** 31 - 1 - self.max_neighbours:
            # int32 slots, with K's padding keyed above every slot (hedger_jax.canonical).
            raise ValueError(f"capacity: must be below 2**31 - max_neighbours (int32 slot "
                             f"indices), got {self.capacity}")
        if self.k_min < self.dim + 1:
            raise ValueError(f"k_min: must be >= the number of regression parameters "
                             f"(dim + 1 = {self.dim + 1}), got {self.k_min}")
        if self.max_neighbours < self.k_min:
            raise ValueError(f"max_neighbours: must be >= k_min ({self.k_min}), "
                             f"got {self.max_neighbours}")
        if any(lo >= hi for lo, hi in zip(self.action_low, self.action_high)):
            raise ValueError(f"action_low/action_high: need low < high, got "
                             f"{self.action_low} / {self.action_high}")
        failure = traced_failure(self, {n: np.asarray(getattr(self, n)) for n in
                                        fields_of(self)})
        if failure:
            raise ValueError(failure)
        if self.neighbour_index == "grid" and self.capacity > GRID_MAX_CAPACITY:
            raise ValueError(f"capacity: the grid index holds at most {GRID_MAX_CAPACITY} slots, "
                             f"got {self.capacity}; use neighbour_index='brute'")
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
        dimension, and above ``AUTO_GRID_LOW_DIM`` dimensions by the scanned fraction)."""
        if self.neighbour_index != "auto":
            return self.neighbour_index
        low_dim = self.dim <= AUTO_GRID_LOW_DIM
        threshold = AUTO_GRID_CAPACITY_LOW_DIM if low_dim else AUTO_GRID_CAPACITY
        if self.capacity < threshold or self.capacity > GRID_MAX_CAPACITY:
            return "brute"
        if low_dim:
            return "grid"
        return "grid" if scanned_fraction(self) <= AUTO_GRID_MAX_FRACTION else "brute"

    @property
    def is_discrete(self) -> bool:
        """Whether the actions are a discrete set (else the continuous box)."""
        return self.discrete_actions is not None

    def replace(self, **changes: Any) -> "HedgerConfig":
        """A copy with some fields changed, re-validated: the same config as constructing
        with those values. A derived field (``Spec.derived_from``: ``k_thresh``, ``k_min``,
        ``max_bandwidth``, the input scaling) that holds its derived value is derived again
        when a field it derives from changes; one set to another value is kept."""
        for f in dataclasses.fields(self):
            inputs = spec(self, f.name).derived_from
            if f.name not in changes and set(inputs) & set(changes):
                if self.is_derived(f.name):
                    changes[f.name] = self._derive_again(f.name)
        return dataclasses.replace(self, **changes)

    def is_derived(self, name: str) -> bool:
        """Whether field ``name`` (one with ``derived_from``) holds the value its declaration
        derives from the other fields."""
        value = getattr(self, name)
        if name == "k_thresh":
            return math.isclose(value, selection_radius(
                self.bandwidth, self.min_weight, self.kernel_range, self.bandwidth_k),
                rel_tol=1e-12)
        if name == "k_min":
            return value == self.dim + 1
        if name == "max_bandwidth":
            return value == self.bandwidth
        return len(set(value)) == 1                 # a vector: one value broadcast

    def _derive_again(self, name: str) -> Any:
        """What to construct with to derive field ``name`` again: None, or a vector's one
        value."""
        return getattr(self, name)[0] if spec(self, name).kind == "vector" else None

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


def traced_failure(config: HedgerConfig, p: Dict[str, np.ndarray]) -> Optional[str]:
    """The rules tying traced values ``p`` (NumPy, any batch shape) to the static config:
    k_min within [dim + 1, max_neighbours], and a selection radius within what the neighbour index is built for. The message of the
    first broken one, else None."""
    k_min = p["k_min"]
    if np.any((k_min < config.dim + 1) | (k_min > config.max_neighbours)):
        bad = k_min[(k_min < config.dim + 1) | (k_min > config.max_neighbours)].ravel()[0]
        return (f"k_min: must be in [dim + 1, max_neighbours] = [{config.dim + 1}, "
                f"{config.max_neighbours}], got {bad}")
    if np.any(p["k_thresh"] > config.max_k_thresh * (1.0 + 1e-6)):
        return (f"bandwidth: the selection radius k_thresh = {float(np.max(p['k_thresh'])):.6g}"
                f" (bandwidth x sqrt(ln(1 / min_weight))) exceeds the "
                f"{config.max_k_thresh:.6g} the config's neighbour index is built for "
                f"(HedgerConfig.max_bandwidth = {config.max_bandwidth}); raise max_bandwidth "
                "in the config")
    return None
