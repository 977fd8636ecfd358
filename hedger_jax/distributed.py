"""Sweeps over several processes: JAX's multi-controller runtime, set up only when asked.

Several processes (one per cluster node or GPU, or several on one machine) join one JAX
runtime with ``initialize()``; ``jax.devices()`` then lists every process's devices and
``hedger_jax.sweep`` splits its members over all of them. Nothing here runs on import.

Where the processes learn who they are, first match wins:

1. arguments to ``initialize(coordinator, num_processes, process_id)``;
2. this module's environment variables (``launch_local`` sets them): ``JAX_COORDINATOR_ADDRESS``
   (JAX's own), ``HEDGER_JAX_NUM_PROCESSES``, ``HEDGER_JAX_PROCESS_ID``;
3. JAX's cluster detection (SLURM, Open MPI, Kubernetes, Cloud TPU); ``detected_cluster``
   recognises SLURM and Open MPI jobs (elsewhere, call ``initialize()`` yourself).

A process that dies stops sending heartbeats; after ``heartbeat_timeout_s`` JAX's coordination
service ends every other process with "The following tasks are unhealthy (stopped sending
heartbeats)", naming the dead one, instead of leaving them waiting in a collective.
``exit_on_error`` makes a process that raises end at once, so that it counts as dead.
``launch_local`` then raises ``ProcessFailedError`` naming the first process that failed.

Two helpers for programs that span the processes: ``barrier`` (wait for the slowest process
before a collective) and ``compile_shared`` (process 0 compiles, the others load).

    python -m hedger_jax.launch -n 2 -- python -m experiments fig2 --quick
"""
from __future__ import annotations

import itertools
import os
import socket
import subprocess
import sys
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"
ENV_NUM_PROCESSES = "HEDGER_JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "HEDGER_JAX_PROCESS_ID"
#: How many of the job's processes share this machine (``local_cores`` divides by it).
ENV_LOCAL_PROCESSES = "HEDGER_JAX_LOCAL_PROCESSES"

#: Seconds without heartbeats after which the others are ended (JAX's default is 100).
HEARTBEAT_TIMEOUT_S = 30
#: How long a process waits at a barrier for the slowest one (a dead one is caught by the
#: heartbeats long before): a week.
BARRIER_TIMEOUT_S = 7 * 24 * 3600

_barriers = itertools.count()


class ProcessFailedError(RuntimeError):
    """A process of a multi-process job exited with an error or was killed."""


def _env_int(name: str, environ) -> Optional[int]:
    text = environ.get(name)
    if text in (None, ""):
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{name}={text!r}: expected an integer") from None


def detected_cluster(environ=None) -> Optional[Tuple[str, int]]:
    """(name, process count) of the multi-process job this environment describes, or None:
    this module's variables (name "hedger_jax"), else SLURM (``srun``: ``SLURM_NTASKS``) or
    Open MPI (``mpirun``: ``OMPI_COMM_WORLD_SIZE``) with more than one process, the launchers
    whose variables JAX's ``initialize()`` then reads by itself. Imports nothing."""
    env = os.environ if environ is None else environ
    for name, variable, needed in (
            ("hedger_jax", ENV_NUM_PROCESSES, ()),
            ("slurm", "SLURM_NTASKS", ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_PROCID",
                                       "SLURM_LOCALID")),
            ("ompi", "OMPI_COMM_WORLD_SIZE", ("OMPI_MCA_orte_hnp_uri",))):
        count = _env_int(variable, env)
        if count is not None and all(v in env for v in needed):
            return (name, count) if count > 1 else None
    return None


def _global_state():
    """JAX's multi-process state. Private JAX (the one place this library reaches into it):
    JAX has no public barrier with a timeout nor key-value store."""
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state


def _client():
    """JAX's coordination-service client (raises before ``initialize``)."""
    client = _global_state().client
    if client is None:
        raise RuntimeError("hedger_jax.distributed: initialize() has not run")
    return client


def is_initialized() -> bool:
    """Whether ``jax.distributed.initialize`` has run in this process."""
    import jax

    public = getattr(jax.distributed, "is_initialized", None)   # not in older JAX
    return public() if public is not None else _global_state().client is not None


def initialize(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
               process_id: Optional[int] = None, *,
               heartbeat_timeout_s: int = HEARTBEAT_TIMEOUT_S,
               initialization_timeout_s: int = 300) -> Tuple[int, int]:
    """Join this process to a multi-process JAX runtime; -> (process_id, num_processes).

    coordinator: "host:port" of process 0's coordination service. Unset arguments come from
    the environment (module doc). Call it before any JAX computation, and after
    ``hedger_jax.cpu.configure`` if you use it. A second call returns the first's answer.
    """
    import jax

    if is_initialized():
        return jax.process_index(), jax.process_count()
    env = os.environ
    coordinator = coordinator or env.get(ENV_COORDINATOR) or None
    num_processes = num_processes if num_processes is not None else _env_int(
        ENV_NUM_PROCESSES, env)
    process_id = process_id if process_id is not None else _env_int(ENV_PROCESS_ID, env)
    if num_processes is not None and num_processes < 1:
        raise ValueError(f"num_processes: must be >= 1, got {num_processes}")
    if process_id is not None and num_processes is not None and not (
            0 <= process_id < num_processes):
        raise ValueError(f"process_id: must be in [0, {num_processes}), got {process_id}")
    jax.distributed.initialize(coordinator, num_processes, process_id,
                               heartbeat_timeout_seconds=int(heartbeat_timeout_s),
                               initialization_timeout=int(initialization_timeout_s))
    return jax.process_index(), jax.process_count()


def barrier(name: str, timeout_s: float = BARRIER_TIMEOUT_S) -> None:
    """Wait until every process of the job has reached this barrier (a no-op in one process).

    Collectives between processes (gathers) give up when the others are 30 s late to set up
    their connections, so every cross-process collective here is preceded by this barrier,
    which waits on the coordination service for as long as the slowest process's share
    takes. Every process must pass the same barriers in the same order.
    """
    import jax

    if jax.process_count() == 1:
        return
    _client().wait_at_barrier(f"hedger_jax/{name}/{next(_barriers)}", int(timeout_s * 1000))


def exit_on_error(main: Any) -> Any:
    """``main`` (a function -> exit status) made to end its process at once on an uncaught
    exception when several processes run: traceback printed, ``os._exit(1)``. Why: a process
    that unwinds normally waits at JAX's shutdown barrier for the others (5 minutes), while
    they wait for it; a process that is gone is noticed by the heartbeats within
    ``HEARTBEAT_TIMEOUT_S``."""
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return main(*args, **kwargs)
        except BaseException:
            if not is_initialized():
                raise
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
            sys.stdout.flush()
            os._exit(1)

    return run


def local_cores(environ=None) -> int:
    """CPU cores for this process: those it may run on, shared evenly among the job's
    processes on this machine (``HEDGER_JAX_LOCAL_PROCESSES``, ``SLURM_NTASKS_PER_NODE``)."""
    env = os.environ if environ is None else environ
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:            # not Linux
        cores = os.cpu_count() or 1
    sharing = _env_int(ENV_LOCAL_PROCESSES, env)
    if sharing is None and "SLURM_NTASKS_PER_NODE" in env and "SLURM_CPUS_PER_TASK" not in env:
        try:                         # e.g. "4" or "4(x2)"
            sharing = int(env["SLURM_NTASKS_PER_NODE"].split("(")[0])
        except ValueError:
            sharing = None
    return max(1, cores // max(1, sharing or 1))


def free_port() -> int:
    """A TCP port on localhost that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def process_environments(n_processes: int, port: int, environ=None) -> List[Dict[str, str]]:
    """The environment of each of ``n_processes`` local processes around a coordinator on
    localhost:``port``."""
    base = dict(os.environ if environ is None else environ)
    return [dict(base, **{ENV_COORDINATOR: f"localhost:{port}",
                          ENV_NUM_PROCESSES: str(n_processes), ENV_PROCESS_ID: str(i),
                          ENV_LOCAL_PROCESSES: str(n_processes)})
            for i in range(n_processes)]


_shared_programs: Dict[Any, Any] = {}
_program_ids = itertools.count()


def compile_shared(jitted: Any, *args: Any) -> Any:
    """``jitted.lower(*args).compile()`` for a program that spans every process, compiled once:
    process 0 compiles it and hands the executable to the others through the coordination
    service (they trace meanwhile, then load it in about a second). Why: processes that
    compile the same program at once on one machine slow each other down (docs/scaling.md).
    Cached per program and argument shapes; every process must call it in the same order."""
    import jax
    from jax.experimental.serialize_executable import deserialize_and_load, serialize

    key = (jitted, jax.tree_util.tree_structure(args),
           tuple((x.shape, str(x.dtype)) for x in jax.tree_util.tree_leaves(args)))
    if key in _shared_programs:
        return _shared_programs[key]
    client = _client()
    name = f"hedger_jax/program/{next(_program_ids)}"
    lowered = jitted.lower(*args)
    if jax.process_index() == 0:
        compiled = lowered.compile()
        client.key_value_set_bytes(name, serialize(compiled)[0])
    else:
        payload = client.blocking_key_value_get_bytes(name, BARRIER_TIMEOUT_S * 1000)
        leaves = jax.tree_util.tree_leaves(args)
        devices = list(leaves[0].sharding.mesh.devices.flat) if leaves else None
        compiled = deserialize_and_load(payload, lowered.in_tree, lowered.out_tree,
                                        execution_devices=devices)
    barrier(f"loaded {name}")
    if jax.process_index() == 0:
        client.key_value_delete(name)
    _shared_programs[key] = compiled
    return compiled


def launch_local(command: Sequence[str], n_processes: int, *, port: Optional[int] = None,
                 log_dir: Optional[str] = None, timeout_s: Optional[float] = None,
                 grace_s: float = HEARTBEAT_TIMEOUT_S + 15, environ=None) -> None:
    """Run ``command`` as ``n_processes`` processes of one job on this machine, and wait.

    Each gets the variables ``initialize()`` reads (process ids 0..n-1, a coordinator on
    localhost). log_dir: each process's stdout and stderr go to ``log_dir/process-I.log``
    (default: this process's). When one fails, the others get ``grace_s`` to end (JAX ends
    them after its heartbeat timeout) and are then killed. Raises ``ProcessFailedError``
    naming the first process that failed (or ``TimeoutError`` after ``timeout_s``).
    """
    if n_processes < 1:
        raise ValueError(f"n_processes: must be >= 1, got {n_processes}")
    if not command:
        raise ValueError("command: empty")
    envs = process_environments(n_processes, port or free_port(), environ)
    logs, procs = [], []
    try:
        for i, env in enumerate(envs):
            out = None
            if log_dir is not None:
                os.makedirs(log_dir, exist_ok=True)
                out = open(os.path.join(log_dir, f"process-{i}.log"), "wb")
                logs.append(out)
            procs.append(subprocess.Popen(list(command), env=env, stdout=out,
                                          stderr=subprocess.STDOUT if out else None))
        _wait_all(procs, timeout_s, grace_s)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs:
            f.close()


def _wait_all(procs: List[subprocess.Popen], timeout_s: Optional[float], grace_s: float):
    """Wait for every process; raise on the first failure once the rest ended or the grace
    time ran out."""
    start = time.monotonic()
    failed_at = failed = None
    while True:
        codes = [p.poll() for p in procs]
        if failed is None:
            bad = [i for i, c in enumerate(codes) if c not in (None, 0)]
            if bad:
                failed, failed_at = bad[0], time.monotonic()
        if all(c is not None for c in codes):
            break
        now = time.monotonic()
        if failed is not None and now - failed_at > grace_s:
            break
        if timeout_s is not None and now - start > timeout_s:
            raise TimeoutError(f"launch_local: the processes ran past {timeout_s} s")
        time.sleep(0.1)
    if failed is not None:
        code = procs[failed].returncode
        how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
        raise ProcessFailedError(f"process {failed} of {len(procs)} {how}")
