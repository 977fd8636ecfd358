"""XLA settings for HEDGER's programs on the CPU. Nothing here runs on import.

Two levels, both explicit:

* ``hedger_jax.jit(fn, ...)`` is ``jax.jit`` with ``compiler_options()``: XLA options that
  apply to that one program only, so nobody else's program is touched. The library's own
  entry points (``Hedger``, the experiments, the benchmarks) compile with it.
* ``configure()`` sets process-wide ``XLA_FLAGS`` that XLA only accepts that way: loops
  compiled into single kernels, a lower LLVM unroll threshold, and the per-program options
  above for every program. Call it first thing, before any JAX computation; the experiments
  CLI and the benchmarks do.

What each setting gains is measured in ``docs/performance.md``.
"""
from __future__ import annotations

import functools
import os
import warnings
from typing import Any, Callable, Dict, List, Optional

#: Per-compilation XLA options (``DebugOptions`` fields) for HEDGER's programs.
_OPTIONS: Dict[str, Any] = {
    # jaxlib 0.10's concurrency-optimised scheduler deadlocked vmapped continuous-action runs.
    "xla_cpu_enable_concurrency_optimized_scheduler": False,
    # The older fusion code generators compile HEDGER's thousands of small fusions faster.
    "xla_cpu_use_fusion_emitters": False,
    # No YNNPACK library fusions: they are slow on the tiny reductions of a local fit.
    "xla_cpu_experimental_ynn_fusion_type": "",
}

#: Process-wide flags of ``configure``: every loop becomes one kernel (XLA's small-while-loop
#: hoisting without a size limit; see ``hedger_jax.kselect``), with LLVM's unroll threshold
#: lowered from 300 to 60.
LOOP_KERNEL_FLAG = ("--xla_backend_extra_options="
                    "xla_cpu_small_while_loop_byte_threshold=1125899906842624,"
                    "-unroll-threshold=60")


@functools.lru_cache(maxsize=None)
def compiler_options() -> Dict[str, Any]:
    """The per-compilation options this jaxlib accepts, for ``jax.jit(compiler_options=...)``.

    Each option is tried once on a trivial program (XLA refuses unknown ones), so a jaxlib
    that has dropped one still compiles. Empty where the default backend is not the CPU.
    """
    import jax
    import jax.numpy as jnp

    if jax.default_backend() != "cpu":
        return {}
    accepted = {}
    probe = jax.jit(lambda x: x + 1).lower(jnp.zeros((), jnp.float32))
    for name, value in _OPTIONS.items():
        try:
            probe.compile(compiler_options={name: value})
        except Exception:  # an option this jaxlib does not know
            continue
        accepted[name] = value
    return accepted


def jit(fun: Callable = None, **jit_kwargs: Any):
    """``jax.jit`` with HEDGER's per-program XLA options (``compiler_options``).

    Same arguments and behaviour as ``jax.jit`` (usable as a decorator); the jitted function
    is made on first use, so defining one starts no XLA backend. Inside another
    transformation the options of the outer program apply (XLA compiles one program).
    """
    if fun is None:
        return functools.partial(jit, **jit_kwargs)
    return _LazyJit(fun, jit_kwargs)


class _LazyJit:
    """A ``jax.jit`` function built on first use (``compiler_options`` needs the backend).
    Called inside another trace (``jit``, ``vmap``, ``eval_shape``), where JAX accepts no
    per-program options, it is the plain ``jax.jit`` function."""

    def __init__(self, fun: Callable, jit_kwargs: Dict[str, Any]):
        functools.update_wrapper(self, fun)
        self._fun, self._kwargs = fun, jit_kwargs
        self._jitted = self._plain = None

    def _get(self):
        if self._jitted is None:
            import jax

            kwargs = dict(self._kwargs)
            options = dict(compiler_options())
            options.update(kwargs.pop("compiler_options", None) or {})
            self._jitted = jax.jit(self._fun, compiler_options=options or None, **kwargs)
        return self._jitted

    def _nested(self):
        if self._plain is None:
            import jax

            kwargs = {k: v for k, v in self._kwargs.items() if k != "compiler_options"}
            self._plain = jax.jit(self._fun, **kwargs)
        return self._plain

    def __call__(self, *args, **kwargs):
        import jax

        leaves = jax.tree_util.tree_leaves((args, kwargs))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._nested()(*args, **kwargs)
        try:
            return self._get()(*args, **kwargs)
        except ValueError as err:         # inside a trace, called with constants only
            if "compiler_options" not in str(err):
                raise
            return self._nested()(*args, **kwargs)

    def __getattr__(self, name):          # lower, trace, eval_shape, ...
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._get(), name)


def xla_started() -> bool:
    """Whether JAX has started an XLA backend in this process (then ``XLA_FLAGS`` has been
    read and changing it does nothing)."""
    from jax.extend.backend import get_backend

    info = getattr(get_backend, "cache_info", None)
    return info is not None and info().currsize > 0


#: Modules whose presence means a JAX accelerator plugin is installed.
_ACCELERATOR_MODULES = ("jax_plugins", "jax_cuda12_plugin", "jax_cuda13_plugin",
                        "jax_rocm60_plugin", "jax_rocm7_plugin", "libtpu")


def accelerator_installed(environ: Any = None) -> bool:
    """Whether JAX may run on something other than the CPU here: ``JAX_PLATFORMS`` names
    another platform, or (unset) an accelerator plugin is installed. Imports nothing."""
    import importlib.util

    env = os.environ if environ is None else environ
    platforms = [p.strip().lower() for p in env.get("JAX_PLATFORMS", "").split(",") if p.strip()]
    if platforms:
        return any(p != "cpu" for p in platforms)
    for name in _ACCELERATOR_MODULES:
        try:
            if importlib.util.find_spec(name) is not None:
                return True
        except (ImportError, ValueError):
            continue
    return False


def flags(loop_kernels: bool = True, host_devices: Optional[int] = None) -> List[str]:
    """The ``XLA_FLAGS`` entries ``configure`` adds: the per-program options, the loop
    kernels (``loop_kernels``) and a forced number of host devices (``host_devices``)."""
    out = []
    for name, value in _OPTIONS.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        out.append(f"--{name}={text}")
    if loop_kernels:
        out.append(LOOP_KERNEL_FLAG)
    if host_devices is not None:
        out.append(f"--xla_force_host_platform_device_count={int(host_devices)}")
    return out


def configure(*, loop_kernels: Optional[bool] = None, host_devices: Optional[int] = None,
              environ: Any = None) -> bool:
    """Tune this process's XLA for HEDGER on the CPU: append ``flags()`` to ``XLA_FLAGS``.

    loop_kernels: compile every loop into one kernel (None: unless an accelerator may be
      used, ``accelerator_installed``: the LLVM setting that comes with it is process-wide).
    host_devices: split the CPU into this many JAX devices (e.g. one per core, so that
      ``hedger_jax.sharding`` runs seeds side by side); None leaves the device count alone.

    Call it before the first JAX computation (XLA reads ``XLA_FLAGS`` once, when its backend
    starts). A flag that ``XLA_FLAGS`` already names is left as you set it. The flags apply
    to every program of the process and to child processes that inherit the environment.
    Returns True when the flags will take effect; False, with a ``RuntimeWarning``, when an
    XLA backend has already started (then nothing is changed).
    """
    env = os.environ if environ is None else environ
    if environ is None and xla_started():
        warnings.warn("hedger_jax.cpu.configure(): JAX has already started its XLA backend, "
                      "so the flags would not take effect; nothing was changed. Call it "
                      "before any JAX computation.", RuntimeWarning, stacklevel=2)
        return False
    if loop_kernels is None:
        loop_kernels = not accelerator_installed(env)
    current = env.get("XLA_FLAGS", "")
    added = [f for f in flags(loop_kernels, host_devices) if f.split("=")[0] not in current]
    if added:
        env["XLA_FLAGS"] = " ".join([current] + added).strip()
    return True
