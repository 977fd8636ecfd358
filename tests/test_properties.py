"""Property tests (hypothesis) of the numerics: IVH affine invariance, a stored point inside its
own hull, finite predictions for any memory contents, and region updates staying between the
old value and the target. Bounded examples, no deadline (the first example compiles)."""

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from hedger_jax.config import HedgerConfig
from hedger_jax.greedy import greedy_value
from hedger_jax.lwr import design_matrix, hull_contains, local_fit
from hedger_jax.memory import Memory
from hedger_jax.prediction import predict_scaled
from hedger_jax.train import region_update

K, D = 16, 3                     # neighbour slots (masked) and input dimension
RIDGE, TOL = 1e-6, 1e-3          # the HedgerConfig defaults
PROPS = settings(max_examples=40, deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.too_slow])


@jax.jit
def _hull(zc, mask):
    return hull_contains(design_matrix(zc, mask), mask, RIDGE, TOL)


@jax.jit
def _fit(zc, y, w, mask):
    return local_fit(zc, y, w, mask, ridge=RIDGE, ivh_tol=TOL)


def _pad(z, n):
    out = np.zeros((K, D), np.float32)
    out[:n] = z
    return out, np.arange(K) < n


def _leverage_ratio(z, q):
    """float64 reference: q's leverage / max point leverage, design [1, z - q]."""
    X = np.concatenate([np.ones((len(z), 1)), z - q], 1)
    G = np.linalg.inv(X.T @ X)
    lev = np.einsum("ij,jk,ik->i", X, G, X)
    return G[0, 0] / lev.max()


def _random_affine(rng, lo=0.2, hi=5.0):
    Q1, _ = np.linalg.qr(rng.standard_normal((D, D)))
    Q2, _ = np.linalg.qr(rng.standard_normal((D, D)))
    return Q1 @ np.diag(rng.uniform(lo, hi, D)) @ Q2, rng.normal(0.0, 2.0, D)


# ------------------------------------------------------------------------------ IVH affine
@PROPS
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(D + 2, K),
       spread=st.sampled_from([1e-2, 0.1, 1.0]), q_scale=st.sampled_from([0.3, 1.0, 2.0, 4.0]))
def test_ivh_invariant_under_affine_maps(seed, n, spread, q_scale):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, D)) * spread
    c = z - z.mean(0)
    sv = np.linalg.svd(c, compute_uv=False)
    assume(sv[-1] > 0.05 * sv[0])                                  # non-degenerate
    q = rng.standard_normal(D) * spread * q_scale
    r = _leverage_ratio(z, q)
    assume(abs(r - (1 + TOL)) > 0.02)                              # not on the boundary
    A, b = _random_affine(rng)
    z2, q2 = z @ A.T + b, q @ A.T + b
    inside = []
    for zz, qq in ((z, q), (z2, q2)):
        zc = zz.astype(np.float32) - qq.astype(np.float32)         # centred in float32
        zc, mask = _pad(zc, n)
        inside.append(bool(_hull(jnp.asarray(zc), jnp.asarray(mask))))
    assert inside[0] == inside[1] == (r <= 1 + TOL), (r, inside)


@PROPS
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(D + 2, K))
def test_local_fit_invariant_under_linear_maps_of_centred_inputs(seed, n):
    """With the weights held fixed, the fitted value at the query and the hull test do not
    change under an invertible linear map of the centred inputs (translations are removed by
    the centring)."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, D)) * 0.1
    sv = np.linalg.svd(z - z.mean(0), compute_uv=False)
    assume(sv[-1] > 0.05 * sv[0])
    q = rng.standard_normal(D) * 0.05
    y = (rng.uniform(0.1, 1.0) * (1.0 + (z - q) @ rng.standard_normal(D))
         + 0.01 * rng.standard_normal(n))
    w = rng.uniform(0.05, 1.0, n)
    A, _ = _random_affine(rng)
    zc1, mask = _pad((z - q).astype(np.float32), n)
    zc2, _ = _pad(((z - q) @ A.T).astype(np.float32), n)
    yp, _ = _pad(np.repeat(y[:, None], D, 1), n)
    wp, _ = _pad(np.repeat(w[:, None], D, 1), n)
    yp, wp = yp[:, 0], wp[:, 0]
    f1 = _fit(jnp.asarray(zc1), jnp.asarray(yp), jnp.asarray(wp), jnp.asarray(mask))
    f2 = _fit(jnp.asarray(zc2), jnp.asarray(yp), jnp.asarray(wp), jnp.asarray(mask))
    scale = np.abs(y).max()
    np.testing.assert_allclose(float(f1.value), float(f2.value), rtol=0, atol=2e-3 * scale)
    r = _leverage_ratio(z, q)
    if abs(r - (1 + TOL)) > 0.02:
        assert bool(f1.inside) == bool(f2.inside) == (r <= 1 + TOL)


# ------------------------------------------------------------------------------ own hull
def _point_set(kind, rng, n):
    if kind == "general":
        return rng.standard_normal((n, D)) * 0.05
    if kind == "duplicates":
        base = rng.standard_normal((max(2, n // 3), D)) * 0.05
        return base[rng.integers(0, len(base), n)]
    if kind == "collinear":
        return rng.standard_normal(D) * 0.05 + rng.standard_normal((n, 1)) * rng.standard_normal(D) * 0.05
    if kind == "coplanar":
        basis = rng.standard_normal((2, D)) * 0.05
        return rng.standard_normal((n, 2)) @ basis
    if kind == "tiny":
        return 0.5 + rng.standard_normal((n, D)) * 1e-5
    if kind == "all_same":
        return np.repeat(rng.uniform(0, 1, (1, D)), n, 0)
    raise AssertionError(kind)


KINDS = ["general", "duplicates", "collinear", "coplanar", "tiny", "all_same"]


@PROPS
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, K), kind=st.sampled_from(KINDS),
       data=st.data())
def test_stored_point_is_inside_its_own_hull(seed, n, kind, data):
    rng = np.random.default_rng(seed)
    z = _point_set(kind, rng, n).astype(np.float32)
    i = data.draw(st.integers(0, n - 1), label="query point")
    zc, mask = _pad(z - z[i], n)                                   # the query is point i
    assert bool(_hull(jnp.asarray(zc), jnp.asarray(mask)))


# ------------------------------------------------------------------------------ finite predictions
CFG = HedgerConfig(2, 1, capacity=32, bandwidth=0.1, max_neighbours=16,
                   discrete_actions=((-1.0,), (0.0,), (1.0,)), input_scale=(1.0, 1.0, 0.05))


@jax.jit
def _predict_and_greedy(memory, z, state):
    p = predict_scaled(CFG, memory, z)
    v, known = greedy_value(CFG, memory, state)
    return p.value, p.known, v, known


VALUE_KINDS = st.sampled_from([0.0, 1.0, -1.0, 0.8 ** 200, -(0.8 ** 200), 1e-38, 1e-30,
                               3e38, -3e38, 1e30, 1e20, 0.8 ** 100])


@PROPS
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 32), kind=st.sampled_from(KINDS),
       values=st.lists(st.one_of(VALUE_KINDS, st.floats(-1e6, 1e6, width=32)), min_size=32,
                       max_size=32),
       far=st.sampled_from([0.0, 1e3, 1e20, 3e38]))
def test_predictions_finite_for_any_memory(seed, n, kind, values, far):
    rng = np.random.default_rng(seed)
    pts = np.zeros((32, D), np.float32)
    if n:
        pts[:n] = 0.5 + _point_set(kind, rng, n)
    if far and n > 2:
        pts[n - 2] = far                                           # points far from everything
        pts[n - 1] = -far
    memory = Memory(points=jnp.asarray(pts.T), values=jnp.asarray(np.float32(values)),
                    size=jnp.int32(n), head=jnp.int32(n % 32), flags=jnp.int32(0))
    q = pts[rng.integers(0, max(n, 1))] if n else np.full(D, 0.5, np.float32)
    q = q + np.float32(rng.choice([0.0, 1e-4, 0.01]))
    state = q[:2]                                                  # input_scale 1, offset 0
    value, known, gv, gknown = (np.asarray(x) for x in _predict_and_greedy(
        memory, jnp.asarray(q), jnp.asarray(state)))
    assert np.isfinite(value) and np.isfinite(gv)
    if not known:
        assert value == np.float32(CFG.default_value)


# ------------------------------------------------------------------------------ region update
@jax.jit
def _region(memory, indices, weights, mask, target):
    return region_update(memory, indices, weights, mask, target)


TARGETS = st.one_of(st.sampled_from([0.0, 1.0, 0.8 ** 100, 0.8 ** 200, 1e-8, -1e-8, 0.5]),
                    st.floats(-1e3, 1e3, width=32))
WEIGHTS = st.one_of(st.sampled_from([0.0, 1.0, 0.99999994, 0.5, 0.01]),
                    st.floats(0.0, 1.0, width=32))

@PROPS
@example(old=[1.0] * 8, weights=[1.0] * 8, target=1e-8)
@given(old=st.lists(TARGETS, min_size=8, max_size=8),
       weights=st.lists(WEIGHTS, min_size=8, max_size=8), target=TARGETS)
def test_region_update_stays_between_old_value_and_target(old, weights, target):
    values = np.zeros(16, np.float32)
    idx = np.array([3, 0, 15, 7, 8, 1, 12, 5], np.int32)
    values[idx] = old
    memory = Memory(points=jnp.zeros((D, 16), jnp.float32), values=jnp.asarray(values),
                    size=jnp.int32(16), head=jnp.int32(0), flags=jnp.int32(0))
    mask = np.array([True] * 7 + [False])
    out = _region(memory, jnp.asarray(idx), jnp.asarray(np.float32(weights)),
                  jnp.asarray(mask), jnp.float32(target))
    new = np.asarray(out.values)
    old32, t = np.float32(old), np.float32(target)
    lo, hi = np.minimum(old32, t), np.maximum(old32, t)
    sel = new[idx]
    assert np.all((sel[mask] >= lo[mask]) & (sel[mask] <= hi[mask])), \
        list(zip(old32[mask], np.float32(weights)[mask], sel[mask]))
    np.testing.assert_array_equal(sel[~mask], old32[~mask])        # unmasked: untouched
    others = np.setdiff1d(np.arange(16), idx)
    np.testing.assert_array_equal(new[others], values[others])
    assert int(out.flags) == 0


@PROPS
@given(old=st.lists(st.floats(-1e3, 1e3, width=32), min_size=8, max_size=8),
       weights=st.lists(st.floats(0.0, float(np.float32(0.999)), width=32), min_size=8, max_size=8),
       target=st.floats(-1e3, 1e3, width=32))
def test_region_update_range_with_kernel_weights_below_one(old, weights, target):
    """The same property for weights < 1 and moderate magnitudes: holds up to a few ulps."""
    values = np.zeros(16, np.float32)
    idx = np.arange(8, dtype=np.int32) * 2
    values[idx] = old
    memory = Memory(points=jnp.zeros((D, 16), jnp.float32), values=jnp.asarray(values),
                    size=jnp.int32(16), head=jnp.int32(0), flags=jnp.int32(0))
    out = _region(memory, jnp.asarray(idx), jnp.asarray(np.float32(weights)),
                  jnp.ones(8, bool), jnp.float32(target))
    new = np.asarray(out.values)[idx]
    old32, t = np.float32(old), np.float32(target)
    lo, hi = np.minimum(old32, t), np.maximum(old32, t)
    ulp = 4 * np.spacing(np.maximum(np.abs(lo), np.abs(hi)))
    assert np.all((new >= lo - ulp) & (new <= hi + ulp))
