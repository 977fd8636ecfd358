"""Sweeps over several processes (hedger_jax.distributed, hedger_jax.launch): real processes
joined by JAX's multi-process runtime on localhost, against the same sweep in one process."""
import json
import os
import random
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from hedger_jax import distributed
from hedger_jax.distributed import ProcessFailedError, launch_local

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOB = os.path.join(ROOT, "tests", "distributed_job.py")
RUNNER_JOB = os.path.join(ROOT, "tests", "distributed_runner_job.py")
#: JAX's heartbeat error naming process 1, in either of its wordings.
HEARTBEAT_LOST = r"stopped sending heartbeats|Task 1 heartbeat timeout"


def _one_process(script, *args, host_devices=1):
    """Run a job script as a plain process with ``host_devices`` CPU devices."""
    flags = os.environ.get("XLA_FLAGS", "")
    if host_devices > 1:
        flags += f" --xla_force_host_platform_device_count={host_devices}"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    for name in (distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID):
        env.pop(name, None)
    proc = subprocess.run([sys.executable, script, *args], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc.stdout


def _launch(n, *args, log_dir, timeout_s=300):
    """``python *args`` as n processes of one job; AssertionError with their logs on failure."""
    try:
        launch_local([sys.executable, *args], n, log_dir=str(log_dir), timeout_s=timeout_s)
    except ProcessFailedError:
        logs = "".join(p.read_text()[-3000:] for p in sorted(log_dir.iterdir()))
        raise AssertionError(logs)


def _load(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _slurm_processes(n, script, *args, log_dir):
    """``python script *args`` as n processes with SLURM's variables (n tasks on localhost)
    and no others: the processes must find each other as they would under srun."""
    job_id = random.randrange(10_000, 1_000_000)
    env_base = {k: v for k, v in os.environ.items()
                if k not in (distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID,
                             distributed.ENV_COORDINATOR)}
    log_dir.mkdir()
    procs = []
    for i in range(n):
        env = dict(env_base, SLURM_JOB_ID=str(job_id), SLURM_STEP_NODELIST="localhost",
                   SLURM_NTASKS=str(n), SLURM_PROCID=str(i), SLURM_LOCALID=str(i),
                   JAX_PLATFORMS="cpu")
        log = open(log_dir / f"process-{i}.log", "wb")
        procs.append((subprocess.Popen([sys.executable, script, *args], env=env, cwd=ROOT,
                                       stdout=log, stderr=subprocess.STDOUT), log))
    for p, log in procs:
        code = p.wait(timeout=300)
        log.close()
        assert code == 0, (log_dir / "process-0.log").read_text()[-3000:]


def test_sweep_over_two_processes_equals_one_process(tmp_path):
    """hj.sweep on 2 processes x 1 device, found from SLURM's variables with no arguments,
    gives bit-identical members to 1 process x 2 devices (each member is the single-member
    program)."""
    _slurm_processes(2, JOB, str(tmp_path / "two.npz"), log_dir=tmp_path / "logs")
    _one_process(JOB, str(tmp_path / "one.npz"), host_devices=2)
    two, one = _load(tmp_path / "two.npz"), _load(tmp_path / "one.npz")
    assert (int(two["processes"]), int(two["devices"])) == (2, 2)
    assert (int(one["processes"]), int(one["devices"])) == (1, 2)
    for name in ("value", "known", "n"):
        assert two[name].shape == (6, 8)
        np.testing.assert_array_equal(two[name], one[name], name)
    # The members really differ: a wider bandwidth selects more neighbours.
    assert two["n"][4].mean() > two["n"][0].mean()


@pytest.mark.full   # ~50 s, mostly waiting
def test_a_late_process_is_waited_for(tmp_path):
    """Process 1 starts its share 40 s late, past the 30 s that a cross-process gather waits
    for its peers to connect: the barrier before the gather waits for it instead."""
    _launch(2, JOB, str(tmp_path / "late.npz"), "--late", "40", log_dir=tmp_path / "logs")
    _one_process(JOB, str(tmp_path / "one.npz"))
    late, one = _load(tmp_path / "late.npz"), _load(tmp_path / "one.npz")
    np.testing.assert_array_equal(late["value"], one["value"])


def _record(out_dir):
    cache = os.path.join(out_dir, "cache")
    records = [f for f in os.listdir(cache) if len(f) == 21 and f.endswith(".json")]
    assert len(records) == 1, os.listdir(cache)
    with open(os.path.join(cache, records[0])) as f:
        return json.load(f)


def test_runner_resumes_with_another_process_count(tmp_path):
    """The experiments runner over 2 processes, stopped after block 2, resumes on 1 process
    from every member's checkpoint and gives the numbers of an uninterrupted 1-process run
    (seed mode map) bit for bit; only process 0 writes results, and no checkpoint is left."""
    _launch(2, RUNNER_JOB, str(tmp_path / "resumed"), "--stop-after", "2",
            log_dir=tmp_path / "logs_stop")
    ckpts = sorted(f.split("-", 2)[2] for f in os.listdir(tmp_path / "resumed" / "cache")
                   if f.startswith("ckpt-"))
    assert ckpts == ["m0-b2.npz", "m1-b2.npz", "m2-b2.npz"]   # each member, block 2
    out = _one_process(RUNNER_JOB, str(tmp_path / "resumed"))
    assert out.startswith("done 1 1")
    _one_process(RUNNER_JOB, str(tmp_path / "one"))
    one, resumed = (_record(tmp_path / n) for n in ("one", "resumed"))
    for name in ("mean_steps", "points", "episodes", "success_rate", "memory_size"):
        assert np.asarray(one[name]).shape[:2] == (3, 4)
        np.testing.assert_array_equal(np.asarray(resumed[name]), np.asarray(one[name]), name)
    assert not [f for f in os.listdir(tmp_path / "resumed" / "cache") if f.startswith("ckpt-")]
    # Both processes computed and stopped; only process 0 wrote (the one record, read above).
    for log in ("process-0.log", "process-1.log"):
        assert "stopped" in (tmp_path / "logs_stop" / log).read_text()


def test_killed_process_ends_the_others_with_a_named_error(tmp_path):
    """Process 1 is killed after joining: process 0 is ended by JAX's heartbeat check (5 s in
    the job) naming the dead process, and the launcher names it too, instead of hanging."""
    start = time.monotonic()
    with pytest.raises(ProcessFailedError, match="process 1 of 2 was killed by signal 9"):
        launch_local([sys.executable, JOB, str(tmp_path / "x.npz"), "--die-after", "1"], 2,
                     log_dir=str(tmp_path / "logs"), timeout_s=120, grace_s=60)
    elapsed = time.monotonic() - start
    log0 = (tmp_path / "logs" / "process-0.log").read_text()
    # JAX words it by where process 0 waits: in a collective or at a barrier.
    assert re.search(HEARTBEAT_LOST, log0), log0[-3000:]
    assert elapsed < 60, elapsed           # heartbeat timeout 5 s, not the job's 120 s sleep
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.full   # ~8 s; the killed-process test covers the heartbeat path in the quick tier
def test_an_exception_in_one_process_ends_the_job(tmp_path):
    """Process 1 raises: exit_on_error ends it at once (no wait at JAX's shutdown barrier),
    and the heartbeat check ends process 0."""
    start = time.monotonic()
    with pytest.raises(ProcessFailedError, match="process 1 of 2 exited with code 1"):
        launch_local([sys.executable, JOB, str(tmp_path / "x.npz"), "--raise-after", "1"], 2,
                     log_dir=str(tmp_path / "logs"), timeout_s=120, grace_s=60)
    assert time.monotonic() - start < 60
    assert "a bug in process 1" in (tmp_path / "logs" / "process-1.log").read_text()
    assert re.search(HEARTBEAT_LOST, (tmp_path / "logs" / "process-0.log").read_text())


def test_detected_cluster_reads_the_environment(monkeypatch):
    for name in ("SLURM_JOB_ID", distributed.ENV_NUM_PROCESSES, "OMPI_MCA_orte_hnp_uri",
                 "OMPI_MCA_ess_base_jobid", "PMIX_NAMESPACE"):
        monkeypatch.delenv(name, raising=False)
    assert distributed.detected_cluster() is None
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "3")
    assert distributed.detected_cluster() == ("hedger_jax", 3)
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "1")
    assert distributed.detected_cluster() is None          # one process: a plain run
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "two")
    with pytest.raises(ValueError, match="HEDGER_JAX_NUM_PROCESSES"):
        distributed.detected_cluster()
    monkeypatch.delenv(distributed.ENV_NUM_PROCESSES)
    for name, value in (("SLURM_JOB_ID", "7"), ("SLURM_STEP_NODELIST", "node[01-02]"),
                        ("SLURM_NTASKS", "4"), ("SLURM_PROCID", "1"), ("SLURM_LOCALID", "1")):
        monkeypatch.setenv(name, value)
    assert distributed.detected_cluster() == ("slurm", 4)
    monkeypatch.setenv("SLURM_NTASKS", "1")
    assert distributed.detected_cluster() is None


def test_local_cores_are_shared_among_local_processes():
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    assert distributed.local_cores({}) == cores
    assert distributed.local_cores({distributed.ENV_LOCAL_PROCESSES: "2"}) == max(1, cores // 2)
    assert distributed.local_cores({distributed.ENV_LOCAL_PROCESSES: str(10 * cores)}) == 1
    envs = distributed.process_environments(3, 1234, environ={"A": "1"})
    assert [e[distributed.ENV_PROCESS_ID] for e in envs] == ["0", "1", "2"]
    assert all(e[distributed.ENV_COORDINATOR] == "localhost:1234" and e["A"] == "1"
               for e in envs)


def test_bad_arguments_are_named(capsys):
    with pytest.raises(ValueError, match="n_processes"):
        launch_local([sys.executable, "-c", "pass"], 0)
    with pytest.raises(ValueError, match="command"):
        launch_local([], 2)
    with pytest.raises(ValueError, match="process_id"):
        distributed.initialize("localhost:1", 2, 5)
    from hedger_jax.launch import main as launch_main

    with pytest.raises(SystemExit):
        launch_main(["-n", "2"])                      # no command
    from experiments.__main__ import main as cli

    for argv, message in ((["fig2", "--processes", "2"], "--process-id"),
                          (["fig2", "--processes", "2", "--process-id", "2", "--coordinator",
                            "localhost:1"], "0..1"),
                          (["fig2", "--process-id", "0"], "--processes N")):
        with pytest.raises(SystemExit):
            cli(argv)
        assert message in capsys.readouterr().err


def test_launcher_reports_a_failing_command(tmp_path):
    with pytest.raises(ProcessFailedError, match="process 0 of 2 exited with code 3"):
        launch_local([sys.executable, "-c",
                      "import os, sys; sys.exit(3 if os.environ['HEDGER_JAX_PROCESS_ID'] == '0'"
                      " else 0)"], 2, log_dir=str(tmp_path), grace_s=5)
    launch_local([sys.executable, "-c", "pass"], 2, log_dir=str(tmp_path))   # all succeed


def _fig2_curves(out_dir):
    with open(os.path.join(out_dir, "fig2.json")) as f:
        data = json.load(f)
    return {v["label"]: np.asarray(v["mean_steps"]) for v in data["variants"]}


@pytest.mark.full   # ~4 min: three Figure-2 quick runs of 2 seeds
def test_cli_over_two_processes_equals_one_process_map(tmp_path):
    """python -m experiments fig2 on 2 processes, with explicit flags and through the
    launcher (found from the environment), gives every seed's curve bit for bit as one
    process with --seed-mode map; only process 0 writes the figure."""
    common = ["-m", "experiments", "fig2", "--quick", "--seeds", "2", "--eval-episodes", "20"]
    port = distributed.free_port()
    env = {k: v for k, v in os.environ.items()
           if k not in (distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID)}
    procs = [subprocess.Popen([sys.executable, *common, "--out", str(tmp_path / "flags"),
                               "--processes", "2", "--process-id", str(i), "--coordinator",
                               f"localhost:{port}"], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
             for i in range(2)]
    outs = [p.communicate(timeout=900)[0].decode() for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][-3000:] + outs[1][-3000:]
    assert "wrote" in outs[0] and "wrote" not in outs[1]      # only process 0 writes
    _launch(2, *common, "--out", str(tmp_path / "launched"), log_dir=tmp_path / "logs",
            timeout_s=900)
    one = subprocess.run([sys.executable, *common, "--out", str(tmp_path / "one"),
                          "--seed-mode", "map", "--devices", "1"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=900)
    assert one.returncode == 0, one.stderr[-3000:]
    ref = _fig2_curves(tmp_path / "one")
    for name in ("flags", "launched"):
        got = _fig2_curves(tmp_path / name)
        assert got.keys() == ref.keys()
        for label in ref:
            np.testing.assert_array_equal(got[label], ref[label], f"{name}: {label}")
