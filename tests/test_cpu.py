"""``hedger_jax.cpu``: nothing global on import; per-program options; the explicit tuning call."""
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hedger_jax
from hedger_jax import cpu

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# A user's own program: a small tanh MLP. Its output bits, the environment and the CPU
# affinity must be the same whether or not hedger_jax and envs were imported first. (The
# environment is compared after the user's own imports of jax and gymnasium, which set a few
# variables of their own.)
_USER_SCRIPT = r"""
import json, os, sys
import jax, gymnasium
env_before = dict(os.environ)
aff_before = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
if sys.argv[1] == "import":
    import hedger_jax, envs, envs.gym_adapter, envs.mountain_car, envs.corridor
    import hedger_jax.learner, hedger_jax.agent, hedger_jax.distributed, hedger_jax.launch
    import experiments.__main__
import jax, jax.numpy as jnp, numpy as np
rng = np.random.default_rng(0)
ws = [jnp.asarray(rng.normal(size=(64, 64)).astype(np.float32) / 8) for _ in range(4)]
x = jnp.asarray(rng.normal(size=(256, 64)).astype(np.float32))
def mlp(x):
    for w in ws:
        x = jnp.tanh(x @ w)
    return jnp.sum(x, axis=1)
out = np.asarray(jax.jit(mlp)(x))
print(json.dumps({"env_same": dict(os.environ) == env_before,
                  "xla_flags": os.environ.get("XLA_FLAGS"),
                  "aff_same": (sorted(os.sched_getaffinity(0)) == aff_before)
                              if aff_before is not None else True,
                  "distributed": jax.distributed.is_initialized(),
                  "bits": out.view(np.uint32).tolist()}))
"""


def _run_user_script(mode):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", _USER_SCRIPT, mode], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_changes_nothing_global():
    """``import hedger_jax, envs`` (and the experiments CLI's module) leaves os.environ
    (XLA_FLAGS included), the CPU affinity, JAX's multi-process runtime and a user's own
    jitted function's output bits as they were without the import."""
    plain, imported = _run_user_script("plain"), _run_user_script("import")
    assert imported["env_same"] and imported["xla_flags"] is None
    assert imported["aff_same"]
    assert not imported["distributed"]        # jax.distributed only when asked
    assert imported["bits"] == plain["bits"]


def test_envs_never_import_hedger_jax():
    """The environments are a lower layer: importing every envs module loads no hedger_jax."""
    script = ("import sys, pkgutil, importlib, envs\n"
              "for m in pkgutil.iter_modules(envs.__path__):\n"
              "    if m.name not in ('brax_adapter', 'keyboard'):\n"
              "        importlib.import_module('envs.' + m.name)\n"
              "print(sorted(n for n in sys.modules if n.split('.')[0] == 'hedger_jax'))")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_core_modules_never_import_envs():
    """The algorithm's modules do not depend on the environments (ast, not import order)."""
    import ast

    core = ("config", "memory", "index", "lwr", "prediction", "greedy", "train", "agent")
    for name in core:
        path = os.path.join(ROOT, "hedger_jax", f"{name}.py")
        if not os.path.exists(path):
            continue
        tree = ast.parse(open(path).read())
        for node in ast.walk(tree):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(m == "envs" or m.startswith("envs.") for m in mods), (name, mods)


#: The one sanctioned use of private JAX: the coordination service's barrier and key-value
#: store, which JAX exposes through no public API (hedger_jax/distributed.py, ``_client``).
PRIVATE_JAX_ALLOWED = {("distributed.py", "jax._src")}


def test_no_private_jax_imports_in_the_library():
    import ast

    for folder in ("hedger_jax", "envs"):
        for fname in os.listdir(os.path.join(ROOT, folder)):
            if not fname.endswith(".py"):
                continue
            tree = ast.parse(open(os.path.join(ROOT, folder, fname)).read())
            for node in ast.walk(tree):
                mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                if (fname, "jax._src") in PRIVATE_JAX_ALLOWED:
                    continue
                assert not any("jax._src" in m for m in mods), (fname, mods)


def test_configure_adds_flags_once_and_keeps_the_users():
    env = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
    assert cpu.configure(environ=env, loop_kernels=True)
    flags = env["XLA_FLAGS"]
    assert flags.startswith("--xla_cpu_use_fusion_emitters=true")      # the user's wins
    assert flags.count("xla_cpu_use_fusion_emitters") == 1
    assert cpu.LOOP_KERNEL_FLAG in flags
    cpu.configure(environ=env, loop_kernels=True)
    assert env["XLA_FLAGS"] == flags                                     # idempotent
    env = {}
    cpu.configure(environ=env, loop_kernels=False, host_devices=2)
    assert cpu.LOOP_KERNEL_FLAG not in env["XLA_FLAGS"]
    assert "--xla_force_host_platform_device_count=2" in env["XLA_FLAGS"]


def test_configure_after_the_backend_started_says_nothing_took_effect(monkeypatch):
    jnp.zeros(1).block_until_ready()                   # this process's backend has started
    before = os.environ.get("XLA_FLAGS")
    with pytest.warns(RuntimeWarning, match="nothing was changed"):
        assert cpu.configure() is False
    assert os.environ.get("XLA_FLAGS") == before


def test_configure_before_the_backend_takes_effect_in_a_fresh_process():
    script = ("from hedger_jax import cpu\nimport os, jax, jax.numpy as jnp\n"
              "assert cpu.configure(host_devices=2)\n"
              "print(len(jax.devices()), 'xla_cpu_small_while_loop' in os.environ['XLA_FLAGS'])")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-2:] == ["2", "True"]


def test_accelerator_detection_reads_jax_platforms():
    assert cpu.accelerator_installed({"JAX_PLATFORMS": "cuda"})
    assert not cpu.accelerator_installed({"JAX_PLATFORMS": "cpu"})


def test_hedger_jit_compiles_with_the_options_and_matches_jax_jit():
    """``hedger_jax.jit`` is jax.jit plus per-program options this jaxlib accepts: same
    results (to float32 rounding), static and donated arguments pass through."""
    opts = cpu.compiler_options()
    assert set(opts) <= set(cpu._OPTIONS)
    if jax.default_backend() == "cpu":
        assert opts                      # at least one option known to this jaxlib

    def f(x, n):
        return jnp.tanh(x * n).sum()

    x = jnp.linspace(-1, 1, 64, dtype=jnp.float32)
    ours = hedger_jax.jit(f, static_argnames="n")
    np.testing.assert_allclose(ours(x, n=3), jax.jit(f, static_argnames="n")(x, n=3),
                               rtol=1e-6)
    assert ours.lower(x, n=3).compile() is not None
    donate = hedger_jax.jit(lambda a: a + 1, donate_argnums=0)
    np.testing.assert_array_equal(donate(jnp.ones(4)), 2 * np.ones(4))


def test_no_public_name_shadows_a_submodule():
    """``import hedger_jax.<module> as m`` must give the module: no name exported by the
    package equals one of its submodules' names (e.g. the function ``predict``)."""
    import pkgutil

    modules = {m.name for m in pkgutil.iter_modules(hedger_jax.__path__)}
    for name in modules:
        obj = getattr(hedger_jax, name, None)
        assert obj is None or getattr(obj, "__name__", "") == f"hedger_jax.{name}", name


def test_hedger_jit_inside_other_transformations():
    """Nested in jax.jit, vmap or eval_shape (where JAX takes no per-program options) a
    ``hedger_jax.jit`` function runs as plain jax.jit would."""
    f = hedger_jax.jit(lambda x: x * 2.0)
    x = jnp.arange(3.0)
    np.testing.assert_array_equal(jax.jit(lambda x: f(x) + 1)(x), x * 2 + 1)
    np.testing.assert_array_equal(jax.vmap(f)(x), x * 2)
    assert jax.eval_shape(f, x).shape == (3,)
    np.testing.assert_array_equal(jax.jit(lambda: f(jnp.ones(2)))(), 2 * np.ones(2))
