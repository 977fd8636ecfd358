"""HEDGER on Gymnasium's classic-control suite, against SB3's DQN / SAC on the same budgets.

``python -m experiments classic-control [--quick] [--seeds 0 1 2 3 4] [--tasks ID ...]
[--methods hedger hedger-hand sb3] [--out DIR] [--docs DIR] [--summary-only] [--keep JSON]``

For each task and seed (docs/classic-control.md has the protocol and the results):

* ``hedger``: ``Hedger(env_id, seed=seed).learn(budget)``: the settings it reads from the
  task (``hedger_jax.task_settings``), nothing hand-picked;
* ``hedger-hand``: the same after ``HAND_EPISODES`` episodes of the task's hand policy
  (``experiments.hand_policies``) as phase 1, on the shorter budget (its steps included);
* ``sb3``: Stable-Baselines3's DQN (discrete actions) or SAC (continuous) with the RL
  Baselines3 Zoo's hyperparameters (``ZOO``), on the full budget (skipped, and said so,
  where SB3 is not installed: ``pip install -e .[deeprl]``).

The greedy policy is evaluated ``CURVE_POINTS`` times per run on ``CURVE_EPISODES``
episodes, and at the end on ``FINAL_EPISODES`` (the reported number). One JSON per run is
written when it ends (atomically); a rerun skips those that exist. ``--quick`` runs the
HEDGER methods on seeds 0 and 1 at a quarter of the budgets. The summary writes
``DIR/classic_control.md`` (the table), ``.json`` and ``.png`` (greedy return against env
steps, 95 % bands), and copies them to ``--docs`` when given; ``--keep`` an earlier
``classic_control.json`` fills the cells with no runs on disk (rerun some rows, keep the rest).
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence

import numpy as np

from experiments.runner import atomic_write_json
from experiments.stats import mean_ci


class Task(NamedTuple):
    """budget: env steps of ``hedger`` and ``sb3``; hand_budget: of ``hedger-hand``;
    target: the greedy return the issue asks for; sb3: "dqn" or "sac"."""

    budget: int
    hand_budget: int
    target: float
    sb3: str


TASKS: Dict[str, Task] = {
    "MountainCar-v0": Task(120_000, 30_000, -110.0, "dqn"),
    "MountainCarContinuous-v0": Task(50_000, 12_500, 90.0, "sac"),
    "Pendulum-v1": Task(20_000, 5_000, -200.0, "sac"),
    "CartPole-v1": Task(50_000, 12_500, 475.0, "dqn"),
    "Acrobot-v1": Task(100_000, 25_000, -100.0, "dqn"),
}
METHODS = ("hedger", "hedger-hand", "sb3")
LABELS = {"hedger": "HEDGER (defaults)", "hedger-hand": "HEDGER + 5 hand-policy episodes",
          "sb3": "SB3 (Zoo hyperparameters)"}
COLORS = {"hedger": "C0", "hedger-hand": "C1", "sb3": "C2"}
HAND_EPISODES = 5
CURVE_POINTS = 5
CURVE_EPISODES = 10
FINAL_EPISODES = 20
QUICK_SEEDS = (0, 1)

#: RL Baselines3 Zoo (DLR-RM/rl-baselines3-zoo, hyperparams/dqn.yml and sac.yml); every
#: setting not listed is SB3's default. MountainCar-v0's DQN is ``experiments.deep_rl``'s.
ZOO: Dict[str, Dict[str, Any]] = {
    "CartPole-v1": dict(learning_rate=2.5e-4, batch_size=512, buffer_size=100_000,
                        learning_starts=0, gamma=0.99, target_update_interval=5000,
                        train_freq=16, gradient_steps=4, exploration_fraction=0.06,
                        exploration_final_eps=0.11),
    "Acrobot-v1": dict(learning_rate=2.5e-4, batch_size=512, buffer_size=100_000,
                       learning_starts=0, gamma=0.99, target_update_interval=5000,
                       train_freq=16, gradient_steps=4, exploration_fraction=0.06,
                       exploration_final_eps=0.11),
    "Pendulum-v1": dict(learning_rate=1e-3),
    "MountainCarContinuous-v0": dict(learning_rate=3e-4, buffer_size=50_000, batch_size=512,
                                     ent_coef=0.1, train_freq=32, gradient_steps=32,
                                     gamma=0.9999, tau=0.01, learning_starts=0, use_sde=True,
                                     policy_kwargs=dict(log_std_init=-3.67,
                                                        net_arch=[64, 64])),
}


def zoo(env_id: str) -> Dict[str, Any]:
    """The Zoo's hyperparameters of ``env_id``'s SB3 agent (``policy`` and ``n_timesteps``
    left out)."""
    if env_id == "MountainCar-v0":
        from experiments.deep_rl import ZOO as MC

        return {k: v for k, v in MC["dqn"].items() if k not in ("env", "n_timesteps", "policy")}
    return dict(ZOO[env_id])


# ------------------------------------------------------------------------------------------
# One run
# ------------------------------------------------------------------------------------------
def _curve(learn: Callable[[int], None], evaluate: Callable[[int], Dict[str, float]],
           start: int, budget: int, log: Optional[Callable[[str], None]] = None,
           position: Optional[Callable[[], int]] = None) -> Dict[str, Any]:
    """Learn to ``budget`` env steps in ``CURVE_POINTS`` pieces from ``start``, evaluating
    after each -> {"steps" (the marks), "env_steps" (the steps actually taken), "returns",
    "final": {...}, "seconds" (learning only)}.

    ``position``: the env steps taken so far (with ``start``), for a learner that finishes
    its episodes (``Hedger.learn``): each piece asks only for what is left to its mark, so
    the run overshoots the budget by less than one episode, not one per piece. ``log`` gets
    a line per evaluation (a full-budget run can take an hour)."""
    steps, taken, returns, seconds = [], [], [], 0.0
    marks = np.linspace(start, budget, CURVE_POINTS + 1)[1:].astype(int)
    done = start
    for mark in marks:
        t0 = time.time()
        learn(max(int(mark - done), 0))
        seconds += time.time() - t0
        done = int(mark) if position is None else int(position())
        last = mark == marks[-1]
        ev = evaluate(FINAL_EPISODES if last else CURVE_EPISODES)
        steps.append(int(mark))
        taken.append(done)
        returns.append(ev["mean_return"])
        if log is not None:
            log(f"{done:,} / {budget:,} steps: greedy return {ev['mean_return']:.1f} "
                f"({seconds:.0f} s learning)")
    return {"steps": steps, "env_steps": taken, "returns": returns, "final": ev,
            "seconds": seconds}


def run_hedger(env_id: str, seed: int, hand: bool, budget: int,
               log: Optional[Callable[[str], None]] = None) -> Dict[str, Any]:
    """``Hedger(env_id, seed=seed)`` (after ``HAND_EPISODES`` hand-policy episodes when
    ``hand``) learning for ``budget`` env steps in all; ``log``: as ``_curve``'s."""
    from hedger_jax.learner import Hedger
    from experiments.hand_policies import HAND_POLICIES

    t0 = time.time()
    model = Hedger(env_id, seed=seed)
    demo_steps = 0
    if hand:
        model.learn_from_demonstrations(HAND_POLICIES[env_id], n_episodes=HAND_EPISODES)
        demo_steps = model.num_demo_timesteps
    setup = time.time() - t0

    def evaluate(n):
        out = model.evaluate(n_episodes=n)
        return {"mean_return": out["mean_return"], "mean_steps": out["mean_steps"]}

    rec = _curve(model.learn, evaluate, demo_steps, budget, log,
                 lambda: demo_steps + model.num_timesteps)
    rec["seconds"] += setup
    rec.update(demo_steps=demo_steps, memory_size=int(model.memory.size))
    return rec


def run_sb3(env_id: str, seed: int, budget: int,
            log: Optional[Callable[[str], None]] = None) -> Dict[str, Any]:
    """SB3's DQN or SAC (``TASKS[env_id].sb3``) with the Zoo's hyperparameters for
    ``budget`` env steps, one torch thread; ``log``: as ``_curve``'s."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN, SAC
    from stable_baselines3.common.evaluation import evaluate_policy

    torch.set_num_threads(1)
    algo = DQN if TASKS[env_id].sb3 == "dqn" else SAC
    model = algo("MlpPolicy", gym.make(env_id), seed=seed, verbose=0, **zoo(env_id))
    eval_env = gym.make(env_id)
    counter = iter(range(10 ** 6))

    def evaluate(n):
        eval_env.reset(seed=10_000 * (seed + 1) + next(counter))
        mean, _ = evaluate_policy(model, eval_env, n_eval_episodes=n, deterministic=True)
        return {"mean_return": float(mean)}

    return _curve(lambda n: model.learn(n, reset_num_timesteps=False), evaluate, 0, budget,
                  log)


def run_one(env_id: str, method: str, seed: int, quick: bool,
            log: Optional[Callable[[str], None]] = None) -> Dict[str, Any]:
    """One (task, method, seed) run -> its record; ``log`` gets its progress lines, each
    prefixed with the run's name."""
    task = TASKS[env_id]
    scale = 4 if quick else 1
    progress = None if log is None else (lambda line: log(f"{env_id} {method} seed {seed}: "
                                                          f"{line}"))
    if method == "hedger":
        rec = run_hedger(env_id, seed, False, task.budget // scale, progress)
    elif method == "hedger-hand":
        rec = run_hedger(env_id, seed, True, task.hand_budget // scale, progress)
    else:
        rec = run_sb3(env_id, seed, task.budget // scale, progress)
    rec.update(env_id=env_id, method=method, seed=seed, quick=quick)
    return rec


def sb3_available() -> bool:
    try:
        import stable_baselines3  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def result_path(out: str, env_id: str, method: str, seed: int, quick: bool) -> str:
    return os.path.join(out, "quick" if quick else "full", env_id, f"{method}_seed{seed}.json")


def load_records(out: str, quick: bool) -> List[Dict[str, Any]]:
    """Every run record on disk under ``out`` for the mode."""
    root = os.path.join(out, "quick" if quick else "full")
    records = []
    for env_id in sorted(os.listdir(root)) if os.path.isdir(root) else ():
        for name in sorted(os.listdir(os.path.join(root, env_id))):
            if name.endswith(".json"):
                with open(os.path.join(root, env_id, name)) as f:
                    records.append(json.load(f))
    return records


def sweep(tasks: Sequence[str], methods: Sequence[str], seeds: Sequence[int], out: str,
          quick: bool, log: Callable[[str], None] = functools.partial(print, flush=True)
          ) -> List[Dict[str, Any]]:
    """Every (task, method, seed) run not already on disk; returns all records."""
    records = []
    for env_id in tasks:
        for method in methods:
            if method == "sb3" and not sb3_available():
                log(f"{env_id} sb3: skipped (stable-baselines3 / torch not installed)")
                continue
            for seed in seeds:
                path = result_path(out, env_id, method, seed, quick)
                if os.path.exists(path):
                    with open(path) as f:
                        records.append(json.load(f))
                    continue
                rec = run_one(env_id, method, seed, quick, log)
                atomic_write_json(path, rec)
                records.append(rec)
                log(f"{env_id} {method} seed {seed}: return {rec['final']['mean_return']:.1f} "
                    f"({rec['seconds']:.0f} s)")
    return records


# ------------------------------------------------------------------------------------------
# Summary
# ------------------------------------------------------------------------------------------
def summarize(records: List[Dict[str, Any]]) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """{env_id: {method: {"mean", "half" (95 % t-interval), "returns", "seconds", "seeds",
    "steps", "curve_mean", "curve_half"}}}."""
    out: Dict[str, Dict[str, Dict[str, Any]]] = {}
    for env_id in TASKS:
        for method in METHODS:
            recs = sorted((r for r in records if r["env_id"] == env_id and r["method"] == method),
                          key=lambda r: r["seed"])
            if not recs:
                continue
            finals = np.asarray([r["final"]["mean_return"] for r in recs])
            mean, half = mean_ci(finals)
            curves = np.asarray([r["returns"] for r in recs])
            c_mean, c_half = mean_ci(curves, axis=0)
            out.setdefault(env_id, {})[method] = {
                "mean": float(mean), "half": float(half), "returns": finals.tolist(),
                "seconds": float(np.mean([r["seconds"] for r in recs])),
                "seeds": [r["seed"] for r in recs], "steps": recs[0]["steps"],
                "curve_mean": np.atleast_1d(c_mean).tolist(),
                "curve_half": np.atleast_1d(c_half).tolist()}
    return out


def _cell(row: Optional[Dict[str, Any]]) -> str:
    if row is None:
        return "not run"
    # One seed has no interval (mean_ci's half-width 0 there is not a measurement).
    one = len(row["seeds"]) < 2 or not np.isfinite(row["half"])
    half = "" if one else f" ± {row['half']:.1f}"
    seeds = "1 seed" if len(row["seeds"]) == 1 else f"{len(row['seeds'])} seeds"
    return f"{row['mean']:.1f}{half} ({seeds}, {row['seconds']:.0f} s)"


def table(summary: Dict[str, Dict[str, Dict[str, Any]]], quick: bool) -> str:
    """The markdown table: one row per task, greedy return (mean ± 95 % CI, seeds, seconds
    per run) per method, and the target."""
    scale = 4 if quick else 1
    lines = ["| task | budget (hand) | " + " | ".join(LABELS[m] for m in METHODS) + " | target |",
             "|---|---|" + "---|" * len(METHODS) + "---|"]
    for env_id, task in TASKS.items():
        rows = summary.get(env_id, {})
        cells = [_cell(rows.get(m)) for m in METHODS]
        lines.append(f"| {env_id} | {task.budget // scale:,} ({task.hand_budget // scale:,}) | "
                     + " | ".join(cells) + f" | ≥ {task.target:g} |")
    return "\n".join(lines)


def plot(summary: Dict[str, Dict[str, Dict[str, Any]]], path: str) -> None:
    """Greedy return against env steps per task, mean with 95 % bands per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(TASKS), figsize=(4 * len(TASKS), 3.4))
    for ax, (env_id, task) in zip(axes, TASKS.items()):
        for method, row in summary.get(env_id, {}).items():
            x = np.asarray(row["steps"])
            m, h = np.asarray(row["curve_mean"]), np.nan_to_num(np.asarray(row["curve_half"]))
            color = COLORS[method]                 # one colour per method on every panel
            ax.plot(x, m, marker="o", label=LABELS[method], color=color)
            ax.fill_between(x, m - h, m + h, alpha=0.2, color=color)
        ax.axhline(task.target, color="k", ls=":", lw=1)
        ax.set_title(env_id)
        ax.set_xlabel("env steps")
    axes[0].set_ylabel("greedy return")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def keep_rows(summary: Dict[str, Dict[str, Dict[str, Any]]], earlier_path: Optional[str]
              ) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """``summary`` with each (task, method) it lacks taken from an earlier summary JSON
    (``report``'s ``classic_control.json``), so that rerunning some rows keeps the others."""
    if earlier_path is None:
        return summary
    with open(earlier_path) as f:
        earlier = json.load(f)["summary"]
    merged = {env_id: dict(rows) for env_id, rows in summary.items()}
    for env_id, rows in earlier.items():
        if env_id not in TASKS:
            raise ValueError(f"--keep: {earlier_path} has an unknown task {env_id!r}")
        for method, row in rows.items():
            merged.setdefault(env_id, {}).setdefault(method, row)
    return merged


def report(records: List[Dict[str, Any]], out: str, docs: Optional[str], quick: bool,
           keep: Optional[str] = None) -> str:
    """Write the table, the summary JSON and the plot to ``out`` (and ``docs``) -> table.
    ``keep``: an earlier summary JSON whose rows fill those without runs (``keep_rows``)."""
    summary = keep_rows(summarize(records), keep)
    text = table(summary, quick)
    name = "classic_control_quick" if quick else "classic_control"
    for folder in filter(None, (out, docs)):
        os.makedirs(folder, exist_ok=True)
        with open(os.path.join(folder, name + ".md"), "w") as f:
            f.write(text + "\n")
        atomic_write_json(os.path.join(folder, name + ".json"),
                          {"summary": summary, "machine": platform.processor() or
                           platform.machine(), "cpus": os.cpu_count()})
        plot(summary, os.path.join(folder, name + ".png"))
    return text


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments classic-control",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, nargs="+")
    parser.add_argument("--tasks", nargs="+", choices=list(TASKS), default=list(TASKS))
    parser.add_argument("--methods", nargs="+", choices=METHODS)
    parser.add_argument("--out", default="results/classic_control")
    parser.add_argument("--docs", default=None)
    parser.add_argument("--summary-only", action="store_true",
                        help="run nothing: the table and plot of the runs on disk")
    parser.add_argument("--keep", metavar="JSON", default=None,
                        help="an earlier classic_control.json: its rows fill the table's "
                             "(task, method) cells that have no runs on disk")
    args = parser.parse_args(argv)
    seeds = args.seeds or (list(QUICK_SEEDS) if args.quick else list(range(5)))
    methods = args.methods or (["hedger", "hedger-hand"] if args.quick else list(METHODS))
    if args.summary_only:
        records = load_records(args.out, args.quick)
    else:
        records = sweep(args.tasks, methods, seeds, args.out, args.quick)
    print(report(records, args.out, args.docs, args.quick, args.keep))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
