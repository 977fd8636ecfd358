"""Each of the paper's figures as data: variants (env + HEDGER settings + run protocol).

A figure is a thin configuration over the library; ``experiments.runner`` runs it. Modes:
``quick`` (minutes on 2 CPU cores; fewer evaluation episodes and a shorter run) and
``full`` (the paper's lengths and its 2500-episode evaluations).

Defaults chosen from measurement (docs/reproduction.md, "Sensitivity"): states scaled to [0, 1] per
dimension, actions raw for discrete mountain car, bandwidth h = 0.015 (the narrow window
in which HEDGER learns mountain car at all), k_thresh = h*sqrt(ln 100), k_min = d + 1, default
("don't know") value 0, IVH with an intercept column.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Optional, Tuple

from hedger_jax.agent import RunConfig
from hedger_jax.presets import (ADAPTIVE_CONTINUOUS_PARAMS, ADAPTIVE_PARAMS, CORRIDOR,
                                CORRIDOR_ADAPTIVE_PARAMS, CORRIDOR_ENV_PARAMS,
                                CORRIDOR_RUN, CORRIDOR_SCALE_FACTORS, MOUNTAIN_CAR,
                                MOUNTAIN_CAR_CONTINUOUS)

MODES = ("quick", "full")

#: The paper's numbers (Smart & Kaelbling 2000, section 3) and the reference lines.
PAPER = {
    "tabular_q": 56.0,
    "tabular_q_paper_reward": 56.0,
    "optimal_dp": 50.0,
    "random": 163.0,
    "optimal": 50.0,
    "demonstrators_mean": 210.0,
    "fig1_converged": 56.0,
    "fig2_after_200_runs": 56.0,
    "corridor_hand_coded": 106.0,
    "corridor_best": 70.0,
}

#: The per-environment settings are ``hedger_jax.presets`` (``Hedger``'s defaults too).
#: A variant holds env-params overrides as sorted (name, value) pairs (hashable).
CORRIDOR_PARAMS = tuple(sorted(CORRIDOR_ENV_PARAMS.items()))


@dataclasses.dataclass(frozen=True)
class Variant:
    """One line of a figure.

    env: name for ``envs.make``. hedger: overrides for ``HedgerConfig.for_env`` (as a tuple of
    items so the variant is hashable). phase1: None, "simulated_person" (11 mountain-car
    demonstrations from a file-format round trip) or "hand_coded" (the corridor controller
    in control for ``phase1_episodes`` runs). x_axis: "points" or "episodes".
    state_scale_factors: multipliers on the [0, 1] state scaling, per state dimension.
    env_params: overrides of the environment's default params (name, value) pairs.
    params: ``HedgerParams`` overrides (name, value) pairs: traced settings, so variants that
    differ only here run as one program (``experiments.runner.run_sweep``).
    """

    label: str
    env: str
    hedger: Tuple[Tuple[str, Any], ...]
    run: RunConfig
    phase1: Optional[str] = None
    phase1_episodes: int = 0
    x_axis: str = "episodes"
    state_scale_factors: Optional[Tuple[float, ...]] = None
    env_params: Tuple[Tuple[str, Any], ...] = ()
    params: Tuple[Tuple[str, Any], ...] = ()

    def hedger_kwargs(self) -> Dict[str, Any]:
        return dict(self.hedger)


@dataclasses.dataclass(frozen=True)
class Figure:
    name: str
    title: str
    variants: Tuple[Variant, ...]
    x_label: str
    reference: Tuple[Tuple[str, str], ...] = ()  # (label, key into reference values)
    #: The paper's reported result(s) for this figure: (label, key into ``PAPER``).
    paper: Tuple[Tuple[str, str], ...] = ()
    #: Variants run only when named with ``--variant`` (too slow for the mode's default).
    optional: Tuple[Variant, ...] = ()


def _items(d: Dict[str, Any], **extra: Any) -> Tuple[Tuple[str, Any], ...]:
    return tuple(sorted(dict(d, **extra).items()))


def _mc_random_starts(mode: str, label: str, continuous: bool,
                      params: Optional[Dict[str, Any]] = None, **hedger_extra: Any) -> Variant:
    full = mode == "full"
    base = MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR
    n_blocks = 30 if full else 6
    return Variant(
        label=label,
        env="mountain_car_continuous" if continuous else "mountain_car_discrete",
        hedger=_items(base, capacity=(n_blocks + 1) * 10_000 + 400, **hedger_extra),
        run=RunConfig(n_blocks=n_blocks, episodes_per_block=None, points_per_block=10_000,
                      eval_episodes=2500 if full else 300),
        x_axis="points",
        params=_items(params or {}),
    )


def _mc_demos(mode: str, label: str, continuous: bool, params: Optional[Dict[str, Any]] = None,
              **hedger_extra: Any) -> Variant:
    full = mode == "full"
    base = MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR
    return Variant(
        label=label,
        env="mountain_car_continuous" if continuous else "mountain_car_discrete",
        hedger=_items(base, capacity=45_000, **hedger_extra),
        run=RunConfig(n_blocks=10 if full else 4, episodes_per_block=20 if full else 50,
                      eval_episodes=2500 if full else 200),
        phase1="simulated_person",
        x_axis="episodes",
        params=_items(params or {}),
    )


def _ablation(name: str, title: str, mode: str, off_label: str, off: Dict[str, Any],
              reference: Tuple[Tuple[str, str], ...]) -> Figure:
    """An ablation figure in the paper's "basic HEDGER" (random-start) setting: discrete and
    continuous, each with the feature on and off (the discrete pair first).

    Optional variants (``--variant "+ demos"``) run the same ablation in the Figure-2 setting
    (11 demonstrations, then phase-two runs): continuous actions learn little from random
    starts within the quick length (60,000 points), but do learn with demonstrations. The
    "on" lines are Figure 2's runs (cached results are shared: the label is not part of the
    cache key)."""
    demos = (_mc_demos(mode, "discrete + demos", False),
             _mc_demos(mode, f"discrete + demos, {off_label}", False, off),
             _mc_demos(mode, "continuous + demos", True),
             _mc_demos(mode, f"continuous + demos, {off_label}", True, off))
    return Figure(name, title,
                  (_mc_random_starts(mode, "discrete", False),
                   _mc_random_starts(mode, f"discrete, {off_label}", False, off),
                   _mc_random_starts(mode, "continuous", True),
                   _mc_random_starts(mode, f"continuous, {off_label}", True, off)),
                  "training points", reference, optional=demos)


def _paper_and_adaptive(make, mode: str, kind: str, continuous: bool) -> Tuple[Variant, ...]:
    """The paper's line and the adaptive kernel's line of one setting (one program)."""
    adaptive = ADAPTIVE_CONTINUOUS_PARAMS if continuous else ADAPTIVE_PARAMS
    return (make(mode, f"{kind} (paper)", continuous),
            make(mode, f"{kind} (adaptive)", continuous, adaptive))


def build_figure(name: str, mode: str = "quick") -> Figure:
    """The figure ``name`` ("fig1" ... "fig5") in ``mode`` ("quick" or "full")."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    full = mode == "full"
    if name == "fig1":
        return Figure("fig1", "Figure 1: HEDGER from random starts (mountain car)",
                      _paper_and_adaptive(_mc_random_starts, mode, "discrete", False)
                      + _paper_and_adaptive(_mc_random_starts, mode, "continuous", True),
                      "training points",
                      (("tabular Q-learning", "tabular_q_paper_reward"), ("optimal (grid DP)", "optimal_dp"),
                       ("random policy", "random")),
                      paper=(("paper: HEDGER after ~300,000 points", "fig1_converged"),))
    if name == "fig2":
        variants = list(_paper_and_adaptive(_mc_demos, mode, "discrete", False))
        continuous = _paper_and_adaptive(_mc_demos, mode, "continuous", True)
        if full:
            variants.extend(continuous)
        return Figure("fig2", "Figure 2: HEDGER with 11 demonstrations (mountain car)",
                      tuple(variants), "phase-two training runs",
                      (("demonstrators' mean", "demonstrators_mean"),
                       ("tabular Q-learning", "tabular_q_paper_reward"),
                       ("optimal (grid DP)", "optimal_dp")),
                      optional=() if full else continuous,
                      paper=(("paper: HEDGER after 200 runs", "fig2_after_200_runs"),))
    if name == "fig3":
        return _ablation("fig3", "Figure 3: HEDGER without the IVH check (mountain car)", mode,
                         "IVH off", dict(use_ivh=False),
                         (("random policy", "random"),
                          ("tabular Q-learning", "tabular_q_paper_reward")))
    if name == "fig4":
        return _ablation("fig4", "Figure 4: HEDGER without region updating (mountain car)",
                         mode, "no region update", dict(region_update=False),
                         (("tabular Q-learning", "tabular_q_paper_reward"),))
    if name == "fig5":
        paper = Variant(
            label="HEDGER (paper)",
            env="corridor",
            hedger=_items(CORRIDOR, capacity=12_000),
            run=RunConfig(n_blocks=6, episodes_per_block=5, **CORRIDOR_RUN,
                          eval_episodes=100 if full else 40, eval_max_steps=200),
            phase1="hand_coded",
            phase1_episodes=25,
            x_axis="episodes",
            state_scale_factors=CORRIDOR_SCALE_FACTORS,
            env_params=CORRIDOR_PARAMS,
        )
        # The adaptive kernel with the observation scaled only from its bounds.
        adaptive = dataclasses.replace(paper, label="HEDGER (adaptive)", state_scale_factors=None,
                                       params=_items(CORRIDOR_ADAPTIVE_PARAMS))
        return Figure("fig5", "Figure 5: corridor following (simulated robot)", (paper, adaptive),
                      "phase-two training runs",
                      (("hand-coded controller", "corridor_hand_coded"),
                       ("best achievable", "corridor_best")))
    raise ValueError(f"unknown figure {name!r}; known: fig1, fig2, fig3, fig4, fig5")


FIGURES = ("fig1", "fig2", "fig3", "fig4", "fig5")
