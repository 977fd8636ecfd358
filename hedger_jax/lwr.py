"""Locally weighted linear regression and the independent-variable hull on a masked set.

Pure math, no knowledge of RL. Inputs are one query's neighbour set, *centred on the query*:
``zc`` (k, d) = neighbour - query, so the design matrix is X = [1, zc] (k, p = d + 1) and

* the local linear fit at the query is the intercept of the weighted least-squares fit;
* the query's design row is x_q = e_0 = [1, 0, ..., 0], so the IVH test
  x_q'(X'X)^-1 x_q <= max_i v_ii reduces to one diagonal entry of (X'X)^-1.

Why an intercept column: with it the hat-matrix diagonal is v_ii = 1/n + Mahalanobis distance
of point i from the neighbours' centroid, so the hull is Cook's ellipsoid centred on the
data and the test is invariant under affine changes of the inputs. Without it the ellipsoid
would be centred on the coordinate origin, which means nothing here.

Numerics (float32): both normal-equation matrices are equilibrated (scaled to a unit
diagonal, an exact change of variables for both the hull test and the intercept), then a
tiny ridge is added before the Cholesky factorisation. The values ``y`` enter only linearly,
so tiny values (gamma^100 ~ 1e-10) keep their relative precision: there is no absolute
epsilon on them.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

#: Largest number of regression parameters p = d + 1 factorised by the unrolled code below;
#: larger systems use LAPACK (``jnp.linalg.cholesky`` / ``solve_triangular``).
_UNROLL_MAX_P = 8


class LocalFit(NamedTuple):
    """value: float32 () fitted value at the query (the intercept).
    inside: bool () query inside the independent-variable hull of the masked points.
    """

    value: jax.Array
    inside: jax.Array


def kernel_weights(sqdist: jax.Array, bandwidth: float, mask: jax.Array) -> jax.Array:
    """Gaussian kernel kappa_i = exp(-d_i^2 / h^2) on masked squared distances (k,) -> (k,)."""
    return jnp.where(mask, jnp.exp(-sqdist / jnp.float32(bandwidth) ** 2), 0.0)


def design_matrix(zc: jax.Array, mask: jax.Array) -> jax.Array:
    """X = [1, zc] with masked rows zeroed: zc (k, d), mask (k,) -> (k, d + 1)."""
    ones = jnp.ones(zc.shape[:-1] + (1,), zc.dtype)
    return jnp.concatenate([ones, zc], axis=-1) * mask[..., None].astype(zc.dtype)


def _cholesky(a: jax.Array) -> jax.Array:
    """Lower Cholesky factor of a symmetric positive-definite a (p, p).

    For p <= ``_UNROLL_MAX_P`` the Cholesky-Banachiewicz recurrence is unrolled into scalar
    jnp ops (p (p + 1) / 2 entries): on CPU a LAPACK call per tiny matrix costs more than the
    arithmetic, and the unrolled ops fuse (and vectorise under vmap). Same algorithm as LAPACK's
    unblocked potrf, float32 throughout.
    """
    p = a.shape[-1]
    if p > _UNROLL_MAX_P:
        return jnp.linalg.cholesky(a)
    L = [[None] * p for _ in range(p)]
    for j in range(p):
        acc = a[j, j]
        for m in range(j):
            acc = acc - L[j][m] * L[j][m]
        L[j][j] = jnp.sqrt(acc)
        inv = 1.0 / L[j][j]
        for i in range(j + 1, p):
            acc = a[i, j]
            for m in range(j):
                acc = acc - L[i][m] * L[j][m]
            L[i][j] = acc * inv
    zero = jnp.zeros((), a.dtype)
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(p)])
                      for i in range(p)])


def _solve_lower(L: jax.Array, b: jax.Array) -> jax.Array:
    """Forward substitution: x with L x = b, L (p, p) lower, b (p,) or (p, k)."""
    p = L.shape[-1]
    if p > _UNROLL_MAX_P:
        return solve_triangular(L, b, lower=True)
    x = []
    for i in range(p):
        acc = b[i]
        for m in range(i):
            acc = acc - L[i, m] * x[m]
        x.append(acc / L[i, i])
    return jnp.stack(x)


def _solve_upper_transposed(L: jax.Array, b: jax.Array) -> jax.Array:
    """Back substitution with L': x with L' x = b, L (p, p) lower, b (p,)."""
    p = L.shape[-1]
    if p > _UNROLL_MAX_P:
        return solve_triangular(L.T, b, lower=False)
    x = [None] * p
    for i in range(p - 1, -1, -1):
        acc = b[i]
        for m in range(i + 1, p):
            acc = acc - L[m, i] * x[m]
        x[i] = acc / L[i, i]
    return jnp.stack(x)


def _sum_small(x: jax.Array) -> jax.Array:
    """Sum over a short leading axis by unrolled adds: x (p, ...) -> (...)."""
    acc = x[0]
    for i in range(1, x.shape[0]):
        acc = acc + x[i]
    return acc


def _equilibrated_cholesky(gram: jax.Array, ridge: float):
    """gram (p, p) PSD -> (L, s) with L L' = D^-1 gram D^-1 + ridge I, D = diag(s)."""
    diag = jnp.diagonal(gram)
    s = jnp.where(diag > 0, jnp.sqrt(diag), 1.0)
    scaled = gram / (s[:, None] * s[None, :])
    p = gram.shape[-1]
    scaled = scaled + jnp.float32(ridge) * jnp.eye(p, dtype=gram.dtype)
    return _cholesky(scaled), s


def moments(X: jax.Array, y: jax.Array, w: jax.Array):
    """X'X, X'WX (p, p) and X'Wy (p,) of X (k, p), y (k,), w (k,), as one reduction.

    One sum over the k rows of x_i [x_i, w_i x_i, w_i y_i]' (k, p, 2p + 1): on XLA's CPU
    backend three separate small sums (the obvious code) were 3x slower batched over queries
    (some went to a YNNPACK kernel) and slower inside a training loop (more operations).
    """
    p = X.shape[-1]
    Xw = X * w[:, None]
    rows = jnp.concatenate([X, Xw, (w * y)[:, None]], axis=-1)        # (k, 2p + 1)
    m = jnp.sum(X[:, :, None] * rows[:, None, :], axis=0)
    return m[:, :p], m[:, p:2 * p], m[:, 2 * p]


def _hull_test(X: jax.Array, mask: jax.Array, gram: jax.Array, ridge: float,
               tol: float) -> jax.Array:
    L, s = _equilibrated_cholesky(gram, ridge)
    Y = _solve_lower(L, (X / s).T)                             # (p, k)
    leverage = jnp.where(mask, _sum_small(Y * Y), -jnp.inf)    # v_ii
    e0 = jnp.zeros((X.shape[-1],), X.dtype).at[0].set(1.0) / s
    yq = _solve_lower(L, e0)
    return _sum_small(yq * yq) <= (1.0 + tol) * jnp.max(leverage)


def _intercept(gram_w: jax.Array, rhs: jax.Array, ridge: float) -> jax.Array:
    L, s = _equilibrated_cholesky(gram_w, ridge)
    u = _solve_lower(L, rhs / s)
    beta_scaled = _solve_upper_transposed(L, u)
    return beta_scaled[0] / s[0]


def hull_contains(X: jax.Array, mask: jax.Array, ridge: float, tol: float) -> jax.Array:
    """IVH test for the query at the origin of the centred design X (k, p) -> bool ().

    Inside iff e_0'(X'X)^-1 e_0 <= (1 + tol) * max_i x_i'(X'X)^-1 x_i over masked rows.
    """
    gram, _, _ = moments(X, jnp.zeros(X.shape[:1], X.dtype), jnp.zeros(X.shape[:1], X.dtype))
    return _hull_test(X, mask, gram, ridge, tol)


def weighted_intercept(X: jax.Array, y: jax.Array, w: jax.Array, ridge: float) -> jax.Array:
    """Intercept of the weighted least-squares fit of y (k,) on X (k, p), weights w (k,)."""
    _, gram_w, rhs = moments(X, y, w)
    return _intercept(gram_w, rhs, ridge)


def local_fit(zc: jax.Array, y: jax.Array, w: jax.Array, mask: jax.Array, *,
              ridge: float = 1e-6, ivh_tol: float = 1e-3) -> LocalFit:
    """Fit at the query from its centred neighbour set.

    zc (k, d) neighbour - query; y (k,) values; w (k,) kernel weights (0 where masked);
    mask (k,) bool. Returns ``LocalFit(value (), inside ())``. Finite for any input that is
    finite (empty sets, duplicates, collinear points): the ridge keeps the factorisations
    positive definite.
    """
    X = design_matrix(zc, mask)
    y = jnp.where(mask, y, 0.0)
    gram, gram_w, rhs = moments(X, y, w)
    value = _intercept(gram_w, rhs, ridge)
    inside = _hull_test(X, mask, gram, ridge, ivh_tol)
    return LocalFit(value=value, inside=inside)
