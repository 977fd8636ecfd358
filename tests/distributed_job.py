"""A small HEDGER sweep run by tests/test_distributed.py, in one process or several.

    python tests/distributed_job.py OUT.npz [--die-after S] [--raise-after S] [--late S]

Every member stores 200 points, indexes them and predicts 8 queries with its own bandwidth
(a traced setting): a real HEDGER program, small enough to compile in seconds. Joins a
multi-process job when the environment describes one (``hedger_jax.distributed``); process 0
writes the gathered outputs to OUT.npz. ``--die-after S``: process 1 kills itself S seconds
after joining (the others must then end with a named error, not hang); ``--raise-after S``:
process 1 raises instead (``distributed.exit_on_error`` ends it at once). ``--late S``:
process 1 starts its share S seconds after the others (they must wait, not give up).
"""
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from hedger_jax import cpu, distributed  # noqa: E402


def main(out: str, die_after: float = -1.0, late: float = 0.0,
         raise_after: float = -1.0) -> None:
    cpu.configure()
    if distributed.detected_cluster():
        distributed.initialize(heartbeat_timeout_s=5)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import hedger_jax as hj
    from hedger_jax.memory import add_points, refresh_index

    if die_after >= 0 and jax.process_index() == 1:
        time.sleep(die_after)
        os.kill(os.getpid(), 9)
    if raise_after >= 0 and jax.process_index() == 1:
        time.sleep(raise_after)
        raise RuntimeError("a bug in process 1")
    if jax.process_index() == 1:
        time.sleep(late)
    config = hj.HedgerConfig(2, 1, capacity=256, bandwidth=0.1, max_bandwidth=0.3)

    def train(key, params):
        k1, k2, k3 = jax.random.split(key, 3)
        s = jax.random.uniform(k1, (200, 2))
        a = jax.random.uniform(k2, (200, 1), minval=-1)
        memory = add_points(config, hj.init_memory(config), s, a, s[:, 0] + a[:, 0] ** 2)
        memory = refresh_index(config, memory)
        q = jax.random.uniform(k3, (8, 2))
        value, known, n = jax.vmap(
            lambda x: hj.predict(config, memory, x, jnp.zeros(1), params))(q)
        return {"value": value, "known": known, "n": n}

    members = 6                                     # 3 bandwidths x 2 seeds
    keys = jax.random.split(jax.random.PRNGKey(0), 2)[jnp.arange(members) % 2]
    params = hj.HedgerParams.create(
        config, bandwidth=jnp.repeat(jnp.array([0.05, 0.1, 0.3]), 2))
    out_tree = hj.sweep(train, keys, params)
    if jax.process_index() == 0:
        np.savez(out, devices=len(jax.devices()), processes=jax.process_count(),
                 **{k: np.asarray(v) for k, v in out_tree.items()})
    if die_after >= 0 or raise_after >= 0:          # wait for the failed process to be noticed
        time.sleep(120)


if __name__ == "__main__":
    args = sys.argv[1:]
    die = float(args[args.index("--die-after") + 1]) if "--die-after" in args else -1.0
    late = float(args[args.index("--late") + 1]) if "--late" in args else 0.0
    fail = float(args[args.index("--raise-after") + 1]) if "--raise-after" in args else -1.0
    distributed.exit_on_error(main)(args[0], die, late, fail)
