"""Soak test: 10^6 HEDGER training steps on a memory that fills and keeps going.

    python benchmarks/soak.py [--steps 1000000] [--capacity 4096] [--out soak.json]

Mountain car (discrete), episodes of a uniformly random policy from uniform random starts,
each replayed in reverse with ``train_prefix`` (Algorithm 2 per step, region updating on),
inside one jitted chunk function (``--chunk-episodes`` episodes per call, memory donated).
The memory has ``full_policy="overwrite_oldest"``, so it fills after ``capacity`` points and
then works as a ring buffer. After every chunk the host checks:

  * every stored value and point is finite (no NaN/inf ever entered the memory);
  * 0 <= size <= capacity, size == min(points written, capacity);
  * 0 <= head < capacity, head == points written mod capacity (every step writes one point);
  * flags == 0 and ``memory_check`` does not raise.

Then it shows the ``"error"`` policy: a small memory filled past capacity sets ``FLAG_FULL``,
``memory_check`` raises ``MemoryFullError`` and the stored points are unchanged by the dropped
writes; and a NaN reward sets ``FLAG_NONFINITE`` (``NonFiniteValueError``) without changing
the memory's points or size.

Prints its figures (steps/s, checks passed, value range) and writes them as JSON (``--out``).
Exit status 0 iff every check passed.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402
from hedger_jax.agent import random_action, rollout, train_prefix  # noqa: E402
from hedger_jax.config import HedgerConfig  # noqa: E402
from hedger_jax.memory import (FLAG_FULL, FLAG_NONFINITE, MemoryFullError,  # noqa: E402
                               NonFiniteValueError, init_memory, memory_check)
from hedger_jax.train import Transition, train_step  # noqa: E402


def make_chunk(env, config: HedgerConfig, n_episodes: int):
    """Jitted (memory, key) -> (memory, key, steps ()): ``n_episodes`` random-policy episodes,
    each replayed in reverse. The memory is donated."""
    params = env.default_params()

    def act(k, obs, s):
        return random_action(config, k), s

    def one(carry, k):
        mem, steps = carry
        k_reset, k_run = jax.random.split(k)
        obs0, s0 = env.reset(k_reset, params)
        ep, length = rollout(env, params, act, k_run, env.max_steps, obs0, s0,
                             jnp.zeros((), jnp.int32))
        mem = train_prefix(config, mem, ep, length)
        return (mem, steps + length), None

    @functools.partial(jax.jit, donate_argnums=(0,))
    def chunk(memory, key):
        key, sub = jax.random.split(key)
        (memory, steps), _ = jax.lax.scan(one, (memory, jnp.zeros((), jnp.int32)),
                                          jax.random.split(sub, n_episodes))
        return memory, key, steps

    return chunk


def check_memory(memory, capacity: int, written: int) -> list:
    """Host-side invariant checks -> list of failure messages (empty when all hold)."""
    fails = []
    values = np.asarray(memory.values)
    points = np.asarray(memory.points)
    size, head, flags = int(memory.size), int(memory.head), int(memory.flags)
    if not np.all(np.isfinite(values)):
        fails.append(f"non-finite values: {int((~np.isfinite(values)).sum())}")
    if not np.all(np.isfinite(points)):
        fails.append(f"non-finite points: {int((~np.isfinite(points)).sum())}")
    if not (0 <= size <= capacity) or size != min(written, capacity):
        fails.append(f"size {size} (expected {min(written, capacity)}, capacity {capacity})")
    if not (0 <= head < capacity) or head != written % capacity:
        fails.append(f"head {head} (expected {written % capacity})")
    if flags != 0:
        fails.append(f"flags {flags}")
    try:
        memory_check(memory)
    except Exception as exc:  # noqa: BLE001
        fails.append(f"memory_check raised {type(exc).__name__}: {exc}")
    return fails


def soak(steps: int, capacity: int, chunk_episodes: int, seed: int, log=print) -> dict:
    env = envs.make("mountain_car_discrete")
    config = HedgerConfig.for_env(env, capacity=capacity, bandwidth=0.015,
                                  full_policy="overwrite_oldest")
    chunk = make_chunk(env, config, chunk_episodes)
    memory = init_memory(config)
    key = jax.random.PRNGKey(seed)

    t0 = time.perf_counter()
    memory, key, n = chunk(memory, key)          # compile + first chunk
    jax.block_until_ready(memory)
    first_s = time.perf_counter() - t0
    written = int(n)
    checks, failures = 0, []
    vmin, vmax = float("inf"), float("-inf")
    fails = check_memory(memory, capacity, written)
    checks += 1
    n_failed_checks = int(bool(fails))
    failures += [f"after {written} steps: {f}" for f in fails]
    full_at = written if written >= capacity else None
    first_steps = written

    t_run = time.perf_counter()
    last_log = t_run
    while written < steps:
        memory, key, n = chunk(memory, key)
        written += int(n)                         # blocks until the chunk is done
        fails = check_memory(memory, capacity, written)
        checks += 1
        n_failed_checks += int(bool(fails))
        failures += [f"after {written} steps: {f}" for f in fails]
        v = np.asarray(memory.values)[: int(memory.size)]
        vmin, vmax = min(vmin, float(v.min())), max(vmax, float(v.max()))
        if full_at is None and written >= capacity:
            full_at = written
        now = time.perf_counter()
        if now - last_log > 30:
            rate = (written - first_steps) / max(now - t_run, 1e-9)
            log(f"  {written:>9,d} steps  {rate:8.0f} steps/s  checks passed "
                f"{checks - n_failed_checks}/{checks}", flush=True)
            last_log = now
    run_s = time.perf_counter() - t_run
    result = {
        "steps": written,
        "capacity": capacity,
        "chunk_episodes": chunk_episodes,
        "compile_and_first_chunk_s": round(first_s, 2),
        "steady_seconds": round(run_s, 2),
        "steady_steps_per_s": round((written - first_steps) / run_s, 1) if run_s > 0 else None,
        "memory_full_after_steps": full_at,
        "checks": checks,
        "checks_passed": checks - n_failed_checks,
        "failures": failures[:20],
        "final_size": int(memory.size),
        "final_head": int(memory.head),
        "value_min": vmin,
        "value_max": vmax,
    }
    return result


def error_policy_demo(seed: int, capacity: int = 256) -> dict:
    """The "error" policy: writes past capacity are dropped, flagged and raised on the host."""
    env = envs.make("mountain_car_discrete")
    config = HedgerConfig.for_env(env, capacity=capacity, bandwidth=0.015, full_policy="error")
    chunk = make_chunk(env, config, 1)
    memory = init_memory(config)
    key = jax.random.PRNGKey(seed)
    written, snapshot = 0, None
    raised = None
    while written < 3 * capacity:
        memory, key, n = chunk(memory, key)
        written += int(n)
        if snapshot is None and int(memory.size) == capacity:
            snapshot = np.asarray(memory.points).copy()
        try:
            memory_check(memory)
        except MemoryFullError as exc:
            raised = str(exc)
            if written >= 2 * capacity:
                break
    points_kept = snapshot is not None and np.array_equal(snapshot, np.asarray(memory.points))
    out = {
        "capacity": capacity,
        "steps_offered": written,
        "size": int(memory.size),
        "flag_full": bool(int(memory.flags) & FLAG_FULL),
        "memory_full_error": raised,
        "stored_points_unchanged_after_full": bool(points_kept),
        "values_finite": bool(np.all(np.isfinite(np.asarray(memory.values)))),
    }
    # NaN reward: refused, flagged, raised; points and size untouched.
    cfg = config.replace(capacity=capacity, full_policy="overwrite_oldest")
    mem = init_memory(cfg)
    mem = mem._replace(points=jnp.asarray(np.asarray(memory.points)),
                       values=jnp.asarray(np.asarray(memory.values)),
                       size=jnp.int32(capacity // 2), head=jnp.int32(capacity // 2))
    before = jax.tree_util.tree_map(np.asarray, mem)
    tr = Transition(jnp.array([-0.5, 0.0]), jnp.array([1.0]), jnp.float32(np.nan),
                    jnp.array([-0.49, 0.001]), jnp.bool_(False), jnp.bool_(True))
    after, _ = jax.jit(functools.partial(train_step, cfg))(mem, tr)
    nan_raised = None
    try:
        memory_check(after)
    except NonFiniteValueError as exc:
        nan_raised = str(exc)
    out.update({
        "nan_reward_flag": bool(int(after.flags) & FLAG_NONFINITE),
        "nan_reward_error": nan_raised,
        "nan_reward_memory_unchanged": bool(
            np.array_equal(before.points, np.asarray(after.points))
            and np.array_equal(before.values, np.asarray(after.values))
            and int(after.size) == int(before.size) and int(after.head) == int(before.head)),
    })
    out["ok"] = bool(out["flag_full"] and raised and points_kept and out["values_finite"]
                     and out["size"] == capacity and out["nan_reward_flag"] and nan_raised
                     and out["nan_reward_memory_unchanged"])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=1_000_000)
    p.add_argument("--capacity", type=int, default=4096)
    p.add_argument("--chunk-episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="write the figures as JSON here")
    args = p.parse_args(argv)

    print(f"soak: {args.steps:,d} steps, capacity {args.capacity}, overwrite_oldest, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}")
    res = soak(args.steps, args.capacity, args.chunk_episodes, args.seed)
    print(f"steps {res['steps']:,d} in {res['steady_seconds']} s after a first chunk of "
          f"{res['compile_and_first_chunk_s']} s (compile included): "
          f"{res['steady_steps_per_s']} steps/s")
    print(f"memory full after {res['memory_full_after_steps']} steps; checks passed "
          f"{res['checks_passed']}/{res['checks']}; values in [{res['value_min']:.3g}, "
          f"{res['value_max']:.3g}]")
    for f in res["failures"]:
        print("  FAIL", f)
    err = error_policy_demo(args.seed)
    print(f"error policy: capacity {err['capacity']}, {err['steps_offered']} steps offered, "
          f"size {err['size']}, FLAG_FULL {err['flag_full']}, MemoryFullError raised: "
          f"{bool(err['memory_full_error'])}, stored points unchanged: "
          f"{err['stored_points_unchanged_after_full']}")
    print(f"NaN reward: FLAG_NONFINITE {err['nan_reward_flag']}, NonFiniteValueError raised: "
          f"{bool(err['nan_reward_error'])}, memory unchanged: "
          f"{err['nan_reward_memory_unchanged']}")
    ok = not res["failures"] and err["ok"]
    report = {"soak": res, "error_policy": err, "ok": ok, "jax": jax.__version__,
              "numpy": np.__version__, "platform": platform.platform(),
              "device": str(jax.devices()[0])}
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
        print(f"wrote {args.out}")
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
