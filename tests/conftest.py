"""The suite runs with ``hedger_jax.cpu.configure()``, as the experiments and benchmarks do:
XLA then compiles HEDGER's many small fusions about a third faster (most of the suite's time
is compilation). ``test_cpu.py`` checks the unconfigured default in fresh processes."""
import os

import pytest

from hedger_jax import cpu

cpu.configure()


def pytest_collection_modifyitems(config, items):
    """Tests marked ``full`` run only with HEDGER_JAX_FULL_TESTS=1 (CI's 10 minutes)."""
    if os.environ.get("HEDGER_JAX_FULL_TESTS"):
        return
    skip = pytest.mark.skip(reason="slow: set HEDGER_JAX_FULL_TESTS=1")
    for item in items:
        if "full" in item.keywords:
            item.add_marker(skip)
