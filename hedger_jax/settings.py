"""Each setting of HEDGER declared once: ``setting(...)`` dataclass fields with their kind, range
and derivation in the field's metadata. ``HedgerConfig`` and ``RunConfig`` declare their fields
this way; ``HedgerParams`` (the traced fields), construction checks, ``replace``,
``HedgerParams.create``/``check_params`` and the docs' lists all read these declarations.

Kinds:
  * ``"static"``: fixes shapes, loop lengths or the program's structure (static under jit);
  * ``"number"``: a traced float32 scalar; ``"integer"``: a traced int32 scalar;
    ``"switch"``: a traced bool; ``"vector"``: a traced float32 (d,) vector.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Dict, Optional, Sequence, Tuple

import numpy as np

from hedger_jax.errors import StaticFieldError

TRACED_KINDS = ("number", "integer", "switch", "vector")
#: The NumPy dtype of each traced kind's leaves.
DTYPES = {"number": np.float32, "integer": np.int32, "switch": np.bool_, "vector": np.float32}


@dataclasses.dataclass(frozen=True)
class Spec:
    """A field's declaration.

    kind: one of ``"static"`` or ``TRACED_KINDS``.
    ok: for traced kinds, an elementwise range test on NumPy arrays (None: any finite value).
    rule: the message a value failing ``ok`` gets ("must be in [0, 1]").
    convert: for static kinds, ``convert(name, value, owner) -> value`` normalising and
      checking it (raises ``ValueError`` naming the field); owner is the half-built object.
    derived_from: the fields a ``None`` default is derived from (again on ``replace``).
    """

    kind: str
    ok: Optional[Callable[[np.ndarray], np.ndarray]] = None
    rule: str = ""
    convert: Optional[Callable[[str, Any, Any], Any]] = None
    derived_from: Tuple[str, ...] = ()


def setting(default: Any, kind: str, ok=None, rule: str = "", convert=None,
            derived_from: Sequence[str] = ()) -> Any:
    """A dataclass field declared with its ``Spec``."""
    assert kind == "static" or kind in TRACED_KINDS, kind
    spec = Spec(kind, ok, rule, convert, tuple(derived_from))
    return dataclasses.field(default=default, metadata={"spec": spec})


def spec(cls_or_obj: Any, name: str) -> Spec:
    """The ``Spec`` of field ``name``."""
    return cls_or_obj.__dataclass_fields__[name].metadata["spec"]


def fields_of(cls_or_obj: Any, kinds: Sequence[str] = TRACED_KINDS) -> Tuple[str, ...]:
    """The names of the declared fields of these kinds, in declaration order."""
    return tuple(f.name for f in dataclasses.fields(cls_or_obj)
                 if f.metadata["spec"].kind in kinds)


def reject_traced(owner: str, name: str, value: Any, traced_here: bool = False) -> None:
    """Raise ``StaticFieldError`` if ``value`` (or an element of nested tuples and lists) is
    a JAX tracer; the message says where a traced field belongs instead."""
    import jax

    items = value if isinstance(value, (tuple, list)) else (value,)
    for item in items:
        if isinstance(item, (tuple, list)):
            reject_traced(owner, name, item, traced_here)
        elif isinstance(item, jax.core.Tracer):
            hint = (f"put it in HedgerParams instead (HedgerParams.create(config, {name}=...)), "
                    "whose fields are traced" if traced_here else
                    "it fixes shapes or loop lengths; sweep it with one program per value")
            raise StaticFieldError(f"{name}: {owner} fields are static and cannot be traced "
                                   f"or vmapped; {hint}")


def as_leaf(kind: str, name: str, value: Any, d: int = 0) -> np.ndarray:
    """``value`` as a NumPy leaf of ``kind``'s dtype (a vector's scalar broadcast to (..., d));
    a non-integral ``"integer"`` raises ``ValueError`` naming the field."""
    v = np.asarray(value)
    if kind == "integer":
        if v.dtype.kind not in "biu" and np.any(v != np.round(v)):
            raise ValueError(f"{name}: must be an integer, got {value!r}")
    if kind == "vector" and (v.ndim == 0 or v.shape[-1] != d):
        v = np.broadcast_to(v[..., None], v.shape + (d,))
    return v.astype(DTYPES[kind])


def python_value(kind: str, name: str, value: Any, d: int = 0) -> Any:
    """``value`` as the Python value a config stores for a traced ``kind``: a float, an int
    (a non-integral value or a bool raises ``ValueError`` naming the field), a bool, or a
    tuple of d floats (a scalar is broadcast)."""
    if kind == "vector":
        return floats(name, value, d)
    try:
        if kind == "switch":
            return bool(value)
        if kind == "integer":
            if isinstance(value, bool) or not _is_integral(value):
                raise ValueError
            return int(value)
        return float(value)
    except (TypeError, ValueError):
        what = "an integer" if kind == "integer" else "a number"
        raise ValueError(f"{name}: must be {what}, got {value!r}") from None


def first_failure(names: Sequence[str], values: Dict[str, np.ndarray],
                  specs: Dict[str, Spec]) -> Optional[str]:
    """The message for the first of ``names`` whose values are not finite or fail their
    declared range (None if all pass)."""
    for name in names:
        s, v = specs[name], values[name]
        if s.kind != "switch":
            bad = ~np.isfinite(v)
            if np.any(bad):
                return f"{name}: {s.rule or 'must be finite'}, got {_first(v, bad)}"
        if s.ok is not None:
            bad = ~np.broadcast_to(s.ok(v), np.shape(v))
            if np.any(bad):
                return f"{name}: {s.rule}, got {_first(v, bad)}"
    return None


def _first(values: np.ndarray, bad: np.ndarray) -> str:
    """The first bad value, float32 leaves at their own precision (-0.1, not -0.100000001)."""
    value = np.asarray(values)[bad].ravel()[0]
    if value.dtype.kind == "f" and np.isfinite(value):
        plain = value == 0 or 1e-4 <= abs(value) < 1e16
        fmt = np.format_float_positional if plain else np.format_float_scientific
        return fmt(value, unique=True, trim="0")
    return repr(value.item())


# ------------------------------------------------------------------ static converters
def integer(low: int, high: Optional[int] = None, optional: bool = False):
    """A converter to an int within [low, high] (None allowed when ``optional``)."""
    def convert(name, value, owner):
        if value is None and optional:
            return None
        span = f">= {low}" if high is None else f"in [{low}, {high}]"
        if isinstance(value, bool) or not _is_integral(value):
            raise ValueError(f"{name}: must be {'None or ' if optional else ''}an integer "
                             f"{span}, got {value!r}")
        if int(value) < low or (high is not None and int(value) > high):
            raise ValueError(f"{name}: must be {span}, got {value!r}")
        return int(value)
    return convert


def positive_float(name, value, owner):
    """A converter to a finite float > 0."""
    if isinstance(value, bool) or not _finite_number(value) or float(value) <= 0:
        raise ValueError(f"{name}: must be a finite number > 0, got {value!r}")
    return float(value)


def choice(options: Tuple[str, ...]):
    """A converter accepting one of ``options``."""
    def convert(name, value, owner):
        if value not in options:
            raise ValueError(f"{name}: must be one of {options}, got {value!r}")
        return value
    return convert


def floats(name: str, value: Any, length: int) -> Tuple[float, ...]:
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


def _is_integral(value: Any) -> bool:
    try:
        return int(value) == value
    except (TypeError, ValueError, OverflowError):
        return False


def _finite_number(value: Any) -> bool:
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False
