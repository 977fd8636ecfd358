"""The suite runs with ``hedger_jax.cpu.configure()``, as the experiments and benchmarks do:
XLA then compiles HEDGER's many small fusions about a third faster (most of the suite's time
is compilation). ``test_cpu.py`` checks the unconfigured default in fresh processes."""
from hedger_jax import cpu

cpu.configure()
