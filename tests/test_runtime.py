"""The XLA CPU flags that hedger-jax applies on import (hedger_jax.runtime)."""
import os
import subprocess
import sys

from hedger_jax import runtime
from hedger_jax.runtime import (LEGACY_EMITTERS_FLAG, LOOP_KERNELS_FLAG, LOOP_KERNELS_OPTION,
                                LOOP_UNROLL_OPTION, LOOP_UNROLL_THRESHOLD, NO_YNN_REDUCE_FLAG,
                                OPT_OUT_VARIABLE, SAFE_CPU_FLAG, apply_safe_cpu_flags,
                                cpu_flags, loop_kernels_enabled)

V010, V011 = (0, 10), (0, 11)
CPU = {"JAX_PLATFORMS": "cpu"}          # a CPU-only process, whatever plugins are installed
BASE = [SAFE_CPU_FLAG, NO_YNN_REDUCE_FLAG, LEGACY_EMITTERS_FLAG]


def test_flags_depend_on_the_jaxlib_version():
    assert cpu_flags(V010, CPU) == BASE + [LOOP_KERNELS_FLAG]
    # An unknown XLA flag aborts the process: only add it where it is known to exist.
    assert cpu_flags(V011, CPU) == [SAFE_CPU_FLAG]
    assert cpu_flags(V011, {"HEDGER_JAX_LOOP_KERNELS": "1"}) == [SAFE_CPU_FLAG]
    assert cpu_flags((0, 4), CPU) == [SAFE_CPU_FLAG]


def test_loop_kernels_default_on_for_the_cpu_only():
    assert LOOP_KERNELS_FLAG.endswith(f"{LOOP_UNROLL_OPTION}={LOOP_UNROLL_THRESHOLD}")
    for off in ("0", "false", "OFF", " no "):
        assert cpu_flags(V010, dict(CPU, HEDGER_JAX_LOOP_KERNELS=off)) == BASE
    for on in ("1", "true", "yes"):
        assert cpu_flags(V010, {"JAX_PLATFORMS": "cuda", "HEDGER_JAX_LOOP_KERNELS": on}) == \
            BASE + [LOOP_KERNELS_FLAG]
    # Unset or "auto": not where JAX may run on an accelerator.
    assert cpu_flags(V010, {"JAX_PLATFORMS": "cuda"}) == BASE
    assert cpu_flags(V010, {"JAX_PLATFORMS": "cpu,tpu", "HEDGER_JAX_LOOP_KERNELS": "auto"}) == BASE
    assert cpu_flags(V010, {"JAX_PLATFORMS": " cpu "}) == BASE + [LOOP_KERNELS_FLAG]


def test_accelerator_plugins_are_detected_without_importing_them(monkeypatch):
    monkeypatch.setattr(runtime, "_ACCELERATOR_MODULES", ("no_such_module_hj", "json"))
    assert runtime._accelerator_possible({}) is True            # "json": found
    assert cpu_flags(V010, {}) == BASE
    assert cpu_flags(V010, CPU) == BASE + [LOOP_KERNELS_FLAG]   # JAX_PLATFORMS decides
    monkeypatch.setattr(runtime, "_ACCELERATOR_MODULES", ("no_such_module_hj", "a.b.c"))
    assert runtime._accelerator_possible({}) is False
    assert cpu_flags(V010, {}) == BASE + [LOOP_KERNELS_FLAG]


def test_adds_flags_to_empty_environment_once():
    env = dict(CPU)
    assert apply_safe_cpu_flags(env, V010) is True
    want = " ".join(BASE + [LOOP_KERNELS_FLAG])
    assert env["XLA_FLAGS"] == want
    assert apply_safe_cpu_flags(env, V010) is False          # idempotent
    assert env["XLA_FLAGS"] == want
    env = dict(CPU)
    assert apply_safe_cpu_flags(env, V011) is True
    assert env["XLA_FLAGS"] == SAFE_CPU_FLAG


def test_keeps_existing_flags():
    env = dict(CPU, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    apply_safe_cpu_flags(env, V010)
    assert env["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2"] + BASE + [
        LOOP_KERNELS_FLAG]


def test_user_setting_of_the_same_flag_wins():
    env = {"XLA_FLAGS": "--xla_cpu_enable_concurrency_optimized_scheduler=true"}
    assert apply_safe_cpu_flags(env, V011) is False
    assert env["XLA_FLAGS"] == "--xla_cpu_enable_concurrency_optimized_scheduler=true"
    off = {"HEDGER_JAX_LOOP_KERNELS": "0"}
    env = dict(off, XLA_FLAGS="--xla_cpu_experimental_ynn_fusion_type=+LIBRARY_FUSION_TYPE_DOT")
    assert apply_safe_cpu_flags(env, V010) is True
    assert env["XLA_FLAGS"].split() == ["--xla_cpu_experimental_ynn_fusion_type="
                                        "+LIBRARY_FUSION_TYPE_DOT", SAFE_CPU_FLAG,
                                        LEGACY_EMITTERS_FLAG]
    env = dict(off, XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")   # the user's choice wins
    assert apply_safe_cpu_flags(env, V010) is True
    assert env["XLA_FLAGS"].split() == ["--xla_cpu_use_fusion_emitters=true", SAFE_CPU_FLAG,
                                        NO_YNN_REDUCE_FLAG]
    # Any backend extra option of the user's: theirs alone (XLA keeps one list).
    env = {"XLA_FLAGS": "--xla_backend_extra_options=xla_cpu_disable_loop_unrolling=true",
           "HEDGER_JAX_LOOP_KERNELS": "1"}
    assert apply_safe_cpu_flags(env, V010) is True
    assert env["XLA_FLAGS"].split()[0] == "--xla_backend_extra_options=xla_cpu_disable_loop_unrolling=true"
    assert LOOP_KERNELS_FLAG not in env["XLA_FLAGS"]
    assert "unroll-threshold" not in env["XLA_FLAGS"]


def test_loop_kernels_enabled_reads_the_threshold():
    assert loop_kernels_enabled({"XLA_FLAGS": LOOP_KERNELS_FLAG})        # CPU backend here
    assert not loop_kernels_enabled({"XLA_FLAGS": ""})
    assert not loop_kernels_enabled({"XLA_FLAGS": f"--xla_backend_extra_options="
                                                  f"{LOOP_KERNELS_OPTION}=1000"})
    assert loop_kernels_enabled({"XLA_FLAGS": f"--xla_backend_extra_options=a=1,"
                                              f"{LOOP_KERNELS_OPTION}={1 << 45}"})


def test_opt_out_variable():
    env = {OPT_OUT_VARIABLE: "1", "XLA_FLAGS": "--foo"}
    assert apply_safe_cpu_flags(env, V010) is False
    assert env["XLA_FLAGS"] == "--foo"
    env = {OPT_OUT_VARIABLE: "0"}
    assert apply_safe_cpu_flags(env, V010) is True


def _flags_after(code: str, extra_env=None) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", OPT_OUT_VARIABLE)}
    env.update(extra_env or {})
    out = subprocess.run([sys.executable, "-c", code + "\nimport os; print(os.environ.get('XLA_FLAGS', ''))"],
                         env=env, capture_output=True, text=True, check=True, timeout=120)
    return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else ""


def test_import_hedger_jax_and_envs_apply_the_flags_before_the_backend_starts():
    assert _flags_after("import hedger_jax").split() == cpu_flags()
    assert _flags_after("import envs").split() == cpu_flags()
    # jax imported first still works: XLA reads the flags when the backend starts.
    code = ("import jax\nimport hedger_jax\nimport jax.numpy as jnp\n"
            "assert float(jnp.ones(2).sum()) == 2.0")
    assert SAFE_CPU_FLAG in _flags_after(code).split()
    assert _flags_after("import hedger_jax", {OPT_OUT_VARIABLE: "1"}) == ""
    # The loop kernels: on by default in a CPU-only process (XLA and LLVM accept the options:
    # an unknown one would abort the computation), off with HEDGER_JAX_LOOP_KERNELS=0.
    code = ("import hedger_jax, jax, jax.numpy as jnp\n"
            "from hedger_jax.runtime import loop_kernels_enabled\n"
            "x = jax.lax.fori_loop(0, 5, lambda i, x: x + i, jnp.float32(0))\n"
            "assert float(x) == 10.0 and loop_kernels_enabled()")
    assert LOOP_KERNELS_FLAG in _flags_after(code, CPU).split()
    assert LOOP_KERNELS_FLAG not in _flags_after("import hedger_jax",
                                                 {"HEDGER_JAX_LOOP_KERNELS": "0"}).split()


# ---------------------------------------------------------------- serial code generation
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from hedger_jax.runtime import (SERIAL_CODEGEN_MIN_BYTES, SERIAL_CODEGEN_VARIABLE,  # noqa: E402
                                jit_serial_codegen, serial_codegen, serial_codegen_wanted)

_HAS_AFFINITY = hasattr(os, "sched_getaffinity") and os.path.isdir("/proc/self/task")


def _affinities():
    out = {}
    for name in os.listdir("/proc/self/task"):
        try:
            out[int(name)] = os.sched_getaffinity(int(name))
        except OSError:
            pass
    return out


def _gathers(table, idx):
    """A scan of small gathers from a large table (the pattern of a HEDGER training step)."""
    return jax.lax.scan(lambda c, i: (c + jnp.sum(table[:, i] * 2.0), None), 0.0, idx)[0]


@pytest.mark.skipif(not _HAS_AFFINITY, reason="needs Linux thread affinity")
def test_serial_codegen_pins_every_thread_then_restores():
    before = _affinities()
    with serial_codegen():
        inside = _affinities()
        assert all(len(a) == 1 for a in inside.values())
        assert len({min(a) for a in inside.values()}) == 1
    after = _affinities()
    for tid, aff in before.items():
        if tid in after:
            assert after[tid] == aff


def test_serial_codegen_restores_affinity_when_compilation_fails():
    before = os.sched_getaffinity(0) if _HAS_AFFINITY else None
    with pytest.raises(TypeError):
        with serial_codegen():
            jax.jit(lambda x: x + "a")(jnp.ones(3))
    if _HAS_AFFINITY:
        assert os.sched_getaffinity(0) == before


@pytest.mark.skipif(not _HAS_AFFINITY, reason="needs Linux thread affinity")
def test_serial_codegen_removes_op_splitting_and_keeps_results():
    rng = np.random.default_rng(0)
    table = jnp.asarray(rng.uniform(size=(3, 200_000)).astype(np.float32))   # 2.4 MB
    idx = jnp.asarray(rng.integers(0, 200_000, (50, 256)).astype(np.int32))
    default = jax.jit(_gathers).lower(table, idx).compile()
    with serial_codegen():
        serial = jax.jit(lambda t, i: _gathers(t, i)).lower(table, idx).compile()
    split_default = default.as_text().count("outer_dimension_partitions")
    split_serial = serial.as_text().count("outer_dimension_partitions")
    if len(os.sched_getaffinity(0)) > 1:  # with one CPU nothing is ever split
        assert split_default > 0
    assert split_serial == 0
    ref = np.sum(np.asarray(table, np.float64)[:, np.asarray(idx)] * 2.0)
    np.testing.assert_allclose(float(serial(table, idx)), ref, rtol=1e-5)
    assert float(serial(table, idx)) == float(default(table, idx))


def test_serial_codegen_wanted_policy():
    big, small = SERIAL_CODEGEN_MIN_BYTES, SERIAL_CODEGEN_MIN_BYTES - 1
    on_cpu = jax.default_backend() == "cpu"
    assert serial_codegen_wanted(big, {}) is on_cpu
    assert serial_codegen_wanted(small, {}) is False
    assert serial_codegen_wanted(small, {SERIAL_CODEGEN_VARIABLE: "1"}) is on_cpu
    assert serial_codegen_wanted(big, {SERIAL_CODEGEN_VARIABLE: "0"}) is False
    assert serial_codegen_wanted(big, {SERIAL_CODEGEN_VARIABLE: "auto"}) is on_cpu
    assert serial_codegen_wanted(big, {}, auto=False) is False
    assert serial_codegen_wanted(small, {SERIAL_CODEGEN_VARIABLE: "1"}, auto=False) is on_cpu


def test_largest_array_bytes_counts_the_index_tables(monkeypatch):
    """The policy looks at a memory's largest array, the grid index's tables included: at
    24,000 slots of 3-d points the grid's sorted copy of the points (576,000 B) crosses the
    threshold while the point array (288,000 B) does not."""
    from hedger_jax import learner
    from hedger_jax.config import HedgerConfig
    from hedger_jax.memory import init_memory, largest_array_bytes

    for kind in ("brute", "grid"):
        for cap in (600, 24_000):
            cfg = HedgerConfig(2, 1, capacity=cap, neighbour_index=kind)
            want = max(x.nbytes for x in jax.tree_util.tree_leaves(init_memory(cfg)))
            assert largest_array_bytes(cfg) == want
    grid = HedgerConfig(2, 1, capacity=24_000, neighbour_index="grid")
    brute = grid.replace(neighbour_index="brute")
    assert largest_array_bytes(brute) == 4 * 3 * 24_000 < SERIAL_CODEGEN_MIN_BYTES
    assert largest_array_bytes(grid) >= SERIAL_CODEGEN_MIN_BYTES
    monkeypatch.delenv(SERIAL_CODEGEN_VARIABLE, raising=False)
    on_cpu = jax.default_backend() == "cpu"
    assert learner._large_memory({"config": grid}) is on_cpu
    assert learner._large_memory({"config": brute}) is False


def test_jit_serial_codegen_matches_jit_with_static_and_donated_arguments():
    def f(x, y, *, scale):
        return x * scale + y, jnp.sum(y)

    plain = jax.jit(f, static_argnames=("scale",))
    wrapped = jit_serial_codegen(f, enabled=lambda kw: kw["scale"] > 1,
                                 static_argnames=("scale",), donate_argnums=(0,))
    x, y = jnp.arange(4.0), jnp.ones(4)
    for scale in (1, 2, 3, 2):
        got = wrapped(jnp.array(x), y, scale=scale)
        want = plain(x, y, scale=scale)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    assert len(wrapped._compiled) == 2          # scale 2 and 3 compiled once each (1: plain jit)
    wrapped(jnp.arange(5.0), jnp.ones(5), scale=2)   # a new shape -> a new executable
    assert len(wrapped._compiled) == 3
    assert wrapped.__name__ == "f"
    # Under a transformation the wrapper traces like jax.jit (no AOT executable involved):
    # the experiment runner calls jax.eval_shape on its (optionally serial) init.
    shapes = jax.eval_shape(lambda a, b: wrapped(a, b, scale=2), x, y)
    assert shapes[0].shape == (4,) and shapes[1].shape == ()
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(lambda a: wrapped(a, y, scale=3)[0])(jnp.ones((2, 4)))),
        np.full((2, 4), 4.0))


def test_learner_gives_identical_memories_with_and_without_serial_codegen(monkeypatch):
    from hedger_jax import Hedger

    out = []
    for mode in ("1", "0"):
        monkeypatch.setenv(SERIAL_CODEGEN_VARIABLE, mode)
        m = Hedger("HedgerMountainCar-v0", capacity=512, seed=3)
        m.learn(300)
        out.append([np.asarray(getattr(m.memory, k)) for k in ("points", "values", "size")])
    for a, b in zip(*out):
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not _HAS_AFFINITY or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux thread affinity and two CPUs")
def test_backend_started_inside_serial_codegen_keeps_all_cpus_afterwards():
    """A process whose first JAX call is inside the context must not be confined for good."""
    code = (
        "import jax, jax.numpy as jnp, numpy as np\n"
        "from hedger_jax.runtime import serial_codegen\n"
        "with serial_codegen():\n"
        "    jax.jit(lambda x: x + 1)(jnp.ones(3))\n"
        "t = jnp.zeros((3, 200_000)); i = jnp.zeros((50, 256), jnp.int32)\n"
        "f = lambda t, i: jax.lax.scan(lambda c, j: (c + jnp.sum(t[:, j] * 2.0), None), 0.0, i)[0]\n"
        "print(jax.jit(f).lower(t, i).compile().as_text().count('outer_dimension_partitions'))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert int(out.stdout.strip().splitlines()[-1]) > 0
