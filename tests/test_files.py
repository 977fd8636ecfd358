"""Files the project writes: atomic, with the permissions a plain ``open`` gives."""
import os
import stat

import numpy as np
import pytest

from envs.demonstrations import Demonstrations, save_demonstrations
from experiments.runner import atomic_write_bytes, atomic_write_json
from hedger_jax.checkpoint import save_checkpoint
from hedger_jax.config import HedgerConfig
from hedger_jax.files import atomic_write, default_mode
from hedger_jax.memory import init_memory


@pytest.fixture(params=[0o022, 0o077])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def _demos():
    T = 3
    z = lambda *s: np.zeros(s, np.float32)  # noqa: E731
    return Demonstrations(obs=z(1, T, 2), action=z(1, T, 1), reward=z(1, T), next_obs=z(1, T, 2),
                          terminated=np.zeros((1, T), bool), truncated=np.zeros((1, T), bool),
                          valid=np.ones((1, T), bool),
                          env_id="mountain_car_discrete", source="test")


def test_every_writer_gives_open_permissions(tmp_path, umask):
    want = 0o666 & ~umask
    assert default_mode() == want
    cfg = HedgerConfig(state_dim=2, capacity=16)
    paths = [save_checkpoint(tmp_path / "a.npz", cfg, init_memory(cfg)),
             save_demonstrations(tmp_path / "d.npz", _demos())]
    atomic_write_bytes(str(tmp_path / "r.csv"), b"x")
    atomic_write_json(str(tmp_path / "r.json"), {"a": 1})
    paths += [tmp_path / "r.csv", tmp_path / "r.json"]
    with open(tmp_path / "plain", "w"):
        pass
    assert _mode(tmp_path / "plain") == want
    for p in paths:
        assert _mode(p) == want, p
    assert sorted(os.listdir(tmp_path)) == ["a.npz", "d.npz", "plain", "r.csv", "r.json"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "f.bin"
    atomic_write(path, lambda f: f.write(b"old"))

    def broken(f):
        f.write(b"new")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, broken)
    assert path.read_bytes() == b"old" and os.listdir(tmp_path) == ["f.bin"]
