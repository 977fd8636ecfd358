"""Demonstrations file format, the episode recorder, and the simulated person."""
from __future__ import annotations

import json
import os
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.demonstrations import (ARRAY_FIELDS, DemonstrationFileError, Demonstrations,
                                 SCHEMA, SCHEMA_VERSION, _digest, concatenate,
                                 load_demonstrations, save_demonstrations)
from envs.demonstrators import (Policy, energy_pumping_policy, record_episodes,
                                simulated_person_demonstrations, simulated_person_policy)
from envs.mountain_car import MountainCar, bottom_start

PAPER_MEAN, PAPER_BEST = 210.0, 106.0


@pytest.fixture(scope="module")
def person_demos():
    return simulated_person_demonstrations(seed=0)


def _small_demos(E=3, T=5, obs_dim=2, action_dim=1, seed=0, env_id="mountain_car_discrete"):
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, T + 1, E)
    lengths[0] = T
    valid = np.arange(T)[None, :] < lengths[:, None]
    m3 = valid[..., None]
    term = np.zeros((E, T), bool)
    term[np.arange(E), lengths - 1] = True
    term[-1, lengths[-1] - 1] = False  # last episode: cut by the time limit
    trunc = np.zeros((E, T), bool)
    trunc[-1, lengths[-1] - 1] = True
    return Demonstrations(
        obs=(rng.normal(size=(E, T, obs_dim)) * m3).astype(np.float32),
        action=(rng.normal(size=(E, T, action_dim)) * m3).astype(np.float32),
        reward=(rng.normal(size=(E, T)) * valid).astype(np.float32),
        next_obs=(rng.normal(size=(E, T, obs_dim)) * m3).astype(np.float32),
        terminated=term, truncated=trunc, valid=valid, env_id=env_id, source="unit-test")


def _write_raw(path, arrays, meta_overrides=None, drop=(), metadata_text=None):
    """Write an npz bypassing all validation (with a *correct* digest unless overridden)."""
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    meta = {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "env_id": "mountain_car_discrete",
            "obs_dim": int(arrays["obs"].shape[-1]), "action_dim": int(arrays["action"].shape[-1]),
            "n_episodes": int(arrays["obs"].shape[0]),
            "lengths": [int(n) for n in np.asarray(arrays["valid"]).sum(1)],
            "source": "raw", "created": "now"}
    try:
        meta["sha256"] = _digest(arrays)
    except Exception:
        meta["sha256"] = "x"
    meta.update(meta_overrides or {})
    out = dict(arrays)
    out["metadata"] = np.array(metadata_text if metadata_text is not None else json.dumps(meta))
    for k in drop:
        out.pop(k)
    with open(path, "wb") as f:
        np.savez_compressed(f, **out)


def _raises(path, match, **kw):
    with pytest.raises(DemonstrationFileError, match=match):
        load_demonstrations(path, **kw)


# ---------------------------------------------------------------------------------------
# File format
# ---------------------------------------------------------------------------------------
def test_round_trip_bit_exact(tmp_path):
    d = _small_demos()
    p = tmp_path / "demos.npz"
    assert save_demonstrations(p, d, metadata={"person": "unit"}) == str(p)
    d2, meta = load_demonstrations(p, env_id="mountain_car_discrete", obs_dim=2, action_dim=1,
                                   return_metadata=True)
    assert d2.equals(d) and d.equals(d2)
    for k in ARRAY_FIELDS:
        a, b = getattr(d, k), getattr(d2, k)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    assert meta["schema"] == "hedger-demonstrations" and meta["schema_version"] == 1
    assert meta["env_id"] == "mountain_car_discrete" and meta["obs_dim"] == 2
    assert meta["action_dim"] == 1 and meta["n_episodes"] == 3
    assert meta["lengths"] == d.lengths.tolist() and meta["source"] == "unit-test"
    assert meta["person"] == "unit" and "created" in meta
    # Atomic write: no temporary file left behind; overwriting works.
    save_demonstrations(p, _small_demos(seed=1))
    assert sorted(os.listdir(tmp_path)) == ["demos.npz"]
    assert load_demonstrations(p).equals(_small_demos(seed=1))
    with pytest.raises(ValueError, match="reserved"):
        save_demonstrations(p, d, metadata={"env_id": "other"})


def test_dataclass_fields_and_lengths():
    d = _small_demos(E=4, T=6)
    assert d.obs.shape == (4, 6, 2) and d.obs.dtype == np.float32
    assert d.action.shape == (4, 6, 1) and d.reward.shape == (4, 6)
    assert d.next_obs.shape == (4, 6, 2)
    for k in ("terminated", "truncated", "valid"):
        assert getattr(d, k).dtype == np.bool_ and getattr(d, k).shape == (4, 6)
    assert d.lengths.tolist() == d.valid.sum(1).tolist() and d.lengths[0] == 6
    assert d.n_transitions == int(d.valid.sum())
    with pytest.raises(dataclasses_frozen_error()):
        d.env_id = "x"


def dataclasses_frozen_error():
    import dataclasses
    return dataclasses.FrozenInstanceError


def test_missing_file(tmp_path):
    _raises(tmp_path / "nope.npz", "missing file")


def test_truncated_file(tmp_path):
    p = tmp_path / "d.npz"
    save_demonstrations(p, _small_demos(E=5, T=50))
    data = p.read_bytes()
    for frac in (0.0, 0.1, 0.5, 0.9, 0.99):
        p.write_bytes(data[: int(len(data) * frac)])
        _raises(p, "truncated or corrupt")


def test_not_a_zip(tmp_path):
    p = tmp_path / "d.npz"
    p.write_bytes(b"this is not a zip file at all" * 10)
    _raises(p, "truncated or corrupt")


def test_flipped_bytes_in_every_member(tmp_path):
    p = tmp_path / "d.npz"
    save_demonstrations(p, _small_demos(E=5, T=50))
    data = p.read_bytes()
    with zipfile.ZipFile(p) as z:
        infos = z.infolist()
    assert len(infos) == 8  # 7 arrays + metadata
    for info in infos:
        # Data starts after the 30-byte local header, the name and the extra field.
        name_len = int.from_bytes(data[info.header_offset + 26: info.header_offset + 28], "little")
        extra_len = int.from_bytes(data[info.header_offset + 28: info.header_offset + 30], "little")
        start = info.header_offset + 30 + name_len + extra_len
        pos = start + info.compress_size // 2
        bad = bytearray(data)
        bad[pos] ^= 0xFF
        p.write_bytes(bytes(bad))
        with pytest.raises(DemonstrationFileError):
            load_demonstrations(p)


def test_wrong_schema_and_version(tmp_path):
    a = _small_demos().arrays()
    p = tmp_path / "d.npz"
    _write_raw(p, a, {"schema_version": 2})
    _raises(p, "schema_version 2")
    _write_raw(p, a, {"schema": "something-else"})
    _raises(p, "wrong schema")
    _write_raw(p, a, metadata_text="{not json")
    _raises(p, "not valid JSON")
    _write_raw(p, a, drop=("metadata",))
    _raises(p, r"missing arrays \['metadata'\]")
    m = {"schema": SCHEMA, "schema_version": 1}
    _write_raw(p, a, metadata_text=json.dumps(m))
    _raises(p, "lacks 'env_id'")


def test_missing_array(tmp_path):
    p = tmp_path / "d.npz"
    _write_raw(p, _small_demos().arrays(), drop=("reward",))
    _raises(p, r"missing arrays \['reward'\]")


def test_shape_mismatches(tmp_path):
    p = tmp_path / "d.npz"
    a = _small_demos(E=3, T=5).arrays()
    b = dict(a, reward=np.zeros((3, 6), np.float32))
    _write_raw(p, b)
    _raises(p, "shape mismatch: 'reward'")
    b = dict(a, next_obs=np.zeros((3, 5, 3), np.float32))
    _write_raw(p, b)
    _raises(p, "shape mismatch: 'next_obs'")
    b = dict(a, obs=np.zeros((3, 5), np.float32))
    _write_raw(p, b)
    _raises(p, "shape mismatch: obs")
    b = dict(a, valid=a["valid"][:2])
    _write_raw(p, b)
    _raises(p, "shape mismatch: 'valid'")
    b = dict(a, terminated=a["terminated"].astype(np.int8))
    _write_raw(p, b)
    _raises(p, "dtype int8, expected bool")


def test_caller_expectations(tmp_path):
    p = tmp_path / "d.npz"
    save_demonstrations(p, _small_demos())
    _raises(p, "env_id mismatch", env_id="corridor")
    _raises(p, "obs_dim mismatch", obs_dim=3)
    _raises(p, "action_dim mismatch", action_dim=2)
    load_demonstrations(p, env_id="mountain_car_discrete", obs_dim=2, action_dim=1)


def test_metadata_disagreeing_with_arrays(tmp_path):
    p = tmp_path / "d.npz"
    a = _small_demos().arrays()
    lengths = [int(n) for n in a["valid"].sum(1)]
    _write_raw(p, a, {"lengths": [n + 1 for n in lengths]})
    _raises(p, "lengths .* disagree with the valid mask")
    _write_raw(p, a, {"obs_dim": 7})
    _raises(p, "metadata obs_dim 7")
    _write_raw(p, a, {"n_episodes": 9})
    _raises(p, "metadata n_episodes 9")
    _write_raw(p, a, {"sha256": "0" * 64})
    _raises(p, "checksum mismatch")


@pytest.mark.parametrize("field,value", [("obs", np.nan), ("action", np.inf),
                                         ("reward", -np.inf), ("next_obs", np.nan)])
def test_nan_inf(tmp_path, field, value):
    p = tmp_path / "d.npz"
    a = _small_demos().arrays()
    x = a[field].copy()
    x[0, 1] = value
    _write_raw(p, dict(a, **{field: x}))
    _raises(p, f"'{field}' contains NaN or inf")


def test_valid_mask_not_prefix(tmp_path):
    p = tmp_path / "d.npz"
    a = _small_demos(E=3, T=5).arrays()
    v = a["valid"].copy()
    v[0] = [True, False, True, True, True]
    _write_raw(p, dict(a, valid=v))
    _raises(p, "valid mask is not a prefix")
    v = a["valid"].copy()
    v[1] = False
    _write_raw(p, dict(a, valid=v, terminated=a["terminated"] & v, truncated=a["truncated"] & v))
    _raises(p, "(not zero on padding|no valid step)")


def test_flag_consistency(tmp_path):
    p = tmp_path / "d.npz"
    a = _small_demos(E=3, T=5).arrays()
    t = a["terminated"].copy()
    t[0, 0] = True  # episode 0 has 5 valid steps: a terminal in the middle
    _write_raw(p, dict(a, terminated=t))
    _raises(p, "continues after a terminated/truncated step")
    tr = a["truncated"].copy()
    tr[0, 4] = True  # episode 0 ends terminated at t=4: both flags
    _write_raw(p, dict(a, truncated=tr))
    _raises(p, "both terminated and truncated")


def test_in_memory_validation():
    a = _small_demos().arrays()
    with pytest.raises(DemonstrationFileError, match="NaN"):
        Demonstrations(**dict(a, reward=np.full_like(a["reward"], np.nan)),
                       env_id="mountain_car_discrete")
    with pytest.raises(DemonstrationFileError, match="env_id"):
        Demonstrations(**a, env_id="")
    assert isinstance(DemonstrationFileError("x"), ValueError)


def test_concatenate_pads():
    d1, d2 = _small_demos(E=2, T=4, seed=1), _small_demos(E=3, T=7, seed=2)
    c = concatenate([d1, d2])
    assert c.obs.shape == (5, 7, 2)
    assert c.lengths.tolist() == d1.lengths.tolist() + d2.lengths.tolist()
    np.testing.assert_array_equal(c.obs[:2, :4], d1.obs)
    assert not c.valid[:2, 4:].any() and np.all(c.obs[:2, 4:] == 0)
    assert c.source == "unit-test"
    with pytest.raises(ValueError, match="env_id"):
        concatenate([d1, _small_demos(env_id="corridor")])
    with pytest.raises(ValueError, match="dims"):
        concatenate([d1, _small_demos(obs_dim=3)])
    with pytest.raises(ValueError):
        concatenate([])


# ---------------------------------------------------------------------------------------
# Recorder
# ---------------------------------------------------------------------------------------
def test_recorder_truncates_at_its_own_max_steps():
    env = MountainCar(False)  # its own limit is 200; the recorder's 1000 replaces it
    params = env.default_params()
    idle = Policy(init=lambda k: jnp.zeros((), jnp.int32),
                  act=lambda k, o, s: (jnp.zeros((1,), jnp.float32), s))
    d = record_episodes(env, params, idle, jax.random.PRNGKey(0), 2, 1000, start=bottom_start())
    assert d.obs.shape == (2, 1000, 2) and d.lengths.tolist() == [1000, 1000]
    assert not d.terminated.any()
    assert d.truncated[:, 999].all() and d.truncated.sum() == 2
    # Bottom of the hill, no push: oscillates gently, never at the goal.
    np.testing.assert_allclose(d.obs[:, 0], [[-0.5, 0.0]] * 2, atol=1e-7)


def test_recorder_episodes_are_consistent():
    env = MountainCar(False)
    params = env.default_params()
    pol = energy_pumping_policy()
    starts = jnp.array([[-0.5, 0.0], [0.3, 0.05], [-1.0, 0.0], [0.0, -0.07]], jnp.float32)
    d = record_episodes(env, params, pol, jax.random.PRNGKey(1), 4, 1000, start=starts,
                        source="pump")
    assert d.env_id == "mountain_car_discrete" and d.source == "pump"
    L = d.lengths
    assert d.obs.shape[1] == L.max() and (L < 200).all()
    assert d.lengths[0] == 124  # push-with-the-velocity from the bottom: 124 steps
    for e in range(4):
        n = L[e]
        np.testing.assert_array_equal(d.obs[e, 0], np.asarray(starts[e]))
        np.testing.assert_array_equal(d.obs[e, 1:n], d.next_obs[e, : n - 1])
        assert d.terminated[e, n - 1] and d.terminated[e].sum() == 1 and not d.truncated.any()
        assert d.next_obs[e, n - 1, 0] >= 0.5
        assert np.all(d.reward[e, : n - 1] == 0) and 0 <= d.reward[e, n - 1] <= 1
        np.testing.assert_allclose(d.reward[e, n - 1], 1 - abs(d.next_obs[e, n - 1, 1]) / 0.07,
                                   atol=1e-6)
        assert np.all(d.obs[e, n:] == 0) and not d.valid[e, n:].any()
    # Every recorded transition is the env's own step from the recorded obs (no drift).
    m = d.valid
    x, v, a = d.obs[m][:, 0], d.obs[m][:, 1], d.action[m]
    from envs.mountain_car import MountainCarState
    s = MountainCarState(position=jnp.asarray(x), velocity=jnp.asarray(v),
                         time=jnp.zeros(x.shape, jnp.int32))
    o, _, r, term, _, _ = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0, None)))(
        None, s, jnp.asarray(a), params)
    np.testing.assert_allclose(np.asarray(o), d.next_obs[m], atol=1e-7, rtol=0)
    np.testing.assert_array_equal(np.asarray(term), d.terminated[m])
    np.testing.assert_allclose(np.asarray(r), d.reward[m], atol=1e-6)
    # Random starts (start=None) are re-sampled per episode.
    d2 = record_episodes(env, params, pol, jax.random.PRNGKey(2), 4, 1000)
    assert len({tuple(o) for o in d2.obs[:, 0]}) == 4


# ---------------------------------------------------------------------------------------
# Simulated person
# ---------------------------------------------------------------------------------------
def test_simulated_person_matches_paper_statistics(person_demos):
    d = person_demos
    L = d.lengths
    print("simulated person lengths:", L.tolist(), "mean", L.mean(), "best", L.min())
    assert d.n_episodes == 11 and d.env_id == "mountain_car_discrete"
    assert abs(L.mean() - PAPER_MEAN) <= 0.15 * PAPER_MEAN
    assert abs(L.min() - PAPER_BEST) <= 0.15 * PAPER_BEST
    # All from the bottom, discrete keys, every run reaches the goal (none truncated).
    np.testing.assert_array_equal(d.obs[:, 0], np.tile(np.asarray(bottom_start()), (11, 1)))
    acts = d.action[d.valid]
    assert set(np.unique(acts).tolist()) <= {-1.0, 0.0, 1.0}
    assert (acts == 0).any()  # the person hesitates / coasts sometimes
    assert d.terminated[np.arange(11), L - 1].all() and not d.truncated.any()
    assert L.max() > 200  # not capped at 200


def test_simulated_person_is_seeded(person_demos):
    again = simulated_person_demonstrations(seed=0)
    assert again.equals(person_demos)
    other = simulated_person_demonstrations(seed=1)
    assert not other.equals(person_demos)
    assert other.lengths.tolist() != person_demos.lengths.tolist()


def test_simulated_person_policy_interface():
    pol = simulated_person_policy(1)
    assert simulated_person_policy(1) is pol and isinstance(pol, Policy)
    ps = pol.init(jax.random.PRNGKey(0))
    a, ps2 = jax.jit(pol.act)(jax.random.PRNGKey(1), jnp.array([-0.5, 0.0]), ps)
    assert a.shape == (1,) and a.dtype == jnp.float32 and float(a[0]) in (-1.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        simulated_person_policy(3)


def test_simulated_person_file_round_trip(tmp_path, person_demos):
    p = tmp_path / "person.npz"
    save_demonstrations(p, person_demos)
    loaded = load_demonstrations(p, env_id="mountain_car_discrete", obs_dim=2, action_dim=1)
    assert loaded.equals(person_demos)
    assert loaded.source == "simulated_person(seed=0)"
