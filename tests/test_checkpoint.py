"""Checkpoints: one file, bit-for-bit round trip, atomic writes, refusal of bad files."""
import json
import os
import zipfile

import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax import checkpoint as ck
from hedger_jax.agent import RunConfig
from hedger_jax.checkpoint import (CheckpointError, load_checkpoint, read_checkpoint_header,
                                   save_checkpoint)
from hedger_jax.config import HedgerConfig
from hedger_jax.memory import Memory, add_points, init_memory

CFG = HedgerConfig(2, 1, capacity=128, bandwidth=0.05, discrete_actions=((-1.0,), (0.0,), (1.0,)),
                   input_offset=(-1.2, -0.07, 0.0), input_scale=(1 / 1.7, 1 / 0.14, 1.0),
                   full_policy="overwrite_oldest")
RUN = RunConfig(epsilon=0.1, n_blocks=3, episodes_per_block=None, points_per_block=500,
                eval_episodes=10)


def _memory(seed=0, n=70):
    rng = np.random.default_rng(seed)
    S = rng.uniform([-1.2, -0.07], [0.5, 0.07], (n, 2)).astype(np.float32)
    A = rng.choice([-1.0, 0.0, 1.0], (n, 1)).astype(np.float32)
    V = (0.8 ** rng.uniform(0, 200, n)).astype(np.float32)        # down to ~4e-20
    mem = add_points(CFG, init_memory(CFG), S, A, V)
    return mem._replace(flags=jnp.int32(0))


def _arrays(mem):
    return [np.asarray(getattr(mem, k)) for k in ("points", "values", "size", "head", "flags")]


def _assert_bitwise(a, b):
    for x, y in zip(_arrays(a), _arrays(b)):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def test_round_trip_bit_for_bit(tmp_path):
    mem = _memory()
    key = np.asarray([7, 11], np.uint32)
    path = save_checkpoint(tmp_path / "a.npz", CFG, mem, RUN, seed=3, env_id="HedgerMountainCar-v0",
                           extra_arrays={"key": key}, metadata={"note": "hi"})
    assert os.listdir(tmp_path) == ["a.npz"]                 # one file, no temporaries
    out = load_checkpoint(path)
    assert out.config == CFG and out.run_config == RUN
    _assert_bitwise(mem, out.memory)
    assert out.extra_arrays["key"].dtype == np.uint32
    np.testing.assert_array_equal(out.extra_arrays["key"], key)
    m = out.metadata
    assert m["seed"] == 3 and m["env_id"] == "HedgerMountainCar-v0" and m["note"] == "hi"
    for k in ("library_version", "jax_version", "numpy_version", "python_version", "created"):
        assert m[k]
    h = read_checkpoint_header(path)
    assert h["format"] == "hedger-jax-checkpoint" and h["format_version"] == ck.FORMAT_VERSION
    # Loading with the same config / run config is accepted.
    load_checkpoint(path, config=CFG, run_config=RUN, env_id="HedgerMountainCar-v0")


def test_round_trip_batched_memory_and_no_run_config(tmp_path):
    a, b = _memory(0), _memory(1, n=40)
    batch = Memory(*(jnp.stack([x, y]) for x, y in zip(_arrays(a), _arrays(b))))
    save_checkpoint(tmp_path / "b.npz", CFG, batch)
    out = load_checkpoint(tmp_path / "b.npz")
    assert out.run_config is None and out.metadata["seed"] is None
    _assert_bitwise(batch, out.memory)


def test_overwrite_keeps_single_file(tmp_path):
    p = tmp_path / "c.npz"
    save_checkpoint(p, CFG, _memory(0))
    save_checkpoint(p, CFG, _memory(1))
    assert os.listdir(tmp_path) == ["c.npz"]
    _assert_bitwise(_memory(1), load_checkpoint(p).memory)


def test_interrupted_save_leaves_previous_file(tmp_path, monkeypatch):
    p = tmp_path / "d.npz"
    save_checkpoint(p, CFG, _memory(0))
    before = p.read_bytes()
    written = []

    def failing_write(f, data):
        f.write(data[: len(data) // 2])                       # partial bytes reach the disk...
        written.append(len(data) // 2)
        raise OSError(28, "No space left on device")          # ...then the write fails

    monkeypatch.setattr(ck, "_write_bytes", failing_write)
    with pytest.raises(OSError, match="No space left on device"):
        save_checkpoint(p, CFG, _memory(1))
    assert written and written[0] > 0
    assert p.read_bytes() == before                            # previous file intact
    assert os.listdir(tmp_path) == ["d.npz"]                   # temporary file removed
    _assert_bitwise(_memory(0), load_checkpoint(p).memory)


def test_interrupt_before_replace(tmp_path, monkeypatch):
    p = tmp_path / "e.npz"
    save_checkpoint(p, CFG, _memory(0))
    before = p.read_bytes()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ck.os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(p, CFG, _memory(1))
    monkeypatch.undo()
    assert p.read_bytes() == before and os.listdir(tmp_path) == ["e.npz"]


def test_truncated_file(tmp_path):
    p = tmp_path / "f.npz"
    save_checkpoint(p, CFG, _memory())
    data = p.read_bytes()
    for n in (0, 10, len(data) // 2, len(data) - 5):
        p.write_bytes(data[:n])
        with pytest.raises(CheckpointError, match=r"truncated or corrupt file"):
            load_checkpoint(p)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(CheckpointError, match=r"missing file \(no such file\)"):
        load_checkpoint(tmp_path / "nope.npz")
    with pytest.raises(CheckpointError, match="is a directory"):
        load_checkpoint(tmp_path)


def _rewrite(src, dst, header_fn=None, array_fn=None):
    """Re-pack a checkpoint with a modified header and/or arrays (valid zip, so only our own
    checks can find the problem)."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: np.array(z[k]) for k in z.files}
    header = json.loads(str(arrays.pop("header")))
    if header_fn:
        header = header_fn(header)
    if array_fn:
        array_fn(arrays)
    np.savez(dst, header=np.array(json.dumps(header)), **arrays)


def test_checksum_mismatch(tmp_path):
    p = tmp_path / "g.npz"
    save_checkpoint(p, CFG, _memory())

    def flip(arrays):
        v = arrays["memory/values"].copy()
        v.view(np.uint32)[3] ^= 1                               # one bit of one value
        arrays["memory/values"] = v

    _rewrite(p, tmp_path / "g2.npz", array_fn=flip)
    with pytest.raises(CheckpointError, match=r"checksum mismatch: array 'memory/values' is "
                                              r"corrupt"):
        load_checkpoint(tmp_path / "g2.npz")


def test_corrupted_bytes_in_place(tmp_path):
    p = tmp_path / "h.npz"
    save_checkpoint(p, CFG, _memory())
    data = bytearray(p.read_bytes())
    with zipfile.ZipFile(p) as z:
        info = z.getinfo("memory/values.npy")
    start = info.header_offset + 30 + len(info.filename) + 200   # inside the array's bytes
    data[start] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"corrupt"):
        load_checkpoint(p)


def test_version_and_format_mismatch(tmp_path):
    p = tmp_path / "i.npz"
    save_checkpoint(p, CFG, _memory())
    _rewrite(p, tmp_path / "v.npz", header_fn=lambda h: {**h, "format_version": 99})
    with pytest.raises(CheckpointError, match=r"unsupported format version 99 \(this hedger_jax "
                                              r"reads version 1\)"):
        load_checkpoint(tmp_path / "v.npz")
    _rewrite(p, tmp_path / "f.npz", header_fn=lambda h: {**h, "format": "something-else"})
    with pytest.raises(CheckpointError, match="not a hedger-jax checkpoint"):
        load_checkpoint(tmp_path / "f.npz")
    np.savez(tmp_path / "plain.npz", x=np.zeros(3))
    with pytest.raises(CheckpointError, match=r"not a hedger-jax checkpoint \(no header"):
        load_checkpoint(tmp_path / "plain.npz")


def test_header_array_disagreement(tmp_path):
    p = tmp_path / "j.npz"
    save_checkpoint(p, CFG, _memory())
    _rewrite(p, tmp_path / "j2.npz", array_fn=lambda a: a.pop("memory/head"))
    with pytest.raises(CheckpointError, match=r"missing arrays \['memory/head'\]"):
        load_checkpoint(tmp_path / "j2.npz")

    def bad_size(h):
        h = json.loads(json.dumps(h))
        return h

    def set_size(arrays):
        arrays["memory/size"] = np.asarray(500, np.int32)

    def fix_digest(h):
        h["arrays"]["memory/size"]["sha256"] = ck._digest(np.asarray(500, np.int32))
        return h

    _rewrite(p, tmp_path / "j3.npz", header_fn=fix_digest, array_fn=set_size)
    with pytest.raises(CheckpointError, match=r"the stored memory is invalid: memory.size: must "
                                              r"be in \[0, 128\], got 500"):
        load_checkpoint(tmp_path / "j3.npz")


def test_config_mismatch_is_refused_with_field_names(tmp_path):
    p = tmp_path / "k.npz"
    save_checkpoint(p, CFG, _memory(), RUN, env_id="HedgerMountainCar-v0")
    other = CFG.replace(bandwidth=0.02, alpha=0.5)
    with pytest.raises(CheckpointError, match=r"config mismatch in fields \['bandwidth', "
                                              r"'k_thresh', 'alpha', 'max_bandwidth'\]") as e:
        load_checkpoint(p, config=other)
    assert "file 0.05 != expected 0.02" in str(e.value)
    with pytest.raises(CheckpointError, match=r"config mismatch in fields \['capacity'\]"):
        load_checkpoint(p, config=CFG.replace(capacity=256))
    with pytest.raises(CheckpointError, match=r"run_config mismatch in fields \['epsilon'\]"):
        load_checkpoint(p, run_config=RunConfig(epsilon=0.3, n_blocks=3, episodes_per_block=None,
                                                points_per_block=500, eval_episodes=10))
    with pytest.raises(CheckpointError, match=r"env_id mismatch: file is for "
                                              r"'HedgerMountainCar-v0', expected 'corridor'"):
        load_checkpoint(p, env_id="corridor")
    assert issubclass(CheckpointError, ValueError)


def test_unknown_or_invalid_config_field(tmp_path):
    p = tmp_path / "l.npz"
    save_checkpoint(p, CFG, _memory())

    def add_field(h):
        h["hedger_config"]["warp_drive"] = True
        return h

    _rewrite(p, tmp_path / "l2.npz", header_fn=add_field)
    with pytest.raises(CheckpointError, match=r"HedgerConfig fields \['warp_drive'\] are unknown"):
        load_checkpoint(tmp_path / "l2.npz")

    def bad_value(h):
        h["hedger_config"]["bandwidth"] = -1.0
        return h

    _rewrite(p, tmp_path / "l3.npz", header_fn=bad_value)
    with pytest.raises(CheckpointError, match=r"stored HedgerConfig is invalid \(bandwidth: must "
                                              r"be a finite number > 0"):
        load_checkpoint(tmp_path / "l3.npz")


def test_save_refuses_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match=r"the memory does not fit the config: memory.points: "
                                         r"expected shape"):
        save_checkpoint(tmp_path / "m.npz", CFG.replace(capacity=64), _memory())
    with pytest.raises(ValueError, match=r"metadata keys \['seed'\] are reserved"):
        save_checkpoint(tmp_path / "m.npz", CFG, _memory(), metadata={"seed": 1})
    with pytest.raises(ValueError, match="extra array 'k' must be numeric"):
        save_checkpoint(tmp_path / "m.npz", CFG, _memory(), extra_arrays={"k": np.array(["x"])})
    assert not os.listdir(tmp_path)


def test_neighbour_index_is_rebuilt_on_load(tmp_path):
    """A grid-index config: the five arrays round-trip exactly and the index (derived state)
    is rebuilt, giving the same predictions."""
    import jax

    from hedger_jax.memory import uses_index
    from hedger_jax.prediction import predict

    cfg = CFG.replace(neighbour_index="grid", full_policy="error")
    assert uses_index(cfg)
    rng = np.random.default_rng(5)
    S = rng.uniform([-1.2, -0.07], [0.5, 0.07], (90, 2)).astype(np.float32)
    A = rng.choice([-1.0, 0.0, 1.0], (90, 1)).astype(np.float32)
    mem = add_points(cfg, init_memory(cfg), S, A, rng.uniform(0, 1, 90).astype(np.float32))
    save_checkpoint(tmp_path / "g.npz", cfg, mem)
    out = load_checkpoint(tmp_path / "g.npz", config=cfg)
    _assert_bitwise(mem, out.memory)
    assert out.memory.index is not None
    q = jax.jit(jax.vmap(lambda m, s, a: predict(cfg, m, s, a)[0], in_axes=(None, 0, 0)))
    np.testing.assert_array_equal(np.asarray(q(mem, S[:16], A[:16])),
                                  np.asarray(q(out.memory, S[:16], A[:16])))
