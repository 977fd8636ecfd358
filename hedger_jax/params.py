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

from hedger_jax.config import HedgerConfig, selection_radius, traced_failure
from hedger_jax.errors import InvalidInputError, InvalidParamsError, StaticFieldError
from hedger_jax.run_config import RunConfig
from hedger_jax.settings import as_leaf, fields_of, first_failure, spec
from hedger_jax.validation import expect

#: Fields of ``HedgerParams``, in order: ``HedgerConfig``'s traced fields, then ``RunConfig``'s.
CONFIG_FIELDS = fields_of(HedgerConfig)
RUN_FIELDS = fields_of(RunConfig)
FIELDS = CONFIG_FIELDS + RUN_FIELDS
#: Each field's ``Spec`` (kind, range): the declarations in ``HedgerConfig`` / ``RunConfig``.
SPECS = {**{n: spec(HedgerConfig, n) for n in CONFIG_FIELDS},
         **{n: spec(RunConfig, n) for n in RUN_FIELDS}}
#: The fields k_thresh is derived from (its declaration's ``derived_from``).
_RADIUS_FIELDS = SPECS["k_thresh"].derived_from


class HedgerParams(NamedTuple("_HedgerParamsFields", [(n, Any) for n in FIELDS])):
    """HEDGER's traced settings, one field per traced ``HedgerConfig``/``RunConfig`` field
    (``FIELDS``; their meaning is documented there): each a scalar (float32; int32 for
    ``k_min`` and ``bandwidth_k``; bool for the switches) or a (d,) float32 vector for the
    input scaling. A sweep gives every leaf the same leading batch axes (vmap over them)."""

    __slots__ = ()

    @classmethod
    def defaults(cls, config: HedgerConfig, run: Optional[RunConfig] = None) -> "HedgerParams":
        """The config's (and run config's; else ``RunConfig()``'s) values as NumPy leaves of
        the canonical dtypes, unchecked: what every ``params=None`` means. The same leaves
        as ``create(config, run)``, so both give one compiled program."""
        run = RunConfig() if run is None else run
        values = {n: getattr(config, n) for n in CONFIG_FIELDS}
        values.update({n: getattr(run, n) for n in RUN_FIELDS})
        params = _as_leaves(config, values)
        if config.is_derived("k_thresh"):
            params = params._replace(k_thresh=_radius(*(getattr(params, n)
                                                        for n in _RADIUS_FIELDS)))
        return params

    @classmethod
    def create(cls, config: HedgerConfig, run: Optional[RunConfig] = None,
               **values: Any) -> "HedgerParams":
        """Params from the config's (and ``run``'s) values, with some replaced by ``values``
        (numbers or arrays; arrays give a sweep: every leaf is broadcast to their common batch
        shape). ``k_thresh`` is derived again from its inputs unless given. Checked on the
        host against the config (``check_params``); a static config field raises
        ``StaticFieldError``, an unknown one ``TypeError``."""
        unknown = sorted(set(values) - set(FIELDS))
        if unknown:
            static = [n for n in unknown if n in HedgerConfig.__dataclass_fields__
                      or n in RunConfig.__dataclass_fields__]
            if static:
                owner = "HedgerConfig" if static[0] in HedgerConfig.__dataclass_fields__ \
                    else "RunConfig"
                raise StaticFieldError(
                    f"{static[0]}: a static {owner} field (it fixes shapes or loop "
                    "lengths), not a HedgerParams field; sweep it with one program per value")
            raise TypeError(f"HedgerParams.create: unknown fields {unknown}; known: {FIELDS}")
        params = cls.defaults(config, run).replace(**values)
        return check_params(config, params)

    def replace(self, **values: Any) -> "HedgerParams":
        """A copy with some fields changed, all leaves broadcast to one batch shape;
        ``k_thresh`` is derived again when a field it derives from changes (and it is not
        given). Concrete leaves stay NumPy (the leaves ``create`` gives); traced ones are
        computed with jax.numpy. No host check: use ``check_params`` for that."""
        derive = "k_thresh" not in values and bool(set(values) & set(_RADIUS_FIELDS))
        merged = self._replace(**values)
        if any(_is_traced(v) for v in merged):
            if derive:
                merged = merged._replace(k_thresh=_radius_traced(
                    *(getattr(merged, n) for n in _RADIUS_FIELDS)))
            return merged
        d = np.shape(self.input_scale)[-1]
        try:
            leaves = {n: as_leaf(SPECS[n].kind, n, getattr(merged, n), d) for n in FIELDS}
        except ValueError as err:
            raise InvalidParamsError(str(err)) from None
        if derive:
            leaves["k_thresh"] = _radius(*(leaves[n] for n in _RADIUS_FIELDS))
        return _broadcast(leaves, d)


def _is_traced(value: Any) -> bool:
    import jax

    return isinstance(value, jax.core.Tracer)


def _radius(bandwidth, min_weight, kernel_range, bandwidth_k) -> np.ndarray:
    """``selection_radius`` of float32 leaves, in float64, as a float32 leaf: the one
    derivation of the concrete params' k_thresh (``defaults``, ``create``, ``replace``)."""
    return np.asarray(selection_radius(bandwidth, min_weight, kernel_range, bandwidth_k),
                      np.float64).astype(np.float32)


def _radius_traced(bandwidth, min_weight, kernel_range, bandwidth_k):
    """``_radius`` in float32 jax.numpy, for traced leaves."""
    import jax.numpy as jnp

    h = jnp.asarray(bandwidth, jnp.float32) * jnp.where(
        jnp.asarray(bandwidth_k) > 0, jnp.asarray(kernel_range, jnp.float32), 1.0)
    return h * jnp.sqrt(jnp.log(1.0 / jnp.asarray(min_weight, jnp.float32)))


def _as_leaves(config: HedgerConfig, values: dict) -> HedgerParams:
    """``HedgerParams`` with NumPy leaves of the canonical dtypes, broadcast to one batch
    shape (a scalar input scaling becomes a (d,) vector)."""
    d = config.dim
    try:
        leaves = {n: as_leaf(SPECS[n].kind, n, values[n], d) for n in FIELDS}
    except ValueError as err:
        raise InvalidParamsError(str(err)) from None
    return _broadcast(leaves, d)


def _broadcast(leaves: dict, d: int) -> HedgerParams:
    vector = lambda n: SPECS[n].kind == "vector"  # noqa: E731
    try:
        batch = np.broadcast_shapes(*[leaves[n].shape[:-1] if vector(n) else leaves[n].shape
                                      for n in FIELDS])
    except ValueError as err:
        raise InvalidParamsError(f"params: the fields' batch shapes differ ({err})") from None
    return HedgerParams(**{n: np.broadcast_to(leaves[n], batch + ((d,) if vector(n) else ()))
                           .copy() for n in FIELDS})


def check_params(config: HedgerConfig, params: HedgerParams) -> HedgerParams:
    """Host-side check of (concrete) params against their declared ranges and the static
    config (``config.traced_failure``: k_min, the selection radius against
    ``max_bandwidth``). Raises ``InvalidParamsError`` naming
    the field. Returns the params."""
    p = {name: np.asarray(getattr(params, name)) for name in FIELDS}
    failure = first_failure(FIELDS, p, SPECS) or traced_failure(config, p)
    if failure:
        raise InvalidParamsError(failure)
    return params


def resolve(config: HedgerConfig, params: Optional[HedgerParams]) -> HedgerParams:
    """``params``, or the config's defaults as constants when None. Given params are checked
    when traced: one setting (scalars, (d,) input scaling), else ``InvalidInputError``
    naming the field (a batch of settings is for ``vmap``)."""
    if params is None:
        return HedgerParams.defaults(config)
    if not isinstance(params, HedgerParams):
        raise InvalidInputError(f"params: expected a HedgerParams, got {type(params).__name__}")
    for name in FIELDS:
        kind = SPECS[name].kind
        expect(f"params.{name}", getattr(params, name),
               (config.dim,) if kind == "vector" else (), "bool" if kind == "switch" else "real")
    return params


def constant(value: Any) -> Any:
    """The Python value of a setting known at trace time (a number or a concrete 0-d array),
    else None (a traced value, or a batch)."""
    if _is_traced(value) or np.ndim(value) != 0:
        return None
    return np.asarray(value).item()


def to_fit_space(p: HedgerParams, q: Any) -> Any:
    """Values as the memory stores and the fit sees them: q itself (``value_eps`` 0, the
    paper), else sign(q) log1p(|q| / value_eps), which turns values spanning orders of
    magnitude (gamma^steps) into numbers that change about linearly with the steps."""
    if constant(p.value_eps) == 0.0:
        return q
    import jax.numpy as jnp

    eps = jnp.asarray(p.value_eps, jnp.float32)
    out = jnp.sign(q) * jnp.log1p(jnp.abs(q) / jnp.where(eps > 0, eps, 1.0))
    return jnp.where(eps > 0, out, q)


def from_fit_space(p: HedgerParams, y: Any) -> Any:
    """The inverse of ``to_fit_space``."""
    if constant(p.value_eps) == 0.0:
        return y
    import jax.numpy as jnp

    eps = jnp.asarray(p.value_eps, jnp.float32)
    out = jnp.sign(y) * eps * jnp.expm1(jnp.abs(y))
    return jnp.where(eps > 0, out, y)


def flag(value: Any, on: Any, off: Any):
    """``on`` where the switch ``value`` holds, else ``off``: a Python branch for a constant
    switch (the same program as a plain ``if``), a select for a traced one."""
    c = constant(value)
    if c is not None:
        return on if c else off
    import jax.numpy as jnp

    return jnp.where(value, on, off)
