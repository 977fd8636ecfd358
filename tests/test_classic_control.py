"""Settings read from the task (``hedger_jax.task_settings``), phase 1 with a hand policy on
a Gymnasium env, the hand policies themselves, and the classic-control experiment's pieces."""
import json

import gymnasium
import numpy as np
import pytest

from experiments import classic_control
from experiments.hand_policies import HAND_POLICIES
from hedger_jax import presets
from hedger_jax.agent import RunConfig
from hedger_jax.learner import Hedger
from hedger_jax.task_settings import discount


def test_the_discount_follows_the_time_limit():
    assert [discount(t) for t in (10, 25, 100, 200, 500, 999)] == \
        [0.9, 0.92, 0.98, 0.99, 0.99, 0.99]


@pytest.mark.parametrize("env_id, gamma, action_scale", [
    ("Pendulum-v1", 0.99, 0.25), ("CartPole-v1", 0.99, None),
    ("MountainCarContinuous-v0", 0.99, 0.5)])
def test_a_gymnasium_id_gets_the_task_settings(env_id, gamma, action_scale):
    """No arguments: the TASK preset, the discount from the time limit, a continuous action
    spanning 1 in scaled units and explored in bursts; the paper's preset is still one
    argument away."""
    m = Hedger(env_id)
    cfg = m.config
    for k, v in presets.TASK.items():
        assert getattr(cfg, k) == v, k
    explore = "random" if action_scale is None else "bursts"      # by the action space
    assert cfg.gamma == gamma and m.run_config == RunConfig(eval_episodes=20,
                                                            eval_max_steps=m.env.max_steps,
                                                            exploration=explore)
    if action_scale is not None:
        assert cfg.input_scale[-1] == pytest.approx(action_scale)
    paper = Hedger(env_id, preset="paper").config
    assert paper.backup_sweeps == 0 and paper.gamma == 0.8 and paper.bandwidth_k == 0
    assert Hedger(env_id, capacity=64).config.capacity == 64          # overrides still win
    with pytest.raises(ValueError, match="preset"):
        Hedger(env_id, preset="nope")


def test_a_dict_run_config_overrides_the_task_s_own():
    """``run_config={...}`` changes those fields only: the task's evaluation protocol and
    HEDGER settings stay (a whole ``RunConfig()`` would bring its own evaluation defaults)."""
    m = Hedger("MountainCarContinuous-v0", run_config={"exploration": "random"}, capacity=64)
    assert m.run_config == RunConfig(exploration="random", eval_episodes=20,
                                      eval_max_steps=999)
    assert m.config.backup_sweeps == presets.TASK["backup_sweeps"]
    with pytest.raises(TypeError, match="nope"):
        Hedger("MountainCarContinuous-v0", run_config={"nope": 1}, capacity=64)


def test_the_jax_envs_keep_the_paper_s_presets():
    cfg = Hedger("HedgerMountainCar-v0").config
    assert cfg.backup_sweeps == 0 and cfg.gamma == presets.MOUNTAIN_CAR["gamma"]
    with pytest.raises(ValueError, match="'task'"):
        Hedger("HedgerMountainCar-v0", preset="task")


def test_learning_runs_past_the_capacity_keeping_the_newest_points():
    """A ring buffer: 600 steps into 256 slots, every slot then holds one of the newest 256
    transitions (the ones of the last episodes), each beside its point."""
    m = Hedger("CartPole-v1", capacity=256, seed=100)
    m.learn(600)
    mem = m.memory
    assert int(mem.size) == 256 and m.num_timesteps >= 600
    assert np.asarray(mem.transitions.present).all()
    assert np.all(np.isfinite(np.asarray(mem.values)))


def test_evaluate_reports_success_only_where_termination_is_the_goal():
    cart = Hedger("CartPole-v1", capacity=64, preset="paper")
    out = cart.evaluate(2)
    assert "success_rate" not in out and out["terminated_rate"] == 1.0   # the pole fell
    car = Hedger("MountainCar-v0", capacity=64, preset="paper")
    assert car.evaluate(1, max_steps=5)["success_rate"] == 0.0


@pytest.mark.parametrize("env_id, at_least", [
    ("MountainCar-v0", -130), ("MountainCarContinuous-v0", 85), ("Pendulum-v1", -300),
    ("CartPole-v1", 475), ("Acrobot-v1", -150)])
def test_each_hand_policy_does_its_job_on_gymnasium_s_env(env_id, at_least):
    """Mean return over 3 episodes of Gymnasium's own env (seeds 0-2)."""
    env = gymnasium.make(env_id)
    returns = []
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, r, terminated, truncated, _ = env.step(HAND_POLICIES[env_id](obs))
            total += r
            done = terminated or truncated
        returns.append(total)
    assert np.mean(returns) >= at_least, returns


def test_phase_one_with_a_hand_policy_on_a_gymnasium_env():
    """The policy is in control: every stored point's action is what it chose in that state
    (a Discrete index mapped to HEDGER's action value), and its steps count as phase one."""
    m = Hedger("MountainCar-v0", capacity=512, preset="paper", seed=1)
    m.learn_from_demonstrations(HAND_POLICIES["MountainCar-v0"], n_episodes=2)
    n = int(m.memory.size)
    assert m.num_demo_timesteps == n and 200 < n <= 400 and m.num_timesteps == 0
    pts = np.asarray(m.memory.points)[:, :n].T / np.asarray(m.config.input_scale) \
        + np.asarray(m.config.input_offset)
    chosen = np.asarray([HAND_POLICIES["MountainCar-v0"](p[:2]) for p in pts], float)
    np.testing.assert_allclose(pts[:, 2], chosen, atol=1e-5)
    with pytest.raises(Exception, match="n_episodes"):
        m.learn_from_demonstrations(HAND_POLICIES["MountainCar-v0"])


def test_the_summary_s_intervals_and_table():
    """Mean and 95 % t-interval per (task, method) against the closed form, a row per task."""
    recs = [{"env_id": "Pendulum-v1", "method": "hedger", "seed": s, "steps": [10, 20],
             "returns": [-900.0 + s, r], "final": {"mean_return": r}, "seconds": 3.0}
            for s, r in enumerate([-200.0, -180.0, -220.0])]
    row = classic_control.summarize(recs)["Pendulum-v1"]["hedger"]
    t975 = 4.302652729911275                          # Student t, 2 degrees of freedom
    assert row["mean"] == pytest.approx(-200.0)
    assert row["half"] == pytest.approx(t975 * 20.0 / np.sqrt(3))
    assert row["curve_mean"][0] == pytest.approx(-899.0)
    text = classic_control.table(classic_control.summarize(recs), quick=False)
    assert "| Pendulum-v1 | 20,000 (5,000) | -200.0 ± 49.7 (3 seeds, 3 s) | not run |" in text
    assert text.count("\n") == 1 + len(classic_control.TASKS)
    one = classic_control.table(classic_control.summarize(recs[:1]), quick=False)
    assert "| -200.0 (1 seed, 3 s) |" in one                  # no interval from one seed


def test_a_rerun_of_some_rows_keeps_the_others(tmp_path):
    """``--keep``: the earlier summary fills only the (task, method) cells without runs."""
    new = {"Pendulum-v1": {"hedger": {"mean": -150.0}}}
    earlier = {"Pendulum-v1": {"hedger": {"mean": -500.0}, "sb3": {"mean": -140.0}},
               "CartPole-v1": {"hedger": {"mean": 400.0}}}
    path = tmp_path / "classic_control.json"
    path.write_text(json.dumps({"summary": earlier}))
    merged = classic_control.keep_rows(new, str(path))
    assert merged == {"Pendulum-v1": {"hedger": {"mean": -150.0}, "sb3": {"mean": -140.0}},
                      "CartPole-v1": {"hedger": {"mean": 400.0}}}
    assert classic_control.keep_rows(new, None) is new
    path.write_text(json.dumps({"summary": {"Nope-v0": {}}}))
    with pytest.raises(ValueError, match="Nope-v0"):
        classic_control.keep_rows(new, str(path))


def test_a_run_logs_each_evaluation_as_it_goes():
    """The curve learns in ``CURVE_POINTS`` pieces from the start to the budget, evaluates
    after each (the last on ``FINAL_EPISODES``) and logs one line per evaluation."""
    learned, lines = [], []
    returns = iter(range(classic_control.CURVE_POINTS))
    rec = classic_control._curve(learned.append,
                                 lambda n: {"mean_return": -10.0 * next(returns), "n": n},
                                 100, 600, lines.append)
    n = classic_control.CURVE_POINTS
    assert sum(learned) == 500 and len(learned) == n
    assert rec["steps"][-1] == 600 and rec["final"]["n"] == classic_control.FINAL_EPISODES
    assert len(lines) == n and lines[-1].startswith(
        f"600 / 600 steps: greedy return {-10.0 * (n - 1):.1f}")


def test_a_learner_that_finishes_its_episodes_overshoots_the_budget_once():
    """``Hedger.learn`` runs whole episodes: each piece asks only for the steps left to its
    mark, so a learner overshooting every call by up to an episode (here 37 steps) ends
    less than one episode past the budget, and the record says where it ended."""
    at = [100]

    def learn(n):
        at[0] += n + 37 if n > 0 else 0

    rec = classic_control._curve(learn, lambda n: {"mean_return": 0.0}, 100, 600,
                                 position=lambda: at[0])
    assert 600 <= at[0] <= 600 + 37 and rec["env_steps"][-1] == at[0]
    assert rec["steps"][-1] == 600 and len(rec["steps"]) == classic_control.CURVE_POINTS
    assert all(m <= e <= m + 37 for m, e in zip(rec["steps"], rec["env_steps"]))
