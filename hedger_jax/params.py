"""HEDGER's numeric hyperparameters as traced values: ``HedgerParams``.

``HedgerConfig`` holds what fixes shapes and loop lengths (static under ``jit``);
``HedgerParams`` holds the numbers a sweep varies. Its leaves are arrays, so a grid of
settings is one program::

    params = HedgerParams.create(config, bandwidth=np.repeat([0.01, 0.02, 0.05], 8))
    keys = jax.random.split(key, 24)
    results = jax.jit(jax.vmap(make_train(env, config, run).train))(keys, params)

Every public function takes ``params=None``, meaning the config's values as compile-time
constants (``HedgerParams.defaults``): the program a config alone describes.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import numpy as np

from hedger_jax.config import (BANDWIDTH_POOL, HedgerConfig, StaticFieldError, selection_radius,
                               warn_data_chosen_width_with_continuous_actions)

#: Fields of ``HedgerParams``, in order.
FIELDS = ("bandwidth", "min_weight", "kernel_k", "kernel_range", "bandwidth_k",
          "bandwidth_shrink", "region_scale", "value_eps",
          "k_thresh",
          "k_min", "alpha", "gamma", "default_value",
          "ridge", "ivh_tol", "input_offset", "input_scale", "use_ivh", "region_update",
          "random_ties", "guess_unknown", "greedy_temperature", "clip_to_neighbours",
          "replay_floor", "epsilon", "noise_std")
#: The fields whose defaults come from ``RunConfig``, not ``HedgerConfig``.
RUN_FIELDS = ("epsilon", "noise_std")
#: The boolean switches.
_BOOLS = ("use_ivh", "region_update", "random_ties", "guess_unknown", "bandwidth_shrink",
          "clip_to_neighbours", "replay_floor")
#: The fields the selection radius k_thresh is derived from.
_RADIUS_FIELDS = ("bandwidth", "min_weight", "kernel_k", "kernel_range", "bandwidth_k")
#: The (d,) vectors; every other field is a scalar.
_VECTORS = ("input_offset", "input_scale")


class InvalidParamsError(ValueError):
    """A ``HedgerParams`` value is out of its range or beyond what the static config allows."""


class HedgerParams(NamedTuple):
    """HEDGER's traced settings: each a scalar, or a (d,) vector for the input scaling; a
    sweep gives every leaf the same leading batch axes (vmap over them).

    bandwidth: Gaussian kernel width h. min_weight: the weight at the selection radius;
    k_thresh: that radius, h sqrt(ln(1 / min_weight)) (derived by ``create``/``replace``).
    k_min: fewest neighbours for a prediction (int32). alpha, gamma: Q-learning's step size
    and discount. default_value: the "don't know" value. ridge, ivh_tol: numerics of the
    fit and the hull test. input_offset, input_scale: (d,) the query scaling
    z = (concat(s, a) - offset) * scale. use_ivh, region_update: the paper's ablation
    switches (bool). random_ties: the continuous greedy search breaks ties at random (bool).
    guess_unknown: where no candidate is known, the greedy action is guessed from the fits
    without the hull check before acting at random (bool; ``hedger_jax.greedy``).
    greedy_temperature: continuous actions only; > 0 makes the greedy action the mean of
    the search's samples weighted by exp((y - y_best) / greedy_temperature), y the values as
    the fit sees them (``to_fit_space``), and its value their values' mean with the same
    weights; 0 the best sample and its value (the paper).
    clip_to_neighbours: a known prediction is clipped to its neighbours' stored values' range
    (bool). replay_floor: the reverse replay takes max_a' Q(s', a') to be at least the value
    it has just stored for the next step (bool; ``hedger_jax.train``).
    bandwidth_k, bandwidth_shrink: the width read from the memory (int32, bool;
    ``hedger_jax.data_bandwidth``). epsilon, noise_std: exploration of the training runs.
    """

    bandwidth: Any
    min_weight: Any
    kernel_k: Any
    kernel_range: Any
    bandwidth_k: Any
    bandwidth_shrink: Any
    region_scale: Any
    value_eps: Any
    k_thresh: Any
    k_min: Any
    alpha: Any
    gamma: Any
    default_value: Any
    ridge: Any
    ivh_tol: Any
    input_offset: Any
    input_scale: Any
    use_ivh: Any
    region_update: Any
    random_ties: Any
    guess_unknown: Any
    greedy_temperature: Any
    clip_to_neighbours: Any
    replay_floor: Any
    epsilon: Any
    noise_std: Any

    @classmethod
    def defaults(cls, config: HedgerConfig, run: Any = None) -> "HedgerParams":
        """The config's (and run config's; else 0.2) values as Python numbers, compile-time
        constants inside a traced function: what every ``params=None`` means. Unchecked."""
        values = {name: getattr(config, name) for name in FIELDS if name not in RUN_FIELDS}
        values["epsilon"] = float(getattr(run, "epsilon", 0.2))
        values["noise_std"] = float(getattr(run, "noise_std", 0.2))
        return cls(**values)

    @classmethod
    def create(cls, config: HedgerConfig, run: Any = None, **values: Any) -> "HedgerParams":
        """Params from the config's (and ``run``'s epsilon / noise_std) values, with some
        replaced by ``values`` (numbers or arrays; arrays give a sweep: every leaf is
        broadcast to their common batch shape). ``k_thresh`` follows bandwidth and
        min_weight unless given. Checked on the host against the config (``check_params``);
        a static config field raises ``StaticFieldError``, an unknown one ``TypeError``.
        The leaves are NumPy arrays (float32, int32 k_min, bool switches)."""
        unknown = sorted(set(values) - set(FIELDS))
        if unknown:
            static = [n for n in unknown if n in HedgerConfig.__dataclass_fields__]
            if static:
                raise StaticFieldError(
                    f"{static[0]}: a static HedgerConfig field (it fixes shapes or loop "
                    "lengths), not a HedgerParams field; sweep it with one program per value")
            raise TypeError(f"HedgerParams.create: unknown fields {unknown}; known: {FIELDS}")
        base = cls.defaults(config, run)._asdict()
        if "k_thresh" not in values and set(values) & set(_RADIUS_FIELDS):
            base.pop("k_thresh")                      # derived again from the new values
        base.update(values)
        if "k_thresh" not in base:
            base["k_thresh"] = selection_radius(base["bandwidth"], base["min_weight"],
                                                base["kernel_k"], base["kernel_range"],
                                                base["bandwidth_k"])
        params = _as_arrays(config, base)
        check_params(config, params)
        if "kernel_k" in values and not config.is_discrete and np.any(params.kernel_k > 0):
            warn_data_chosen_width_with_continuous_actions(config)
        return params

    def replace(self, **values: Any) -> "HedgerParams":
        """A copy with some fields changed; ``k_thresh`` is derived again when bandwidth or
        min_weight changes (and is not given). Works on NumPy and traced leaves alike (no
        host check: use ``check_params`` for that)."""
        if "k_thresh" not in values and set(values) & set(_RADIUS_FIELDS):
            import jax.numpy as jnp

            get = lambda name: jnp.asarray(values.get(name, getattr(self, name)))  # noqa: E731
            h = get("bandwidth").astype(jnp.float32) * jnp.where(
                (get("kernel_k") > 0) | (get("bandwidth_k") > 0),
                get("kernel_range").astype(jnp.float32), 1.0)
            values["k_thresh"] = h * jnp.sqrt(jnp.log(1.0 / get("min_weight").astype(
                jnp.float32)))
        return self._replace(**values)


def _as_arrays(config: HedgerConfig, values: dict) -> HedgerParams:
    """``HedgerParams`` with NumPy leaves of the canonical dtypes, broadcast to one batch
    shape (a scalar input scaling becomes a (d,) vector)."""
    d = config.dim
    out = {}
    for name in FIELDS:
        v = np.asarray(values[name])
        if name in _VECTORS:
            if v.shape[-1:] != (d,):
                v = np.broadcast_to(v[..., None], v.shape + (d,)) if v.ndim == 0 or \
                    v.shape[-1] != d else v
            out[name] = v.astype(np.float32)
        elif name in _BOOLS:
            out[name] = v.astype(bool)
        elif name in ("k_min", "kernel_k", "bandwidth_k"):
            if np.any(np.asarray(v) != np.round(v)):
                raise InvalidParamsError(f"{name}: must be an integer, got {v}")
            out[name] = v.astype(np.int32)
        else:
            out[name] = v.astype(np.float32)
    batch = np.broadcast_shapes(*[out[n].shape[:-1] if n in _VECTORS else out[n].shape
                                  for n in FIELDS])
    for name in FIELDS:
        shape = batch + ((d,) if name in _VECTORS else ())
        out[name] = np.broadcast_to(out[name], shape).copy()
    return HedgerParams(**out)


def _bad(name: str, values: np.ndarray, ok: np.ndarray, rule: str):
    """Raise ``InvalidParamsError`` naming the field and its first bad value unless all ok."""
    if not np.all(ok):
        first = np.asarray(values)[~np.broadcast_to(ok, np.shape(values))].ravel()[0]
        raise InvalidParamsError(f"{name}: {rule}, got {first!r}")


def check_params(config: HedgerConfig, params: HedgerParams) -> HedgerParams:
    """Host-side check of (concrete) params against their ranges and the static config:
    finite values, 0 < min_weight < 1, alpha and gamma in [0, 1], k_min between the number
    of regression parameters and ``max_neighbours``, a positive input scale, and a
    selection radius ``k_thresh`` within the one the config's neighbour index is built
    for (``HedgerConfig.max_bandwidth``). Raises ``InvalidParamsError`` naming the field.
    Returns the params."""
    p = {name: np.asarray(getattr(params, name)) for name in FIELDS}
    for name in FIELDS:
        if name not in _BOOLS:
            _bad(name, p[name], np.isfinite(p[name]), "must be finite")
    _bad("bandwidth", p["bandwidth"], p["bandwidth"] > 0, "must be > 0")
    _bad("min_weight", p["min_weight"], (p["min_weight"] > 0) & (p["min_weight"] < 1),
         "must be in (0, 1)")
    _bad("k_thresh", p["k_thresh"], p["k_thresh"] > 0, "must be > 0")
    _bad("kernel_k", p["kernel_k"], (p["kernel_k"] >= 0) & (p["kernel_k"] <= config.max_neighbours),
         f"must be in [0, max_neighbours = {config.max_neighbours}]")
    _bad("kernel_range", p["kernel_range"], p["kernel_range"] >= 1, "must be >= 1")
    _bad("bandwidth_k", p["bandwidth_k"],
         (p["bandwidth_k"] >= 0) & (p["bandwidth_k"] <= BANDWIDTH_POOL),
         f"must be in [0, {BANDWIDTH_POOL}] (the pool the width is read from)")
    _bad("bandwidth_k", p["bandwidth_k"], (p["bandwidth_k"] == 0) | (p["kernel_k"] == 0),
         "and kernel_k: choose one data-chosen width (one for the memory, or one per "
         "query), both > 0")
    _bad("value_eps", p["value_eps"], p["value_eps"] >= 0, "must be >= 0")
    _bad("greedy_temperature", p["greedy_temperature"], p["greedy_temperature"] >= 0,
         "must be >= 0")
    if config.is_discrete:
        _bad("greedy_temperature", p["greedy_temperature"], p["greedy_temperature"] == 0,
             "must be 0 with discrete actions (a weighted mean of them is not one of them)")
    _bad("region_scale", p["region_scale"], (p["region_scale"] >= 0) & (p["region_scale"] <= 1),
         "must be in [0, 1]")
    for name in ("alpha", "gamma", "epsilon"):
        _bad(name, p[name], (p[name] >= 0) & (p[name] <= 1), "must be in [0, 1]")
    _bad("noise_std", p["noise_std"], p["noise_std"] >= 0, "must be >= 0")
    _bad("ridge", p["ridge"], (p["ridge"] > 0) & (p["ridge"] < 1), "must be in (0, 1)")
    _bad("ivh_tol", p["ivh_tol"], (p["ivh_tol"] >= 0) & (p["ivh_tol"] < 1), "must be in [0, 1)")
    _bad("input_scale", p["input_scale"], p["input_scale"] > 0, "every entry must be > 0")
    _bad("k_min", p["k_min"], (p["k_min"] >= config.dim + 1)
         & (p["k_min"] <= config.max_neighbours),
         f"must be in [dim + 1, max_neighbours] = [{config.dim + 1}, {config.max_neighbours}]")
    limit = config.max_k_thresh * (1.0 + 1e-6)
    if np.any(p["k_thresh"] > limit):
        worst = float(np.max(p["k_thresh"]))
        raise InvalidParamsError(
            f"bandwidth: the selection radius k_thresh = {worst:.6g} (bandwidth x "
            f"sqrt(ln(1 / min_weight))) exceeds the {config.max_k_thresh:.6g} the config's "
            f"neighbour index is built for (HedgerConfig.max_bandwidth = "
            f"{config.max_bandwidth}); raise max_bandwidth in the config")
    return params


def resolve(config: HedgerConfig, params: Optional[HedgerParams]) -> HedgerParams:
    """``params``, or the config's defaults as constants when None. Given params are checked
    when traced: one setting (scalars, (d,) input scaling), else ``InvalidInputError``
    naming the field (a batch of settings is for ``vmap``)."""
    if params is None:
        return HedgerParams.defaults(config)
    from hedger_jax.validation import InvalidInputError, expect

    if not isinstance(params, HedgerParams):
        raise InvalidInputError(f"params: expected a HedgerParams, got {type(params).__name__}")
    for name in FIELDS:
        shape = (config.dim,) if name in _VECTORS else ()
        expect(f"params.{name}", getattr(params, name), shape,
               "bool" if name in _BOOLS else "real")
    return params


def to_fit_space(p: HedgerParams, q: Any) -> Any:
    """Values as the memory stores and the fit sees them: q itself (``value_eps`` 0, the
    paper), else sign(q) log1p(|q| / value_eps), which turns values spanning orders of
    magnitude (gamma^steps) into numbers that change about linearly with the steps."""
    if isinstance(p.value_eps, float) and p.value_eps == 0.0:
        return q
    import jax.numpy as jnp

    eps = jnp.asarray(p.value_eps, jnp.float32)
    out = jnp.sign(q) * jnp.log1p(jnp.abs(q) / jnp.where(eps > 0, eps, 1.0))
    return jnp.where(eps > 0, out, q)


def from_fit_space(p: HedgerParams, y: Any) -> Any:
    """The inverse of ``to_fit_space``."""
    if isinstance(p.value_eps, float) and p.value_eps == 0.0:
        return y
    import jax.numpy as jnp

    eps = jnp.asarray(p.value_eps, jnp.float32)
    out = jnp.sign(y) * eps * jnp.expm1(jnp.abs(y))
    return jnp.where(eps > 0, out, y)


def flag(value: Any, on: Any, off: Any):
    """``on`` where the switch ``value`` holds, else ``off``: a Python branch for a constant
    switch (the same program as a plain ``if``), a select for a traced one."""
    if isinstance(value, (bool, np.bool_)):
        return on if value else off
    import jax.numpy as jnp

    return jnp.where(value, on, off)


