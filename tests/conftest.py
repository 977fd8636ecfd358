"""Suite-wide set-up.

* ``hedger_jax.cpu.configure()``, as the experiments and benchmarks do: XLA then compiles
  HEDGER's many small fusions about a third faster (most of the suite's time is compilation).
  ``test_cpu.py`` checks the unconfigured default in fresh processes.
* One XLA compilation cache for the whole run, shared by the xdist workers: a program that
  several tests (or both workers) build is compiled once. It lives in a temporary folder made
  for this run and removed at its end, so no run reads another's programs.
* Tests marked ``full`` run only with HEDGER_JAX_FULL_TESTS=1 (docs/testing.md).
* The quick tier compiles with LLVM's -O1 (``--xla_backend_optimization_level=1``, unless
  XLA_FLAGS names a level): compiling is most of its time, and -O1 compiles about a third
  faster; the full tier keeps XLA's default, what users run. Subprocesses inherit the flag.
"""
import os
import shutil
import tempfile

import jax
import pytest

from hedger_jax import cpu

_OPT_LEVEL = "--xla_backend_optimization_level"
_FLAGS = os.environ.get("XLA_FLAGS", "")
if not os.environ.get("HEDGER_JAX_FULL_TESTS") and _OPT_LEVEL not in _FLAGS:
    os.environ["XLA_FLAGS"] = (_FLAGS + f" {_OPT_LEVEL}=1").strip()
cpu.configure()

_CACHE_ENV = "HEDGER_JAX_TEST_XLA_CACHE"
# The controller makes the folder before xdist starts its workers, which inherit the variable.
_OWN_CACHE = _CACHE_ENV not in os.environ
if _OWN_CACHE:
    os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="hedger-jax-xla-cache-")
jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if _OWN_CACHE:
        shutil.rmtree(os.environ.pop(_CACHE_ENV), ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``full`` run only with HEDGER_JAX_FULL_TESTS=1."""
    if os.environ.get("HEDGER_JAX_FULL_TESTS"):
        return
    skip = pytest.mark.skip(reason="slow: set HEDGER_JAX_FULL_TESTS=1")
    for item in items:
        if "full" in item.keywords:
            item.add_marker(skip)
