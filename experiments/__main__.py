"""Command line: ``python -m experiments <fig1..fig5|all> [--quick|--full] [--seeds N] [--out DIR]``
(and ``python -m experiments classic-control ...``: ``experiments.classic_control``).

Runs each figure's variants over vmapped seeds with progress bars, writes per figure
``DIR/<fig>.json`` (configuration, versions, every seed's curve), ``DIR/<fig>.csv`` and
``DIR/<fig>.png`` (mean with 95% confidence bands), and ends by printing and writing
``DIR/summary.md``: each figure's numbers beside the paper's. Interrupted runs resume.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import os
import sys
import time
from typing import Dict, List, Optional


from hedger_jax import cpu, distributed
from experiments.figures import FIGURES, PAPER, build_figure
from experiments.plotting import plot_figure
from experiments.figures import Variant
from experiments.runner import (atomic_write_bytes, atomic_write_json, run_sweep,
                                static_part, versions)
from experiments.summary import figure_summary, reference_values


def _csv(records: List[Dict]) -> bytes:
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["variant", "seed", "eval", "points", "episodes", "mean_steps", "success_rate"])
    for rec in records:
        for i, seed in enumerate(rec["seeds"]):
            for j in range(len(rec["mean_steps"][i])):
                w.writerow([rec["label"], seed, j, rec["points"][i][j], rec["episodes"][i][j],
                            f"{rec['mean_steps'][i][j]:.4f}", f"{rec['success_rate'][i][j]:.4f}"])
    return out.getvalue().encode()


def select_variants(figure, only: Optional[List[str]] = None,
                    eval_episodes: Optional[int] = None):
    """The figure with only the variants whose label contains one of ``only`` (searched
    among its default and optional variants; default: the default variants), each with
    ``eval_episodes`` evaluation episodes when given."""
    variants = figure.variants
    if only:
        pool = figure.variants + figure.optional
        variants = tuple(v for v in pool if any(o in v.label for o in only))
        if not variants:
            raise SystemExit(f"--variant {only} matches none of {[v.label for v in pool]}")
    if eval_episodes is not None:
        variants = tuple(dataclasses.replace(
            v, run=dataclasses.replace(v.run, eval_episodes=eval_episodes)) for v in variants)
    x_label = figure.x_label
    axes = {v.x_axis for v in variants}
    if axes == {"episodes"} and x_label == "training points":
        x_label = "phase-two training runs"      # e.g. an ablation in the Figure-2 setting
    return dataclasses.replace(figure, variants=variants, optional=(), x_label=x_label)


def output_problem(path: str) -> Optional[str]:
    """Why ``path`` cannot be the output directory (None if it can): created if missing."""
    if os.path.exists(path) and not os.path.isdir(path):
        return f"{path!r} exists and is not a directory"
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        return f"cannot create {path!r}: {err.strerror}"
    if not os.access(path, os.W_OK | os.X_OK):
        return f"{path!r} is not writable"
    return None


def run_figure(name: str, mode: str, seeds: List[int], out: str, seed_batch: int,
               base_seed: int, only: Optional[List[str]] = None,
               eval_episodes: Optional[int] = None, seed_mode: str = "vmap",
               devices: Optional[int] = 1) -> Dict:
    import jax

    figure = select_variants(build_figure(name, mode), only, eval_episodes)
    main_process = jax.process_index() == 0   # across processes only process 0 writes files
    if main_process:
        print(f"{figure.title} [{mode}, {len(seeds)} seeds]")
    t0 = time.time()
    # Variants that differ only in traced settings (an ablation's on and off) run as one
    # program; a group's batch holds seed_batch seeds of each of its variants.
    groups: Dict[Variant, List[int]] = {}
    for i, v in enumerate(figure.variants):
        groups.setdefault(static_part(v), []).append(i)
    records: List[Dict] = [{}] * len(figure.variants)
    for idx in groups.values():
        recs = run_sweep([figure.variants[i] for i in idx], seeds, out, base_seed=base_seed,
                         seed_batch=seed_batch * len(idx), seed_mode=seed_mode, devices=devices)
        for i, rec in zip(idx, recs):
            records[i] = rec
    refs = reference_values(figure, records)
    paper = {label: PAPER[key] for label, key in figure.paper}
    data = {"figure": name, "title": figure.title, "mode": mode, "x_label": figure.x_label,
            "reference": refs, "paper": paper, "versions": versions(), "variants": records,
            "wall_seconds": time.time() - t0,
            "compute_seconds": sum(r.get("compute_seconds", 0.0) for r in records)}
    if main_process:
        atomic_write_json(os.path.join(out, f"{name}.json"), data)
        atomic_write_bytes(os.path.join(out, f"{name}.csv"), _csv(records))
        plot_figure(os.path.join(out, f"{name}.png"), figure.title, figure.x_label, records, refs,
                    paper)
        print(f"  wrote {os.path.join(out, name)}.{{json,csv,png}} ({time.time() - t0:.0f} s; "
              f"computing the results took {data['compute_seconds']:.0f} s)")
    return data


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["classic-control"]:      # beyond the paper: experiments.classic_control
        from experiments.classic_control import main as classic_control

        return classic_control(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m experiments", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("figure", choices=list(FIGURES) + ["all"],
                        help="the paper's figure to reproduce, or all of them")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", dest="mode", action="store_const", const="quick",
                      help="short runs (default): minutes on 2 CPU cores")
    mode.add_argument("--full", dest="mode", action="store_const", const="full",
                      help="the paper's lengths and 2500-episode evaluations")
    parser.add_argument("--seeds", type=int, default=5, help="number of seeds (default 5)")
    parser.add_argument("--seed-batch", type=int, default=8,
                        help="seeds of each variant run in one computation (default 8); "
                             "variants that differ only in traced settings share it")
    parser.add_argument("--seed-mode", choices=["auto", "vmap", "map"], default="auto",
                        help="how a batch runs: vmapped together, or one after another in one "
                             "program (map: each seed then runs the one-seed program); "
                             "default auto: map on a CPU, vmap on an accelerator")
    parser.add_argument("--devices", default="cores", metavar="N|cores",
                        help="split each seed batch over N devices; 'cores' (default): on a "
                             "CPU-only machine one host device per core, up to the seed batch "
                             "(JAX's forced host device count, set here before JAX starts), "
                             "else all devices. With --seed-mode map a seed's numbers do not "
                             "depend on it")
    parser.add_argument("--base-seed", type=int, default=0,
                        help="seed i runs with fold_in(PRNGKey(base), i) (default 0)")
    parser.add_argument("--out", default="results",
                        help="output directory, created if needed (default results/)")
    parser.add_argument("--variant", action="append", default=None, metavar="TEXT",
                        help="run only the variants whose label contains TEXT (repeatable); "
                             "also selects optional variants (fig2 --quick: 'continuous')")
    parser.add_argument("--eval-episodes", type=int, default=None, metavar="N",
                        help="evaluation episodes per evaluation point (default: the mode's, "
                             "2500 with --full)")
    parser.add_argument("--processes", type=int, default=None, metavar="N",
                        help="run as process --process-id of N joined by JAX's multi-process "
                             "runtime (docs/scaling.md); default: one process, or what the "
                             "environment describes (SLURM, Open MPI, python -m "
                             "hedger_jax.launch)")
    parser.add_argument("--process-id", type=int, default=None, metavar="I",
                        help="this process's index in 0..N-1 (with --processes)")
    parser.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                        help="process 0's address (with --processes)")
    args = parser.parse_args(argv)
    mode_name = args.mode or "quick"
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    if args.seed_batch < 1:
        parser.error("--seed-batch must be >= 1")
    if args.eval_episodes is not None and args.eval_episodes < 1:
        parser.error("--eval-episodes must be >= 1")
    processes = join_processes(parser, args)
    if args.devices == "cores":
        n = (distributed.local_cores() if processes > 1 else
             min(os.cpu_count() or 1, args.seed_batch, args.seeds))
        if n > 1 and not cpu.accelerator_installed():
            cpu.configure(host_devices=n)
        else:
            cpu.configure()
        devices = None                       # all of them
    else:
        try:
            devices = int(args.devices)
        except ValueError:
            devices = 0
        if devices < 1:
            parser.error("--devices must be a number >= 1 or 'cores'")
        if processes > 1 and not cpu.accelerator_installed():
            cpu.configure(host_devices=devices)   # with several processes: N per process
        else:
            cpu.configure()
    if processes > 1:
        distributed.initialize(args.coordinator, args.processes, args.process_id)
    import jax

    if devices is None or processes > 1:
        devices = len(jax.devices())
    main_process = jax.process_index() == 0
    problem = output_problem(args.out)
    if problem:
        parser.error(f"--out: {problem}")
    names = list(FIGURES) if args.figure == "all" else [args.figure]
    seeds = list(range(args.seeds))
    # Summaries of figures run earlier into the same directory are kept in summary.md.
    summaries: Dict[str, str] = {}
    for existing in FIGURES:
        path = os.path.join(args.out, f"{existing}.json")
        if existing not in names and os.path.exists(path):
            with open(path) as f:
                summaries[existing] = figure_summary(json.load(f))
    try:
        for name in names:
            data = run_figure(name, mode_name, seeds, args.out, args.seed_batch, args.base_seed,
                              args.variant, args.eval_episodes, args.seed_mode, devices)
            summaries[name] = figure_summary(data)
    except KeyboardInterrupt:
        print("\ninterrupted — rerun the same command to resume", file=sys.stderr)
        return 130
    text = "# hedger-jax: reproduction summary\n\n" + "\n".join(
        summaries[n] for n in FIGURES if n in summaries)
    if main_process:
        atomic_write_bytes(os.path.join(args.out, "summary.md"), text.encode())
        print()
        print(text)
    return 0


def join_processes(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """How many processes this run has (1: a plain run): from --processes, --process-id and
    --coordinator, else from the environment (``hedger_jax.distributed.detected_cluster``)."""
    flags = (args.processes, args.process_id, args.coordinator)
    if all(f is None for f in flags):
        found = distributed.detected_cluster()
        return 1 if found is None else found[1]
    if args.processes is None or args.processes < 1:
        parser.error("--processes N (N >= 1) is needed with --process-id and --coordinator")
    if args.processes > 1 and (args.process_id is None or args.coordinator is None):
        parser.error("--processes N > 1 needs --process-id and --coordinator HOST:PORT")
    if args.process_id is not None and not 0 <= args.process_id < args.processes:
        parser.error(f"--process-id must be in 0..{args.processes - 1}")
    return args.processes


if __name__ == "__main__":
    sys.exit(distributed.exit_on_error(main)())
