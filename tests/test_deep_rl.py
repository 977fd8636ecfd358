"""experiments.deep_rl: start protocols, steps-to-goal evaluation, first-reach, resumable
sweep and summary (no SB3 needed); tiny SB3 runs where stable-baselines3 is installed."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from experiments import deep_rl as d  # noqa: E402


def _starts(protocol, continuous=False, n=300):
    env = d.make_env(protocol, continuous)
    out = []
    for s in range(n):
        obs, _ = env.reset(seed=s)
        state = np.asarray(env.unwrapped.state, np.float64)
        np.testing.assert_allclose(obs, state, rtol=0, atol=1e-7)   # obs = float32 state
        out.append(state)
    return np.array(out)


@pytest.mark.parametrize("continuous", [False, True])
def test_random_starts_follow_the_papers_distribution(continuous):
    x, v = _starts("random", continuous).T
    assert x.min() >= -1.2 and x.max() < 0.5
    assert v.min() >= -0.07 and v.max() < 0.07
    # spread over the whole range (300 uniform draws), both velocity signs
    assert x.min() < -1.1 and x.max() > 0.4 and v.min() < -0.06 and v.max() > 0.06
    assert abs(x.mean() - (-0.35)) < 0.1 and abs(v.mean()) < 0.01
    assert len(np.unique(x)) == len(x)


@pytest.mark.parametrize("continuous", [False, True])
def test_gymnasium_starts_are_gymnasiums_own(continuous):
    import gymnasium as gym

    x, v = _starts("gymnasium", continuous, n=50).T
    assert x.min() >= -0.6 and x.max() < -0.4 and np.all(v == 0.0)
    plain = gym.make("MountainCarContinuous-v0" if continuous else "MountainCar-v0")
    for s in range(50):
        np.testing.assert_array_equal(plain.reset(seed=s)[0], np.float32([x[s], v[s]]))


def test_random_starts_are_seeded_and_stepped_from():
    env = d.make_env("random")
    a = env.reset(seed=7)[0]
    b = env.reset(seed=7)[0]
    c = env.reset(seed=8)[0]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    env.reset(seed=7)
    x, v = (float(z) for z in env.unwrapped.state)
    obs, *_ = env.step(2)                         # push right once from the set state
    v2 = min(max(v + 0.001 - 0.0025 * math.cos(3 * x), -0.07), 0.07)
    np.testing.assert_allclose(obs, [x + v2, v2], atol=1e-6)


def test_unknown_protocol_is_refused():
    with pytest.raises(ValueError, match="protocol"):
        d.make_env("paper")


def _hand_rollout(x, v, push, continuous, cap=200):
    """An independent rollout of mountain car (Sutton & Barto; MountainCarContinuous: power
    0.0015, goal 0.45, state kept in float32): steps to the goal, ``cap`` if not reached."""
    power, goal = (0.0015, 0.45) if continuous else (0.001, 0.5)
    for t in range(1, cap + 1):
        a = push(v)
        v = min(max(v + a * power - 0.0025 * math.cos(3 * x), -0.07), 0.07)
        x = min(max(x + v, -1.2), 0.6)
        if x == -1.2 and v < 0:
            v = 0.0
        if continuous:
            x, v = float(np.float32(x)), float(np.float32(v))
        if x >= goal and v >= 0:
            return t
    return cap


def _eval_starts(protocol, continuous, n):
    env = d.make_env(protocol, continuous)
    out = []
    for i in range(n):
        env.reset(seed=d.EVAL_SEED + i)
        out.append(tuple(float(z) for z in env.unwrapped.state))
    return out


@pytest.mark.parametrize("protocol", d.PROTOCOLS)
@pytest.mark.parametrize("continuous", [False, True])
def test_steps_to_goal_of_energy_pumping_match_an_independent_rollout(protocol, continuous):
    n = 12
    if continuous:
        def act(obs):
            return np.where(obs[:, 1] >= 0, 1.0, -1.0)[:, None]
    else:
        def act(obs):
            return np.where(obs[:, 1] >= 0, 2, 0)
    got = d.evaluate_steps(act, protocol, n, continuous)
    want = [_hand_rollout(x, v, lambda vel: 1.0 if vel >= 0 else -1.0, continuous)
            for x, v in _eval_starts(protocol, continuous, n)]
    np.testing.assert_array_equal(got, want)
    assert got.max() < 200 and len(np.unique(got)) > 1      # a real, varied measurement


@pytest.mark.parametrize("continuous", [False, True])
def test_failures_count_as_the_cap(continuous):
    def coast(obs):
        return np.zeros((len(obs), 1)) if continuous else np.ones(len(obs), int)

    got = d.evaluate_steps(coast, "gymnasium", 5, continuous)
    np.testing.assert_array_equal(got, 200.0)
    # A cap below the episode's length: the episode counts the cap.
    pump = (lambda o: np.sign(o[:, 1:] + 1e-12)) if continuous else \
        (lambda o: np.where(o[:, 1] >= 0, 2, 0))
    full = d.evaluate_steps(pump, "random", 6, continuous)
    short = d.evaluate_steps(pump, "random", 6, continuous, cap=40)
    np.testing.assert_array_equal(short, np.where(full <= 40, full, 40))


def test_first_reach_is_the_first_evaluation_at_or_below_the_target():
    xs = [1000, 2000, 3000, 4000, 5000]
    assert d.first_reach(xs, [200, 150, 110, 90, 130]) == 3000        # <= counts
    assert d.first_reach(xs, [200, 111, 95, 130, 80]) == 3000
    assert d.first_reach(xs, [109, 200, 200, 200, 200]) == 1000       # first, not last
    assert d.first_reach(xs, [200, 180, 150, 120, 110.5]) is None
    assert d.first_reach(xs, [200, 180, 150, 120, 100], target=90) is None


def _fake_runner(calls, stop_after=None):
    def runner(method, protocol, seed, steps, eval_every, hedger_episodes):
        if stop_after is not None and len(calls) >= stop_after:
            raise KeyboardInterrupt
        calls.append((method, protocol, seed))
        curve = [200.0, 150.0, 100.0 + seed] if seed % 2 == 0 else [200.0, 190.0, 180.0]
        return {"method": method, "protocol": protocol, "seed": seed,
                "env_steps": [1000, 2000, 3000], "mean_steps": curve,
                "success_rate": [0.0, 0.5, 1.0], "final_steps": curve[-1],
                "first_reach": d.first_reach([1000, 2000, 3000], curve),
                "wall_s": 10.0 + seed}
    return runner


def test_sweep_resumes_after_being_killed(tmp_path):
    out = str(tmp_path / "res")
    args = (["dqn", "hedger"], ["gymnasium", "random"], range(2), out, d.BUDGET,
            d.EVAL_EVERY, 10)
    calls = []
    with pytest.raises(KeyboardInterrupt):
        d.sweep(*args, runner=_fake_runner(calls, stop_after=3))
    assert len(calls) == 3
    files = sorted(os.listdir(out))
    assert len(files) == 3 and all(f.endswith(".json") for f in files)   # no partial file
    calls2 = []
    written = d.sweep(*args, runner=_fake_runner(calls2))
    assert len(calls2) == 5 and len(written) == 5
    assert set(calls) | set(calls2) == {(m, p, s) for m in ("dqn", "hedger")
                                         for p in ("gymnasium", "random") for s in (0, 1)}
    assert d.sweep(*args, runner=_fake_runner([])) == []               # all done: nothing
    with open(d.result_path(out, "dqn", "random", 1)) as f:
        assert json.load(f)["seed"] == 1


def test_summary_counts_seeds_that_reached_and_tables_say_never(tmp_path):
    out = str(tmp_path / "res")
    d.sweep(["dqn"], ["random"], range(4), out, d.BUDGET, d.EVAL_EVERY, 10,
            runner=_fake_runner([]))
    rows = d.summarize(d.load_results(out))
    row = rows["random"]["dqn"]
    assert row["n"] == 4 and row["reached"] == 2              # seeds 0 and 2 reach 100, 102
    assert row["first_reach"][0] == 3000.0 and row["first_reach"][1] == 0.0
    np.testing.assert_allclose(row["final"][0], np.mean([100, 180, 102, 180]))
    np.testing.assert_allclose(row["wall_s"][0], 11.5)
    text = d.table(rows, "random")
    assert "| dqn | 3,000 | 3,000 ± 0 (2/4) |" in text
    d.sweep(["ppo"], ["random"], [1], out, d.BUDGET, d.EVAL_EVERY, 10,
            runner=_fake_runner([]))
    assert "| ppo | 3,000 | never (0/1) |" in d.table(d.summarize(d.load_results(out)),
                                                       "random")


def test_hedger_protocol_params_give_the_protocols_starts():
    import jax

    from envs.mountain_car import MountainCar

    env = MountainCar()
    for protocol, (x_lo, x_hi, v_lo, v_hi) in d.STARTS.items():
        obs, _ = env.evaluation_starts(jax.random.PRNGKey(0), d.hedger_env_params(env, protocol),
                                       500)
        x, v = np.asarray(obs).T
        assert x.min() >= x_lo and x.max() < x_hi and v.min() >= v_lo and v.max() <= v_hi
        assert x.max() - x.min() > 0.9 * (x_hi - x_lo)
        assert v.max() - v.min() >= 0.9 * (v_hi - v_lo)


@pytest.mark.parametrize("method,steps,every", [("dqn", 320, 160), ("ppo", 512, 256),
                                                ("sac", 64, 32)])
def test_sb3_runs_record_a_curve(method, steps, every):
    pytest.importorskip("stable_baselines3")
    rec = d.run_sb3(method, "random", 0, steps, every, eval_episodes=2, final_episodes=3)
    assert rec["env_steps"][-1] == steps and rec["env_steps"] == sorted(rec["env_steps"])
    assert len(rec["env_steps"]) == steps // every
    assert all(1 <= y <= 200 for y in rec["mean_steps"])
    assert rec["final_steps"] == rec["mean_steps"][-1] and len(rec["final_per_episode"]) == 3
    assert rec["wall_s"] >= rec["eval_s"] > 0
