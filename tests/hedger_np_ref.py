"""Independent float64 NumPy reference for HEDGER's Algorithms 1 and 2 (test-only).

Written from the specification, never from the library: nothing here imports ``hedger_jax``.
Conventions (the same as the library's documented ones):

* scaled input  z = (concat(s, a) - input_offset) * input_scale
* K             = valid stored points with ||z_i - z_q|| <= k_thresh, the ``max_neighbours``
                  nearest of them
* |K| < k_min   -> (default_value, unknown)
* IVH           X = [1, z_i - z_q] (rows: K, unweighted), x_q = e_0; inside iff
                  x_q'(X'X)^-1 x_q <= (1 + ivh_tol) * max_i V_ii,  V = X (X'X)^-1 X'
* LWR           kappa_i = exp(-||z_q - z_i||^2 / h^2); weighted least squares of the values on X;
                  the prediction is the intercept.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Optional

import numpy as np


def default_k_thresh(bandwidth: float, min_weight: float = 0.01) -> float:
    return bandwidth * math.sqrt(math.log(1.0 / min_weight))


class RefPrediction(NamedTuple):
    value: float
    known: bool
    n: int
    idx: np.ndarray          # memory slots of K, nearest first
    dist: np.ndarray         # their distances
    kappa: np.ndarray        # their kernel weights
    ivh_lhs: float           # x_q'(X'X)^-1 x_q  (nan when |K| < k_min)
    ivh_rhs: float           # (1 + ivh_tol) max V_ii
    ambiguous: bool          # True when float32 rounding could flip a discrete decision


def scale(s, a, offset=None, scale_=None) -> np.ndarray:
    x = np.concatenate([np.atleast_1d(np.asarray(s, np.float64)),
                        np.atleast_1d(np.asarray(a, np.float64))])
    off = np.zeros_like(x) if offset is None else np.asarray(offset, np.float64)
    sc = np.ones_like(x) if scale_ is None else np.asarray(scale_, np.float64)
    return (x - off) * sc


def to_fit(q, value_eps: float = 0.0):
    """The fit's value space: q, or sign(q) log1p(|q| / value_eps)."""
    q = np.asarray(q, np.float64)
    return q if value_eps == 0 else np.sign(q) * np.log1p(np.abs(q) / value_eps)


def from_fit(y, value_eps: float = 0.0):
    y = np.asarray(y, np.float64)
    return y if value_eps == 0 else np.sign(y) * value_eps * np.expm1(np.abs(y))


def ref_predict(points: np.ndarray, values: np.ndarray, size: int, zq: np.ndarray, *,
                bandwidth: float, k_thresh: Optional[float] = None, k_min: int,
                max_neighbours: int, default_value: float = 0.0, use_ivh: bool = True,
                ivh_tol: float = 1e-3, rel_margin: float = 1e-4,
                value_eps: float = 0.0, clip_to_neighbours: bool = False) -> RefPrediction:
    """Algorithm 1 in float64. ``points``: (N, d) rows = stored scaled inputs; slots >= size
    are empty and ignored. ``values`` are raw Q values; with ``value_eps`` the fit is made
    on ``to_fit`` of them and its intercept mapped back; ``clip_to_neighbours`` clips the
    intercept to the neighbours' (fit-space) values' range first."""
    points = np.asarray(points, np.float64)[:size]
    values = np.asarray(values, np.float64)[:size]
    zq = np.asarray(zq, np.float64)
    if k_thresh is None:
        k_thresh = default_k_thresh(bandwidth)
    d = np.linalg.norm(points - zq[None, :], axis=1) if size else np.zeros(0)
    ambiguous = bool(np.any(np.abs(d - k_thresh) <= rel_margin * k_thresh))
    inside_r = np.nonzero(d <= k_thresh)[0]
    order = inside_r[np.argsort(d[inside_r], kind="stable")]
    if len(order) > max_neighbours:
        # a near-tie at the cut-off could be resolved either way in float32
        gap = d[order[max_neighbours]] - d[order[max_neighbours - 1]]
        ambiguous |= bool(gap <= rel_margin * max(k_thresh, 1e-30))
        order = order[:max_neighbours]
    idx = order
    dist = d[idx]
    h = bandwidth
    kappa = np.exp(-dist ** 2 / h ** 2)
    n = len(idx)
    if n < k_min:
        return RefPrediction(float(default_value), False, n, idx, dist, kappa,
                             float("nan"), float("nan"), ambiguous)
    X = np.concatenate([np.ones((n, 1)), points[idx] - zq[None, :]], axis=1)
    G = X.T @ X
    Gi = np.linalg.pinv(G, rcond=1e-12, hermitian=True)
    lhs = float(Gi[0, 0])
    # A singular X'X (duplicated / collinear points): the limit of x_q'(X'X + lam I)^-1 x_q as
    # lam -> 0 is infinite when x_q has a component in the null space of X'X (the query is
    # off the flat hull), and the pseudo-inverse value otherwise.
    evals, evecs = np.linalg.eigh(G)
    null = evecs[:, evals <= 1e-10 * max(evals.max(), 1e-300)]
    if null.shape[1] and np.linalg.norm(null[0, :]) > 1e-6:
        lhs = float("inf")
    v = np.einsum("ij,jk,ik->i", X, Gi, X)
    rhs = float((1.0 + ivh_tol) * v.max())
    if use_ivh:
        ambiguous |= bool(abs(lhs - rhs) <= 1e-3 * rhs)
        if lhs > rhs:
            return RefPrediction(float(default_value), False, n, idx, dist, kappa, lhs, rhs,
                                 ambiguous)
    sw = np.sqrt(kappa)[:, None]
    y = to_fit(values[idx], value_eps)
    beta, *_ = np.linalg.lstsq(X * sw, y * sw[:, 0], rcond=None)
    intercept = float(np.clip(beta[0], y.min(), y.max())) if clip_to_neighbours else beta[0]
    return RefPrediction(float(from_fit(intercept, value_eps)), True, n, idx, dist, kappa, lhs,
                         rhs, ambiguous)


@dataclasses.dataclass
class RefParams:
    """The subset of HedgerConfig the reference needs (kept separate on purpose)."""
    bandwidth: float
    k_min: int
    max_neighbours: int
    k_thresh: Optional[float] = None
    default_value: float = 0.0
    use_ivh: bool = True
    ivh_tol: float = 1e-3
    alpha: float = 0.8
    gamma: float = 0.8
    region_update: bool = True
    discrete_actions: Optional[tuple] = None
    value_eps: float = 0.0
    clip_to_neighbours: bool = False

    def predict(self, points, values, size, zq) -> RefPrediction:
        return ref_predict(points, values, size, zq, bandwidth=self.bandwidth,
                           k_thresh=self.k_thresh, k_min=self.k_min,
                           max_neighbours=self.max_neighbours,
                           default_value=self.default_value, use_ivh=self.use_ivh,
                           ivh_tol=self.ivh_tol, value_eps=self.value_eps,
                           clip_to_neighbours=self.clip_to_neighbours)


def ref_greedy_value_discrete(p: RefParams, points, values, size, s) -> float:
    best = -np.inf
    for a in p.discrete_actions:
        r = p.predict(points, values, size, scale(s, a))
        best = max(best, r.value if r.known else p.default_value)
    return float(best)


def ref_train_step(p: RefParams, points, values, size, s, a, r, s_next, terminated,
                   q_floor: float = -np.inf):
    """Algorithm 2 (discrete greedy max, identity input scaling); max_a' Q(s', a') is at
    least ``q_floor``. Returns (new_points (N+1,d), new_values (N+1,), q, q_next, q_new,
    pred)."""
    points = np.asarray(points, np.float64)[:size]
    values = np.asarray(values, np.float64)[:size].copy()
    zq = scale(s, a)
    pred = p.predict(points, values, size, zq)
    q = pred.value
    q_next = 0.0 if terminated else max(
        ref_greedy_value_discrete(p, points, values, size, s_next), q_floor)
    q_new = q + p.alpha * (r + p.gamma * q_next - q)
    # Region update and the new point in the fit's value space (the identity by default):
    # the returned values are as the memory stores them.
    stored = to_fit(values, p.value_eps)
    target = to_fit(q_new, p.value_eps)
    if p.region_update:
        kappa = pred.kappa
        stored[pred.idx] = stored[pred.idx] + kappa * (target - stored[pred.idx])
    new_points = np.concatenate([points, zq[None, :]], axis=0)
    new_values = np.concatenate([stored, [target]])
    return new_points, new_values, q, q_next, q_new, pred


def ref_train_episode(p: RefParams, points, values, size, episode, replay_floor=False):
    """Reverse replay of an episode (a dict of arrays obs (T,S), action (T,A), reward (T,),
    next_obs (T,S), terminated (T,), all steps valid), newest first; with ``replay_floor``
    each step's q_next is at least the q_new the step after it stored (value_eps 0). Returns
    (points, values, q_new (T,) in time order)."""
    points = np.asarray(points, np.float64)[:size]
    values = np.asarray(values, np.float64)[:size]
    T = len(episode["reward"])
    q_new = np.zeros(T)
    floor = -np.inf
    for t in reversed(range(T)):
        points, values, _, _, q_new[t], _ = ref_train_step(
            p, points, values, len(values), episode["obs"][t], episode["action"][t],
            float(episode["reward"][t]), episode["next_obs"][t], bool(episode["terminated"][t]),
            floor)
        floor = q_new[t] if replay_floor else -np.inf
    return points, values, q_new


def replace_fields(obj, **kw):
    """Replace fields of a NamedTuple / (frozen) dataclass / flax-style struct pytree."""
    if hasattr(obj, "_replace"):
        return obj._replace(**kw)
    if dataclasses.is_dataclass(obj):
        return dataclasses.replace(obj, **kw)
    if hasattr(obj, "replace"):
        return obj.replace(**kw)
    raise TypeError(f"cannot replace fields of {type(obj)}")


def f32(x) -> np.ndarray:
    """Round to float32 (so that the library and the reference see identical inputs)."""
    return np.asarray(x, np.float32)
