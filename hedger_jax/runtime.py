"""XLA CPU runtime setting that keeps vmapped HEDGER programs from hanging.

With jax/jaxlib 0.10.2 on the CPU, XLA's concurrency-optimised scheduler can produce a
program that deadlocks: every XLA worker thread waits for work, the host waits for the
result, and the process sits at 0 % CPU forever. Seen here with
``jax.jit(jax.vmap(train.init))`` over 5 seeds of continuous-action mountain car (the
Figure 3 quick variant), in 3 of 3 tries at 5 seeds on the 2-core machine (1 and 2 seeds
finished). ``--xla_cpu_multi_thread_eigen=false``, the usual advice for XLA CPU hangs, did not
help (2 of 2 still hung); ``--xla_cpu_enable_concurrency_optimized_scheduler=false`` did
(3, 5 and 8 seeds all finished, 4 of 4 tries). The flag only changes the order in which XLA
schedules independent operations, not what they compute.

``apply_safe_cpu_flags`` appends that flag to ``XLA_FLAGS``. ``import hedger_jax`` and
``import envs`` call it, so it takes effect as long as JAX has not yet started its CPU
backend (JAX reads ``XLA_FLAGS`` when the first computation runs, not at ``import jax``).
It changes nothing when ``XLA_FLAGS`` already mentions
``xla_cpu_enable_concurrency_optimized_scheduler`` (your choice wins), or when the
environment variable ``HEDGER_JAX_KEEP_XLA_FLAGS`` is set to a non-empty value other than
``0``.
"""
from __future__ import annotations

import os
from typing import MutableMapping, Optional

#: The flag appended to ``XLA_FLAGS``.
SAFE_CPU_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
_FLAG_NAME = "xla_cpu_enable_concurrency_optimized_scheduler"
#: Set this environment variable (to anything but "" or "0") to leave ``XLA_FLAGS`` alone.
OPT_OUT_VARIABLE = "HEDGER_JAX_KEEP_XLA_FLAGS"


def apply_safe_cpu_flags(environ: Optional[MutableMapping[str, str]] = None) -> bool:
    """Append ``SAFE_CPU_FLAG`` to ``environ["XLA_FLAGS"]`` (default ``os.environ``).

    Returns True if the flag was added, False if it was left alone (opt-out variable set, or
    ``XLA_FLAGS`` already sets the scheduler flag). Idempotent.
    """
    env = os.environ if environ is None else environ
    if env.get(OPT_OUT_VARIABLE, "") not in ("", "0"):
        return False
    flags = env.get("XLA_FLAGS", "")
    if _FLAG_NAME in flags:
        return False
    env["XLA_FLAGS"] = f"{flags} {SAFE_CPU_FLAG}".strip()
    return True
