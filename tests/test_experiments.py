"""The experiments layer: resumable seed-batched runs, result files, statistics, plots, CLI."""
import json
import os

import numpy as np
import pytest
from scipy import stats

from experiments import runner
from experiments.figures import FIGURES, Variant, _items, build_figure
from experiments.stats import mean_ci, welch_p
from experiments.summary import figure_summary
from hedger_jax.agent import RunConfig

#: A tiny run: at most 3 blocks x 2 episodes x 40 steps = 240 points per seed. Its memory
#: (256 slots, below 512) uses the brute-force neighbour search, which compiles about three
#: times faster than the grid index (the experiments layer, not the index, is tested here).
TINY = Variant(
    label="tiny",
    env="mountain_car_discrete",
    hedger=_items(dict(bandwidth=0.05, capacity=256)),
    run=RunConfig(n_blocks=3, episodes_per_block=2, eval_episodes=4, eval_max_steps=30,
                  train_max_steps=40),
    x_axis="episodes",
)


def test_mean_ci_matches_t_interval():
    x = np.array([[1.0, 10.0], [2.0, 12.0], [4.0, 11.0], [3.0, 15.0]])
    mean, half = mean_ci(x, axis=0)
    for j in range(2):
        lo, hi = stats.t.interval(0.95, 3, loc=x[:, j].mean(), scale=stats.sem(x[:, j]))
        assert mean[j] == pytest.approx(x[:, j].mean())
        assert mean[j] - half[j] == pytest.approx(lo)
        assert mean[j] + half[j] == pytest.approx(hi)
    assert mean_ci(np.array([[3.0]]))[1] == 0.0


def test_welch_p():
    rng = np.random.default_rng(0)
    assert welch_p(rng.normal(0, 1, 30), rng.normal(3, 1, 30)) < 1e-6
    assert welch_p(np.ones(5), np.ones(5)) == 1.0
    assert welch_p(np.ones(5), 2 * np.ones(5)) == 0.0


def test_every_figure_builds_in_both_modes():
    for name in FIGURES:
        for mode in ("quick", "full"):
            fig = build_figure(name, mode)
            assert fig.variants and fig.name == name
            for v in fig.variants:
                hash(v)  # static, hashable
    with pytest.raises(ValueError, match="unknown figure"):
        build_figure("fig9")
    with pytest.raises(ValueError, match="mode"):
        build_figure("fig1", "slow")


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    runner.atomic_write_json(str(path), {"a": 1})

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        runner.atomic_write_json(str(path), {"a": 2})
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temp file left behind


def test_run_variant_resumes_after_interruption(tmp_path):
    out = str(tmp_path)
    calls = []

    def interrupt(block):
        calls.append(block)
        if block == 2:
            raise KeyboardInterrupt

    # Every run in this module uses batches of 2 seeds: one compilation of the batched init and
    # block for all of them.
    seeds = [0, 1, 2, 3]
    with pytest.raises(KeyboardInterrupt):
        runner.run_variant(TINY, seeds, out, seed_batch=2, progress=False, on_block=interrupt)
    assert calls == [1, 2]
    # The checkpoint holds blocks 0..2 of the first batch; resuming runs only block 3 there.
    resumed = []
    rec = runner.run_variant(TINY, seeds, out, seed_batch=2, progress=False,
                             on_block=resumed.append)
    assert resumed == [3, 1, 2, 3]  # batch 1 resumes at block 3; batch 2 (seeds 2, 3) from scratch
    assert rec["complete"]
    assert np.asarray(rec["mean_steps"]).shape == (4, 4)
    assert np.asarray(rec["episodes"]).tolist() == [[0, 2, 4, 6]] * 4
    ms = np.asarray(rec["mean_steps"])
    assert np.all((ms >= 1) & (ms <= 30))
    # The same seeds run uninterrupted, each at another place in another batch, give the same
    # numbers (seed i's key depends neither on batching nor on resumption).
    swapped = [1, 0, 3, 2]
    fresh = runner.run_variant(TINY, swapped, str(tmp_path / "fresh"), seed_batch=2,
                               progress=False)
    np.testing.assert_allclose(fresh["mean_steps"], ms[swapped], rtol=1e-5)
    assert not np.allclose(ms[0], ms[1])  # the seeds really differ
    # A finished variant is read from its result file, not recomputed.
    again = []
    runner.run_variant(TINY, seeds, out, seed_batch=2, progress=False, on_block=again.append)
    assert again == []
    # The same run under another label (another figure's name for it) is shared, and is
    # reported under the label it was asked for.
    import dataclasses
    renamed = runner.run_variant(dataclasses.replace(TINY, label="tiny, as in fig. 9"),
                                 seeds, out, seed_batch=2, progress=False,
                                 on_block=again.append)
    assert again == [] and renamed["label"] == "tiny, as in fig. 9"
    assert renamed["mean_steps"] == rec["mean_steps"]
    # No checkpoints remain once batches are finished.
    assert not [p for p in os.listdir(os.path.join(out, "cache")) if p.startswith("ckpt-")]


@pytest.mark.full   # ~30 s; map mode runs in the other experiment tests (auto on CPU)
def test_seed_mode_map_runs_each_seed_alone(tmp_path):
    """seed_mode="map": the batch's seeds one after another in one program. Each seed runs the
    one-seed program, so its numbers do not depend on the batch it ran in (batches of 2 and of
    1 agree bit for bit, resumption included)."""
    seeds = [0, 1, 2]
    calls = []

    def interrupt(block):
        calls.append(block)
        if block == 2:
            raise KeyboardInterrupt

    out = str(tmp_path / "map2")
    with pytest.raises(KeyboardInterrupt):
        runner.run_variant(TINY, seeds, out, seed_batch=2, progress=False, on_block=interrupt,
                           seed_mode="map")
    pairs = runner.run_variant(TINY, seeds, out, seed_batch=2, progress=False, seed_mode="map")
    ones = runner.run_variant(TINY, seeds, str(tmp_path / "map1"), seed_batch=1,
                              progress=False, seed_mode="map")
    assert pairs["complete"] and np.asarray(pairs["mean_steps"]).shape == (3, 4)
    for name in ("mean_steps", "points", "episodes", "memory_size"):
        np.testing.assert_array_equal(np.asarray(pairs[name]), np.asarray(ones[name]), name)
    assert np.asarray(pairs["episodes"]).tolist() == [[0, 2, 4, 6]] * 3
    ms = np.asarray(pairs["mean_steps"])
    assert np.all((ms >= 1) & (ms <= 30)) and not np.allclose(ms[0], ms[1])
    assert runner.resolve_seed_mode("vmap") == "vmap"
    assert runner.resolve_seed_mode("auto") in ("map", "vmap")
    with pytest.raises(ValueError, match="seed_mode"):
        runner.resolve_seed_mode("pmap")


def test_a_sweep_program_takes_only_the_settings_its_variants_vary(tmp_path, monkeypatch):
    """run_sweep bakes the settings that every variant shares into its programs as constants
    (a program with every setting traced compiles about twice as long): with two variants
    that differ in bandwidth, it (with the radius it sets) is the programs' only input, and each
    record holds its own variant's settings."""
    import dataclasses

    from hedger_jax.params import FIELDS

    varying = []
    real = runner.with_shared_settings

    def spy(fn, treedef, constants):
        fixed = {i for i, _ in constants}
        varying.append([FIELDS[i] for i in range(treedef.num_leaves) if i not in fixed])
        return real(fn, treedef, constants)

    monkeypatch.setattr(runner, "with_shared_settings", spy)
    runner.compiled_group.cache_clear()
    narrow, wide = (dataclasses.replace(TINY, label=f"h {h}", params=_items(dict(bandwidth=h)))
                    for h in (0.03, 0.2))
    records = runner.run_sweep([narrow, wide], [0, 1], str(tmp_path), progress=False,
                               seed_mode="map")
    # init and run_block; the neighbour radius k_thresh follows the bandwidth.
    assert varying == [["bandwidth", "k_thresh"]] * 2
    assert [r["params"]["bandwidth"] for r in records] == pytest.approx([0.03, 0.2])
    runner.run_variant(wide, [0, 1], str(tmp_path / "alone"), progress=False, seed_mode="map")
    assert varying[2:] == [[], []]                       # one variant: every setting shared


_TWO_DEVICES = """
import sys, numpy as np, jax, pytest
sys.path.insert(0, {tests!r})
from test_experiments import TINY
from experiments import runner
assert len(jax.devices()) == 2
out = sys.argv[1]
seeds = [0, 1, 2]                                    # padded to 4 on 2 devices

def stop(block):
    if block == 2:
        raise KeyboardInterrupt

try:
    runner.run_variant(TINY, seeds, out + "/two", seed_batch=3, progress=False, on_block=stop,
                       seed_mode="map", devices=2)
except KeyboardInterrupt:
    pass
two = runner.run_variant(TINY, seeds, out + "/two", seed_batch=3, progress=False,
                         seed_mode="map", devices=2)
one = runner.run_variant(TINY, seeds, out + "/one", seed_batch=3, progress=False,
                         seed_mode="map", devices=1)
for name in ("mean_steps", "points", "episodes", "memory_size"):
    np.testing.assert_array_equal(np.asarray(two[name]), np.asarray(one[name]), name)
assert np.asarray(two["mean_steps"]).shape == (3, 4)
print("OK")
"""


@pytest.mark.full   # ~40 s; tests/test_sharding.py covers the split over two devices
def test_seed_batches_split_over_two_forced_cpu_devices(tmp_path):
    """devices=2 (map): each device runs its share of a batch padded to a multiple of the
    device count; resumed from a checkpoint, the numbers equal one device's bit for bit."""
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu",
               PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    code = _TWO_DEVICES.format(tests=os.path.join(root, "tests"))
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env, cwd=root,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "OK" in proc.stdout


def test_corrupt_checkpoint_is_not_trusted(tmp_path):
    out = str(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        runner.run_variant(TINY, [0, 1], out, progress=False,
                           on_block=lambda b: (_ for _ in ()).throw(KeyboardInterrupt()))
    ckpts = sorted(p for p in os.listdir(os.path.join(out, "cache")) if p.startswith("ckpt-"))
    # One file per member (seed), after block 1; block 0's were dropped once block 1's existed.
    assert [p.split("-", 2)[2] for p in ckpts] == ["m0-b1.npz", "m1-b1.npz"]
    path = os.path.join(out, "cache", ckpts[1])
    data = open(path, "rb").read()
    open(path, "wb").write(data[: len(data) // 2])
    blocks = []
    rec = runner.run_variant(TINY, [0, 1], out, progress=False, on_block=blocks.append)
    assert blocks == [1, 2, 3]  # restarted from scratch
    assert rec["complete"]


def test_summary_and_plot(tmp_path):
    from experiments.plotting import plot_figure

    rec = runner.run_variant(TINY, [0, 1], str(tmp_path), progress=False)
    fake_on = dict(rec, label="discrete")
    fake_off = dict(rec, label="discrete, IVH off",
                    mean_steps=(np.asarray(rec["mean_steps"]) + 50).tolist())
    data = {"figure": "fig3", "title": "t", "mode": "quick", "variants": [fake_on, fake_off],
            "reference": {"random policy": 163.0}}
    text = figure_summary(data)
    assert "| discrete | 2 |" in text and "IVH off" in text and "Welch p" in text
    png = tmp_path / "f.png"
    plot_figure(str(png), "t", "runs", [fake_on, fake_off], {"random policy": 163.0})
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_rejects_bad_arguments(capsys):
    from experiments.__main__ import main

    with pytest.raises(SystemExit):
        main(["fig7"])
    with pytest.raises(SystemExit):
        main(["fig1", "--seeds", "0"])
    with pytest.raises(SystemExit):
        main(["fig1", "--seed-mode", "pmap"])
    with pytest.raises(SystemExit):
        main(["fig1", "--devices", "0"])


def test_select_variants_optional_and_eval_episodes():
    from experiments.__main__ import select_variants

    fig = build_figure("fig2", "quick")
    assert [v.label for v in fig.variants] == ["discrete (paper)", "discrete (adaptive)"]
    assert [v.label for v in fig.optional] == ["continuous (paper)", "continuous (adaptive)"]
    # The adaptive kernel is a traced setting: both lines are one program.
    assert runner.static_part(fig.variants[0]) == runner.static_part(fig.variants[1])
    assert dict(fig.variants[1].params)["bandwidth_k"] > 0
    # Default: the default variants only, unchanged.
    same = select_variants(fig)
    assert same.variants == fig.variants and same.optional == ()
    # --variant reaches the optional (slow) variant; --eval-episodes overrides the protocol.
    cont = select_variants(fig, ["continuous"], eval_episodes=7)
    assert [v.label for v in cont.variants] == ["continuous (paper)", "continuous (adaptive)"]
    assert cont.variants[0].env == "mountain_car_continuous"
    assert cont.variants[0].run.eval_episodes == 7
    assert cont.variants[0].run.n_blocks == fig.optional[0].run.n_blocks
    with pytest.raises(SystemExit, match="matches none"):
        select_variants(fig, ["no such variant"])
    # --full runs the continuous variant by default.
    full = build_figure("fig2", "full")
    assert [v.label for v in full.variants] == ["discrete (paper)", "discrete (adaptive)",
                                                "continuous (paper)", "continuous (adaptive)"]
    assert full.optional == ()


def test_ablation_demo_variants_share_figure2_cache_key():
    from experiments.__main__ import select_variants

    fig4 = select_variants(build_figure("fig4", "quick"), ["continuous + demos"])
    assert [v.label for v in fig4.variants] == ["continuous + demos",
                                                "continuous + demos, no region update"]
    assert fig4.x_label == "phase-two training runs"
    # The ablation switch is a traced setting: on and off are one program.
    assert dict(fig4.variants[1].params)["region_update"] is False
    assert runner.static_part(fig4.variants[0]) == runner.static_part(fig4.variants[1])
    fig2 = select_variants(build_figure("fig2", "quick"), ["continuous"])
    # Same run, different label: one cache entry.
    assert runner.variant_key(fig4.variants[0], [0, 1], 0) == \
        runner.variant_key(fig2.variants[0], [0, 1], 0)
    assert runner.variant_key(fig4.variants[0], [0, 1], 0) != \
        runner.variant_key(fig4.variants[1], [0, 1], 0)
    fig3 = select_variants(build_figure("fig3", "quick"), ["discrete + demos"])
    assert dict(fig3.variants[1].params)["use_ivh"] is False



def test_group_config_covers_the_widest_selection_radius():
    """A group with an adaptive-kernel line: the grid is sized for its selection radius
    (kernel_range times the paper's), so its params pass the host check."""
    fig = build_figure("fig2", "quick")
    config = runner.group_config(list(fig.variants))
    widest = max(runner.params_of(v, config).k_thresh for v in fig.variants)
    assert config.max_k_thresh >= widest * (1 - 1e-6)
    assert widest == pytest.approx(config.k_thresh * dict(fig.variants[1].params)["kernel_range"],
                                   rel=1e-5)


def test_bandwidth_study_methods_and_robustness_plot(tmp_path):
    """Methods by name or as name:key=value lists; the robustness plot draws one line per
    method with its 95 % band (a PNG of the size the figures use)."""
    from experiments.bandwidth_study import METHODS, _parse_method
    from experiments.plotting import plot_robustness

    assert _parse_method("adaptive") == dict(METHODS["adaptive"])
    assert _parse_method("x:bandwidth_k=8,kernel_range=8.0,value_eps=1e-6") == \
        {"bandwidth_k": 8, "kernel_range": 8.0, "value_eps": 1e-6}
    assert _parse_method("adaptive:kernel_range=3.0") == {**METHODS["adaptive"],
                                                          "kernel_range": 3.0}
    rows = [{"method": m, "bandwidth": h, "per_seed_final": [60.0 + i, 62.0, 64.0 + h]}
            for m in ("paper", "adaptive") for i, h in enumerate((0.01, 0.05, 0.1))]
    path = tmp_path / "robustness.png"
    plot_robustness(str(path), "t", rows, {"paper": 56})
    import matplotlib.image

    assert matplotlib.image.imread(str(path)).shape[:2] == (1350, 2100)


def _adaptive_lines():
    """(figure, variant) of every adaptive line of the quick figures, optional ones included."""
    for name in ("fig1", "fig2", "fig5"):
        fig = build_figure(name, "quick")
        for v in fig.variants + fig.optional:
            if "adaptive" in v.label:
                yield name, v


def test_adaptive_lines_use_the_data_chosen_width_with_both_action_kinds():
    """Every adaptive line -- discrete and continuous actions alike -- uses the kernel width
    read from the stored data (``bandwidth_k`` > 0); only the continuous-action lines narrow
    it as the memory fills (``bandwidth_shrink``). Each line's settings are the library's
    presets (read from ``hedger_jax.presets``, not retyped), and build without a warning."""
    import warnings

    import hedger_jax
    from hedger_jax import presets

    assert dict(presets.ADAPTIVE_PARAMS) == dict(hedger_jax.ADAPTIVE)
    assert dict(presets.ADAPTIVE_CONTINUOUS_PARAMS) == dict(
        hedger_jax.ADAPTIVE_CONTINUOUS, action_scale=presets.ADAPTIVE_CONTINUOUS_PARAMS[
            "action_scale"])
    assert dict(hedger_jax.ADAPTIVE_CONTINUOUS) == dict(hedger_jax.ADAPTIVE,
                                                        bandwidth_shrink=True)
    want = {"mountain_car_discrete": presets.ADAPTIVE_PARAMS,
            "mountain_car_continuous": presets.ADAPTIVE_CONTINUOUS_PARAMS,
            "corridor": presets.CORRIDOR_ADAPTIVE_PARAMS}
    envs_seen = set()
    for name, v in _adaptive_lines():
        params = dict(v.params)
        assert params == dict(want[v.env]), (name, v.label)
        assert params["bandwidth_k"] > 0, (name, v.label)
        continuous = v.env != "mountain_car_discrete"
        assert params.get("bandwidth_shrink", False) == continuous, (name, v.label)
        envs_seen.add(v.env)
    assert envs_seen == set(want)                 # both action kinds (and the corridor) seen
    corridor = build_figure("fig5", "quick").variants[1]
    assert "adaptive" in corridor.label and corridor.state_scale_factors is None
    # Every line of these figures builds its traced settings without a warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in ("fig1", "fig2", "fig5"):
            fig = build_figure(name, "quick")
            for v in fig.variants + fig.optional:
                runner.params_of(v, runner.group_config([v]))
