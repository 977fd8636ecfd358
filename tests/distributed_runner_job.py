"""The experiments runner in one process or several, for tests/test_distributed.py.

    python tests/distributed_runner_job.py OUT_DIR [--stop-after B]

Runs tests/test_experiments.py's TINY variant over seeds 0..2 in one batch of 3 members,
each member the single-member program (seed_mode "map"), split over every device of every
process; joins a multi-process job when the environment describes one. ``--stop-after B``
stops every process after block B (as an interrupted run would), leaving checkpoints.
"""
import os
import sys

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(TESTS), TESTS]

from hedger_jax import cpu, distributed  # noqa: E402


class Stop(Exception):
    pass


def main(out: str, stop_after: int = -1) -> None:
    cpu.configure()
    import jax

    if distributed.detected_cluster():
        distributed.initialize(heartbeat_timeout_s=10)
    elif os.environ.get("HEDGER_JAX_TEST_XLA_CACHE"):
        # One process: the suite's compilation cache (the resumed and the uninterrupted run
        # compile the same programs).
        jax.config.update("jax_compilation_cache_dir", os.environ["HEDGER_JAX_TEST_XLA_CACHE"])

    from experiments import runner
    from test_experiments import TINY

    def on_block(block):
        if block == stop_after:
            raise Stop

    try:
        record = runner.run_variant(TINY, [0, 1, 2], out, seed_batch=3, progress=False,
                                    seed_mode="map", devices=None, on_block=on_block)
    except Stop:
        print("stopped", flush=True)
        return
    print("done", jax.process_count(), len(jax.devices()), record["mean_steps"], flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    stop = int(args[args.index("--stop-after") + 1]) if "--stop-after" in args else -1
    main(args[0], stop)
