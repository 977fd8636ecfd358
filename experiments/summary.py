"""The summary table: each figure's measured numbers beside the paper's, and the claims."""
from __future__ import annotations

import functools
import json
import os
from typing import Dict, List

import numpy as np

from experiments.figures import PAPER, Figure
from experiments.stats import mean_ci, welch_p

_REFERENCE_JSON = os.path.join(os.path.dirname(__file__), "reference_lines.json")


def _measured_references() -> Dict[str, float]:
    """Converged tabular Q-learning / DP optimum / random policy, if measured (tabular.py)."""
    try:
        with open(_REFERENCE_JSON) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return {}
    out = {}
    for key in ("tabular_q", "tabular_q_paper_reward", "optimal_dp", "random"):
        value = data.get(key)
        if isinstance(value, dict):
            value = value.get("mean_steps")
        if isinstance(value, (int, float)):
            out[key] = float(value)
    return out


@functools.lru_cache(maxsize=1)
def _corridor_references() -> Dict[str, float]:
    """Hand-coded and best-achievable controllers' mean steps on the evaluation starts."""
    try:
        from envs.corridor import evaluate_controller
        from envs.corridor_controllers import best_policy, hand_coded_policy
    except ImportError:
        return {}
    import jax

    key = jax.random.PRNGKey(0)
    return {"corridor_hand_coded": evaluate_controller(hand_coded_policy(), key=key, n_repeats=5),
            "corridor_best": evaluate_controller(best_policy(), key=key, n_repeats=5)}


@functools.lru_cache(maxsize=4)
def _hand_coded_samples(n: int) -> np.ndarray:
    """The hand-coded controller's mean steps under n evaluation keys (n,): the sample a
    Welch test compares HEDGER's per-seed means with."""
    import jax

    from envs.corridor import evaluate_controller
    from envs.corridor_controllers import hand_coded_policy

    return np.asarray([evaluate_controller(hand_coded_policy(), key=jax.random.PRNGKey(i))
                       for i in range(n)])


def reference_values(figure: Figure, records: List[Dict]) -> Dict[str, float]:
    """Horizontal reference lines for a figure: measured where we have them, else the paper's."""
    measured = dict(_measured_references())
    if any(rec.get("env") == "corridor" for rec in records):
        measured.update(_corridor_references())
    for rec in records:
        info = rec.get("phase1_info") or {}
        if "demo_mean_steps" in info:
            measured["demonstrators_mean"] = info["demo_mean_steps"]
    refs = {}
    for label, key in figure.reference:
        refs[label] = measured.get(key, PAPER.get(key))
    return refs


def _fmt(mean: float, half: float) -> str:
    return f"{mean:.1f} ± {half:.1f}"


def _final(rec: Dict) -> np.ndarray:
    return np.asarray(rec["mean_steps"], float)[:, -1]


def _first(rec: Dict) -> np.ndarray:
    return np.asarray(rec["mean_steps"], float)[:, 0]


def _by_label(data: Dict) -> Dict[str, Dict]:
    return {rec["label"]: rec for rec in data["variants"]}


def _claims(data: Dict) -> List[str]:
    fig, recs, refs = data["figure"], _by_label(data), data.get("reference", {})
    lines = []
    for label, rec in recs.items() if fig == "fig2" else ():
        demo = refs.get("demonstrators' mean") or PAPER["demonstrators_mean"]
        m0, h0 = mean_ci(_first(rec))
        m1, h1 = mean_ci(_final(rec))
        lines.append(f"- {label}: after phase 1 {_fmt(m0, h0)} steps vs demonstrators' mean "
                     f"{demo:.0f}: {'below (reproduced)' if m0 + h0 < demo else 'NOT below'}; "
                     f"after {rec['episodes'][0][-1]} phase-two runs {_fmt(m1, h1)} "
                     f"(paper ≈ 56).")
    if fig in ("fig3", "fig4"):
        off = "IVH off" if fig == "fig3" else "no region update"
        deltas = {}
        for kind in ("discrete", "continuous"):
            on_rec, off_rec = recs.get(kind), recs.get(f"{kind}, {off}")
            if on_rec is None or off_rec is None:
                continue
            a, b = _final(on_rec), _final(off_rec)
            p = welch_p(a, b)
            deltas[kind] = b.mean() - a.mean()
            lines.append(f"- {kind}: on {_fmt(*mean_ci(a))} vs {off} {_fmt(*mean_ci(b))} steps; "
                         f"difference {b.mean() - a.mean():+.1f}, Welch p = {p:.3g}"
                         f"{' (significantly worse at 95%)' if p < 0.05 and b.mean() > a.mean() else ''}.")
        if fig == "fig4" and len(deltas) == 2:
            worse = deltas["continuous"] > deltas["discrete"]
            lines.append(f"- Region updating off hurts continuous more than discrete: "
                         f"{'yes' if worse else 'no'} ({deltas['continuous']:+.1f} vs "
                         f"{deltas['discrete']:+.1f} steps).")
    for rec in data["variants"] if fig == "fig5" else ():
        hand = refs.get("hand-coded controller")
        best = refs.get("best achievable")
        first, last = _first(rec), _final(rec)
        if hand is not None:
            p = welch_p(first, _hand_coded_samples(len(first)))
            lines.append(f"- {rec['label']}: after phase 1 {_fmt(*mean_ci(first))} vs "
                         f"hand-coded {hand:.1f}: "
                         f"{'NOT significantly better' if p >= 0.05 else 'significantly better' if first.mean() < hand else 'significantly worse'}"
                         f" (Welch p = {p:.3g}).")
        if best is not None:
            m1, h1 = mean_ci(last)
            lines.append(f"- {rec['label']}: after {rec['episodes'][0][-1]} phase-two runs "
                         f"{_fmt(m1, h1)} vs best {best:.1f} (within 15 %: "
                         f"{'yes' if m1 <= 1.15 * best else 'no'}).")
    return lines


def figure_summary(data: Dict) -> str:
    """Markdown section for one figure's results (``run_figure`` output)."""
    paper_final = {"fig1": "≈ 56 after ~300k points (discrete and continuous)",
                   "fig2": "near 56 after 200 phase-two runs; after phase 1 already < 210",
                   "fig3": "IVH off: only slightly better than random",
                   "fig4": "region updating off: continuous worse, discrete unaffected",
                   "fig5": "after phase 1 < hand-coded (106); after 30 runs ≈ best (70)"}
    out = [f"## {data['title']} ({data['mode']})", "",
           f"Paper: {paper_final.get(data['figure'], '')}.", "",
           "| variant | seeds | eval episodes | after phase 1 / first eval | final | points at end |",
           "|---|---|---|---|---|---|"]
    for rec in data["variants"]:
        n_eval = rec.get("run_config", {}).get("eval_episodes", "")
        out.append(f"| {rec['label']} | {len(rec['seeds'])} | {n_eval} | "
                   f"{_fmt(*mean_ci(_first(rec)))} | {_fmt(*mean_ci(_final(rec)))} | "
                   f"{int(np.mean(np.asarray(rec['points'])[:, -1]))} |")
    refs = data.get("reference", {})
    if refs:
        out.append("")
        out.append("Reference lines: " + ", ".join(
            f"{k} {v:.1f}" for k, v in refs.items() if v is not None))
    claims = _claims(data)
    if claims:
        out += [""] + claims
    out.append("")
    return "\n".join(out)
