"""Run a command as N processes of one JAX job on this machine (for tests and laptops)::

    python -m hedger_jax.launch -n 2 [--port P] [--logs DIR] -- python -m experiments fig2 --quick

Each process finds its place from the environment (``hedger_jax.distributed``); the first
process that fails ends the launch with its exit code named.
"""
from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

from hedger_jax.distributed import ProcessFailedError, launch_local


def main(argv: Optional[Sequence[str]] = None) -> int:
    """The command line (module doc); -> exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        argv = argv + ["--"] if argv[:1] in (["-h"], ["--help"]) else argv
    head, command = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv \
        else (argv, [])
    ap = argparse.ArgumentParser(prog="python -m hedger_jax.launch",
                                 description="Run a command as N processes of one JAX job on "
                                             "this machine: python -m hedger_jax.launch "
                                             "-n 2 -- python -m experiments fig2 --quick")
    ap.add_argument("-n", "--processes", type=int, required=True, help="number of processes")
    ap.add_argument("--port", type=int, default=None, help="coordinator port (default: free)")
    ap.add_argument("--logs", default=None, help="write process-I.log here (default: console)")
    args = ap.parse_args(head)
    if not command:
        ap.error("give the command after --")
    if args.processes < 1:
        ap.error("--processes must be >= 1")
    try:
        launch_local(command, args.processes, port=args.port, log_dir=args.logs)
    except ProcessFailedError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
