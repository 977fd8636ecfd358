"""shard_seeds: a vmapped train with the seed axis sharded over (forced) CPU devices."""
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax.sharding import shard_seeds

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_SCRIPT = textwrap.dedent("""
    import os
    import jax, jax.numpy as jnp, numpy as np
    if os.environ.get("HEDGER_JAX_TEST_XLA_CACHE"):    # the suite's compilation cache
        jax.config.update("jax_compilation_cache_dir", os.environ["HEDGER_JAX_TEST_XLA_CACHE"])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    from hedger_jax.config import HedgerConfig
    from hedger_jax.memory import add_points, init_memory, refresh_index
    from hedger_jax.prediction import predict
    from hedger_jax.sharding import shard_seeds

    assert len(jax.devices()) == 2, jax.devices()
    cfg = HedgerConfig(2, 1, capacity=256, bandwidth=0.2, neighbour_index="brute")

    def train(key):  # a small HEDGER job per seed: store points, index, predict
        k1, k2, k3 = jax.random.split(key, 3)
        s = jax.random.uniform(k1, (200, 2)); a = jax.random.uniform(k2, (200, 1), minval=-1)
        mem = refresh_index(cfg, add_points(cfg, init_memory(cfg), s, a, s[:, 0] + a[:, 0]))
        q = jax.random.uniform(k3, (8, 2))
        v, known, n = jax.vmap(lambda x: predict(cfg, mem, x, jnp.zeros(1)))(q)
        return {"value": v, "n": n, "size": mem.size}

    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    ref = jax.jit(jax.vmap(train))(keys)                      # unsharded reference
    single = [jax.jit(train)(k) for k in keys]                # one seed at a time
    for mode in ("auto", "map", "vmap"):
        out = shard_seeds(train, keys, per_device=mode)
        assert len(out["value"].sharding.device_set) == 2, out["value"].sharding
        assert out["value"].shape == (4, 8) and out["size"].shape == (4,)
        # Differently compiled programs may fuse the float32 sums of the local fit in a
        # different order: equal to float32 round-off, not bit for bit.
        np.testing.assert_allclose(np.asarray(out["value"]), np.asarray(ref["value"]),
                                   rtol=2e-5, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(out["n"]), np.asarray(ref["n"]))
        if mode != "vmap":   # "auto" is "map" on CPU devices: each seed the one-seed program
            for i, s in enumerate(single):
                np.testing.assert_allclose(np.asarray(out["value"][i]), np.asarray(s["value"]),
                                           rtol=2e-5, atol=1e-7)
                np.testing.assert_array_equal(np.asarray(out["n"][i]), np.asarray(s["n"]))
    toy = lambda k: jax.random.normal(k, (3,))
    odd = jax.random.split(jax.random.PRNGKey(1), 5)           # 5 seeds on 2 devices: padded
    for mode in ("map", "vmap"):
        got = shard_seeds(toy, odd, per_device=mode)
        assert got.shape == (5, 3)
        np.testing.assert_allclose(np.asarray(got), np.asarray(jax.vmap(toy)(odd)), rtol=1e-6)
    # Typed keys work too.
    typed = jax.random.split(jax.random.key(3), 3)
    np.testing.assert_allclose(np.asarray(shard_seeds(toy, typed)),
                               np.asarray(jax.vmap(toy)(typed)), rtol=1e-6)
    print("OK")
""")


def test_shard_seeds_two_forced_cpu_devices():
    # The suite's XLA flags (hedger_jax.cpu.configure, set by conftest) and two host devices.
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2")
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu",
               PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", _SCRIPT], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "OK" in proc.stdout


def test_shard_seeds_in_process_single_device_and_padding():
    def train(key):
        return {"x": jax.random.normal(key, (3,)), "s": jnp.sum(jax.random.uniform(key, (4,)))}

    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    ref = jax.vmap(train)(keys)
    for mode in ("auto", "map", "vmap"):
        out = shard_seeds(train, keys, per_device=mode)
        np.testing.assert_allclose(np.asarray(out["x"]), np.asarray(ref["x"]), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(out["s"]), np.asarray(ref["s"]), rtol=1e-6)
        assert out["s"].shape == (3,)


def test_shard_seeds_rejects_bad_arguments():
    toy = lambda k: jax.random.normal(k, (2,))  # noqa: E731
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match="per_device"):
        shard_seeds(toy, keys, per_device="pmap")
    with pytest.raises(ValueError, match="keys"):
        shard_seeds(toy, jnp.zeros((0, 2), jnp.uint32))
    with pytest.raises(ValueError, match="devices"):
        shard_seeds(toy, keys, devices=[])


def test_auto_mode_maps_on_cpu_devices():
    from hedger_jax.sharding import resolve_per_device, seed_mesh

    mesh = seed_mesh()
    assert resolve_per_device("auto", mesh) == ("map" if jax.default_backend() == "cpu"
                                                 else "vmap")
    assert resolve_per_device("vmap", mesh) == "vmap"


def test_sweep_deals_members_to_devices_and_checks_params():
    from hedger_jax.sharding import member_order, sweep

    # 6 members on 3 devices: device d runs members d and d + 3.
    assert member_order(6, 3).tolist() == [0, 3, 1, 4, 2, 5]
    assert member_order(4, 1).tolist() == [0, 1, 2, 3]
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    scale = {"a": jnp.array([1.0, 2.0, 3.0])}
    out = sweep(lambda k, p: jax.random.normal(k, (2,)) * p["a"], keys, scale)
    ref = jax.vmap(lambda k, p: jax.random.normal(k, (2,)) * p["a"])(keys, scale)
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-6)
    with pytest.raises(ValueError, match=r"params\['a'\].*length 3"):
        sweep(lambda k, p: p["a"], keys, {"a": jnp.ones(2)})
    with pytest.raises(ValueError, match="leading member axis"):
        sweep(lambda k, p: p["a"], keys, {"a": jnp.float32(1.0)})


def test_shared_settings_become_constants_and_results_do_not_change():
    """prepare_sweep passes only the leaves that differ between members; the leaves every
    member shares (NaN included) are baked in, and the outputs equal a vmap over all of them."""
    from hedger_jax.sharding import prepare_sweep, sweep

    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    params = {"scale": jnp.array([1.0, 2.0, 3.0, 4.0]), "shift": jnp.full(4, 0.5),
              "nan": jnp.full(4, jnp.nan), "steps": jnp.full(4, 3, jnp.int32)}

    def train(k, p):
        x = jax.random.normal(k, (2,)) * p["scale"] + p["shift"]
        return x * p["steps"] + jnp.where(jnp.isnan(p["nan"]), 0.0, 1.0)

    fn, args, back = prepare_sweep(train, keys, params, 2)
    assert len(args[1]) == 1 and args[1][0].shape == (4,)       # only "scale" varies
    np.testing.assert_array_equal(np.sort(args[1][0]), [1.0, 2.0, 3.0, 4.0])
    assert back.tolist() == [0, 2, 1, 3]                        # dealt to 2 devices in turn
    out = sweep(train, keys, params)
    # Equal to float32 round-off (XLA may fold the constants in another order).
    np.testing.assert_allclose(np.asarray(out), np.asarray(jax.vmap(train)(keys, params)),
                               rtol=1e-5, atol=1e-6)
