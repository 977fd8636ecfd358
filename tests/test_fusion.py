"""``hedger_jax.fusion.computed_once``: an exact identity that XLA evaluates once."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax.fusion import computed_once


def _jaxlib_version():
    from importlib.metadata import version

    return tuple(int(v) for v in version("jaxlib").split(".")[:2])


@pytest.mark.parametrize("x", [
    np.float32(1.5), np.float32(-0.0), np.float32(np.inf), np.float32(np.nan),
    np.float32(3.4e38), np.float32(-np.inf), np.float32(-3.4e38), np.int32(2**31 - 1), np.int32(-2**31), True, False,
    np.arange(6, dtype=np.float32).reshape(2, 3) - 2.5,
    np.array([2**31 - 1, -2**31, 0], np.int32), np.array([True, False, True])])
def test_computed_once_is_the_identity_bit_for_bit(x):
    x = np.asarray(x)
    for out in (computed_once(x), jax.jit(computed_once)(x)):
        out = np.asarray(out)
        assert out.dtype == x.dtype and out.shape == x.shape
        if x.dtype.kind == "f":  # same bits: -0.0 stays -0.0, NaN stays NaN
            assert np.array_equal(out.view(np.int32), x.view(np.int32))
        else:
            assert np.array_equal(out, x)


def test_computed_once_under_vmap_and_grad():
    xs = jnp.asarray([[-1.0, 2.0], [3.5, -0.25]], jnp.float32)
    assert np.array_equal(np.asarray(jax.vmap(computed_once)(xs)), np.asarray(xs))
    g = jax.grad(lambda v: jnp.sum(computed_once(v) ** 2))(xs)
    np.testing.assert_array_equal(np.asarray(g), 2 * np.asarray(xs))


@pytest.mark.skipif(jax.default_backend() != "cpu" or _jaxlib_version() != (0, 10),
                    reason="checks XLA's CPU fusion decisions as of jaxlib 0.10")
def test_a_scalar_chain_is_not_recomputed_inside_a_large_fusion():
    """Why the helper exists: a cheap scalar chain (a dynamic slice, floor, scaling) broadcast
    against a large array is fused into -- and recomputed for every element of -- the large
    loop; through ``computed_once`` it stays outside it."""
    def program(wrap):
        def f(table, zs, i):
            key = wrap(jnp.floor(jnp.clip(zs[i] * 31.3, 0, 31)).astype(jnp.int32) * 375)
            return jnp.where(jnp.arange(table.shape[0]) < key, table, key)
        return jax.jit(f).lower(jnp.zeros(4096, jnp.int32), jnp.ones(8, jnp.float32),
                                jnp.int32(3)).compile().as_text()

    def big_fusions_with_floor(text):
        bodies = re.split(r"\n(?=%?[\w.\-]+ \()", text)
        return [b for b in bodies if "s32[4096]" in b.split("\n")[0] and "floor(" in b]

    assert big_fusions_with_floor(program(lambda k: k))          # XLA's default: fused in
    assert not big_fusions_with_floor(program(computed_once))    # computed once, outside
