"""The XLA CPU flag that hedger-jax applies on import (hedger_jax.runtime)."""
import os
import subprocess
import sys

from hedger_jax.runtime import OPT_OUT_VARIABLE, SAFE_CPU_FLAG, apply_safe_cpu_flags


def test_adds_flag_to_empty_environment_once():
    env = {}
    assert apply_safe_cpu_flags(env) is True
    assert env["XLA_FLAGS"] == SAFE_CPU_FLAG
    assert apply_safe_cpu_flags(env) is False          # idempotent
    assert env["XLA_FLAGS"] == SAFE_CPU_FLAG


def test_keeps_existing_flags():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    apply_safe_cpu_flags(env)
    assert env["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2",
                                        SAFE_CPU_FLAG]


def test_user_setting_of_the_same_flag_wins():
    env = {"XLA_FLAGS": "--xla_cpu_enable_concurrency_optimized_scheduler=true"}
    assert apply_safe_cpu_flags(env) is False
    assert env["XLA_FLAGS"] == "--xla_cpu_enable_concurrency_optimized_scheduler=true"


def test_opt_out_variable():
    env = {OPT_OUT_VARIABLE: "1", "XLA_FLAGS": "--foo"}
    assert apply_safe_cpu_flags(env) is False
    assert env["XLA_FLAGS"] == "--foo"
    env = {OPT_OUT_VARIABLE: "0"}
    assert apply_safe_cpu_flags(env) is True


def _flags_after(code: str, extra_env=None) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", OPT_OUT_VARIABLE)}
    env.update(extra_env or {})
    out = subprocess.run([sys.executable, "-c", code + "\nimport os; print(os.environ.get('XLA_FLAGS', ''))"],
                         env=env, capture_output=True, text=True, check=True, timeout=120)
    return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else ""


def test_import_hedger_jax_and_envs_apply_the_flag_before_the_backend_starts():
    assert SAFE_CPU_FLAG in _flags_after("import hedger_jax").split()
    assert SAFE_CPU_FLAG in _flags_after("import envs").split()
    # jax imported first still works: XLA reads the flags when the backend starts.
    code = ("import jax\nimport hedger_jax\nimport jax.numpy as jnp\n"
            "assert float(jnp.ones(2).sum()) == 2.0")
    assert SAFE_CPU_FLAG in _flags_after(code).split()
    assert _flags_after("import hedger_jax", {OPT_OUT_VARIABLE: "1"}) == ""
