"""Locally weighted linear regression and the independent-variable hull on a masked set.

Pure math, no knowledge of RL. Inputs are one query's neighbour set, *centred on the query*:
``zc`` (k, d) = neighbour - query, so the query is the origin and the design matrix of the
paper's formulation is X = [1, zc] (k, p = d + 1):

* the local linear fit at the query is the intercept of the weighted least-squares fit;
* the query's design row is x_q = e_0, and the IVH test is x_q'(X'X)^-1 x_q <= max_i v_ii,
  v_ii = x_i'(X'X)^-1 x_i.

Why an intercept column: with it v_ii = 1/n + the Mahalanobis distance of point i from the
neighbours' centroid, so the hull is Cook's ellipsoid centred on the data and the test is
invariant under affine changes of the inputs (without it the ellipsoid would be centred on
the coordinate origin, which means nothing here).

Computed through the centroid (the same quantities in exact arithmetic): with centroid m and
centred scatter C = sum (z_i - m)(z_i - m)', x_q'(X'X)^-1 x_q = 1/n + m'C^-1 m and
v_ii = 1/n + (z_i - m)'C^-1 (z_i - m); the weighted fit is y_w - b'm_w with
b = C_w^-1 sum w_i (z_i - m_w)(y_i - y_w) (weighted centroid m_w, mean value y_w, weighted
scatter C_w). Only d x d systems remain, centred on the data, so better conditioned than
the (d + 1) x (d + 1) normal equations; both are factorised together.

Numerics (float32): each scatter matrix is equilibrated (scaled to a unit diagonal, an exact
change of variables), then a tiny ridge is added before it is factorised. The values ``y``
enter only linearly, so tiny values (gamma^100 ~ 1e-10) keep their relative precision: there
is no absolute epsilon on them.

Layout: internally the neighbours are feature-major, ``zt`` (d, k) (``local_fit_columns``;
``local_fit`` takes (k, d) and transposes), so every sum over the k neighbours is a reduction
along the minor axis, which XLA's CPU backend vectorises. The hull test compares every
leverage with the query's (an ``any``) instead of taking their maximum first: the same answer
for finite values (x -> (1 + tol)(1/n + x) is non-decreasing in floating point too), without
XLA's NaN-propagating maximum, a serial loop.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class LocalFit(NamedTuple):
    """value: float32 () fitted value at the query (the intercept).
    inside: bool () query inside the independent-variable hull of the masked points.
    """

    value: jax.Array
    inside: jax.Array


def kernel_weights(sqdist: jax.Array, bandwidth: float, mask: jax.Array) -> jax.Array:
    """Gaussian kernel kappa_i = exp(-d_i^2 / h^2): sqdist (k,), bandwidth h (float or
    traced ()), mask (k,) -> float32 (k,), 0 where masked."""
    return jnp.where(mask, jnp.exp(-sqdist / jnp.float32(bandwidth) ** 2), 0.0)


def design_matrix(zc: jax.Array, mask: jax.Array) -> jax.Array:
    """X = [1, zc] with masked rows zeroed: zc (k, d), mask (k,) -> (k, d + 1)."""
    ones = jnp.ones(zc.shape[:-1] + (1,), zc.dtype)
    return jnp.concatenate([ones, zc], axis=-1) * mask[..., None].astype(zc.dtype)


def _cholesky(a: jax.Array) -> jax.Array:
    """Lower Cholesky factors of symmetric positive-definite matrices a (..., p, p).

    The Cholesky-Banachiewicz recurrence unrolled into scalar jnp ops: on the CPU a LAPACK
    call per tiny matrix costs more than the arithmetic, and the unrolled ops fuse (and
    vectorise under vmap). Cholesky, not the adjugate: for a nearly collinear neighbourhood
    the adjugate's determinant spreads the rounding of the ill-conditioned direction into
    the well-conditioned ones.
    """
    p = a.shape[-1]
    L = [[None] * p for _ in range(p)]
    for j in range(p):
        acc = a[..., j, j]
        for m in range(j):
            acc = acc - L[j][m] * L[j][m]
        L[j][j] = jnp.sqrt(acc)
        inv = 1.0 / L[j][j]
        for i in range(j + 1, p):
            acc = a[..., i, j]
            for m in range(j):
                acc = acc - L[i][m] * L[j][m]
            L[i][j] = acc * inv
    zero = jnp.zeros_like(a[..., 0, 0])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(p)], -1)
                      for i in range(p)], -2)


def _solve_lower(L: jax.Array, b: jax.Array) -> jax.Array:
    """Forward substitution: L (p, p) lower, b (p, ...) -> x (p, ...) with L x = b."""
    x = []
    for i in range(L.shape[-1]):
        acc = b[i]
        for m in range(i):
            acc = acc - L[i, m] * x[m]
        x.append(acc / L[i, i])
    return jnp.stack(x)


def _solve_upper_transposed(L: jax.Array, b: jax.Array) -> jax.Array:
    """Back substitution: L (p, p) lower, b (p,) -> x (p,) with L' x = b."""
    p = L.shape[-1]
    x = [None] * p
    for i in range(p - 1, -1, -1):
        acc = b[i]
        for m in range(i + 1, p):
            acc = acc - L[m, i] * x[m]
        x[i] = acc / L[i, i]
    return jnp.stack(x)


def _equilibrated_cholesky(C: jax.Array, ridge: float):
    """Scatter matrices C (..., p, p) -> (L (..., p, p), inv_s (..., p)) with
    L L' = D^-1 C D^-1 + ridge I, D = diag(sqrt(diag C)) = diag(1 / inv_s) (equilibration:
    an exact change of variables; a zero diagonal entry is left unscaled)."""
    p = C.shape[-1]
    diag = jnp.stack([C[..., i, i] for i in range(p)], -1)
    inv_s = jax.lax.rsqrt(jnp.where(diag > 0, diag, 1.0))
    R = C * (inv_s[..., :, None] * inv_s[..., None, :]) \
        + jnp.float32(ridge) * jnp.eye(p, dtype=C.dtype)
    return _cholesky(R), inv_s


def _fit_parts(zt: jax.Array, y: jax.Array, w: jax.Array, m: jax.Array, ridge: float):
    """Centroids and both scatter factors at once, from feature-major neighbours zt (d, k),
    values y (k,), weights w (k,) and the mask as float m (k,) -> (n (), mean (d,), u (d, k)
    centred masked columns, factor of C, mean_w (d,), y_w (), factor of C_w, c_w (d,)).
    A factor is (L, inv_s) of ``_equilibrated_cholesky``. Every sum runs over the minor
    (neighbour) axis."""
    d = zt.shape[0]
    first = jnp.sum(jnp.concatenate([m[None, :] * zt, w[None, :] * zt, (w * y)[None, :],
                                     m[None, :], w[None, :]], axis=0), axis=-1)
    n, W = first[2 * d + 1], first[2 * d + 2]
    denom = jnp.concatenate([jnp.full((d,), jnp.maximum(n, 1.0)),
                             jnp.full((d + 1,), jnp.where(W > 0, W, 1.0))])
    means = first[:2 * d + 1] / denom                    # (mean, mean_w, y_w): one division
    mean, mean_w, y_w = means[:d], means[d:2 * d], means[2 * d]
    u = (zt - mean[:, None]) * m[None, :]
    sw = jnp.sqrt(w)
    v = (zt - mean_w[:, None]) * sw[None, :]
    r = (y - y_w) * sw
    rows = jnp.concatenate([u[:, None, :] * u[None, :, :], v[:, None, :] * v[None, :, :],
                            (v * r[None, :])[:, None, :]], axis=1)     # (d, 2d + 1, k)
    second = jnp.sum(rows, axis=-1)
    # Both scatter matrices factorised at once (one set of fused ops for the two).
    L, inv_s = _equilibrated_cholesky(jnp.stack([second[:, :d], second[:, d:2 * d]]), ridge)
    return n, mean, u, (L[0], inv_s[0]), mean_w, y_w, (L[1], inv_s[1]), second[:, 2 * d]


def _hull(n, mean, u, chol, mask, tol):
    """The hull test 1/n + m'C^-1 m <= (1 + tol)(1/n + max_i u_i'C^-1 u_i), C^-1 through its
    factor, u (d, k) -> bool (). Evaluated as "for some masked i, ..." (the same answer for
    finite values: module doc); False without masked neighbours."""
    L, inv_s = chol
    cols = jnp.concatenate([mean[:, None], u], axis=1) * inv_s[:, None]   # (d, k + 1)
    y = _solve_lower(L, cols)                                           # (d, k + 1)
    q = _sum_small(y * y)                                               # (k + 1,)
    inv_n = 1.0 / jnp.maximum(n, 1.0)
    return jnp.any(mask & (inv_n + q[0] <= (1.0 + tol) * (inv_n + q[1:])))


def _intercept(mean_w, y_w, chol, cw):
    """The weighted fit's intercept y_w - b'm_w () with b = C_w^-1 c_w (through the
    equilibrated factor)."""
    L, inv_s = chol
    b = _solve_upper_transposed(L, _solve_lower(L, cw * inv_s)) * inv_s
    return y_w - _sum_small(b * mean_w)


def _sum_small(x: jax.Array) -> jax.Array:
    """Sum over a short leading axis by unrolled adds: x (p, ...) -> (...)."""
    acc = x[0]
    for i in range(1, x.shape[0]):
        acc = acc + x[i]
    return acc


def hull_contains(X: jax.Array, mask: jax.Array, ridge: float, tol: float) -> jax.Array:
    """IVH test for the query at the origin of the centred design: X = [1, zc] (k, p),
    mask (k,) -> bool ().

    Inside iff e_0'(X'X)^-1 e_0 <= (1 + tol) * max_i x_i'(X'X)^-1 x_i over masked rows.
    """
    zero = jnp.zeros(X.shape[:1], X.dtype)
    n, mean, u, chol, *_ = _fit_parts(X[:, 1:].T, zero, zero, mask.astype(X.dtype), ridge)
    return _hull(n, mean, u, chol, mask, tol)


def weighted_intercept(X: jax.Array, y: jax.Array, w: jax.Array, ridge: float) -> jax.Array:
    """Intercept () of the weighted least-squares fit of y (k,) on X = [1, zc] (k, p) with
    weights w (k,) (zero on the rows to leave out)."""
    *_, mean_w, y_w, chol_w, cw = _fit_parts(X[:, 1:].T, y, w, (w > 0).astype(X.dtype), ridge)
    return _intercept(mean_w, y_w, chol_w, cw)


def local_fit(zc: jax.Array, y: jax.Array, w: jax.Array, mask: jax.Array, *,
              ridge: float = 1e-6, ivh_tol: float = 1e-3) -> LocalFit:
    """Fit at the query from its centred neighbour set.

    zc (k, d) neighbour - query; y (k,) values; w (k,) kernel weights (0 where masked);
    mask (k,) bool; ridge, ivh_tol floats or traced (). Returns ``LocalFit(value (),
    inside ())``. Finite for any finite input (empty sets, duplicates, collinear points):
    the ridge keeps the inverses finite. ``local_fit_columns`` with zc.T.
    """
    return local_fit_columns(zc.T, y, w, mask, ridge=ridge, ivh_tol=ivh_tol)


def local_fit_columns(zt: jax.Array, y: jax.Array, w: jax.Array, mask: jax.Array, *,
                      ridge: float = 1e-6, ivh_tol: float = 1e-3) -> LocalFit:
    """``local_fit`` from feature-major neighbours: zt (d, k) = neighbour - query, one column
    per neighbour (the layout of ``Memory.points``' gathered columns); y, w, mask (k,).
    Entries where ``mask`` is False are ignored whatever their y and w."""
    y = jnp.where(mask, y, 0.0)
    w = jnp.where(mask, w, 0.0)
    n, mean, u, chol, mean_w, y_w, chol_w, cw = _fit_parts(zt, y, w, mask.astype(zt.dtype),
                                                            ridge)
    return LocalFit(value=_intercept(mean_w, y_w, chol_w, cw),
                    inside=_hull(n, mean, u, chol, mask, ivh_tol))
