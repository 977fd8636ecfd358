"""Keyboard demonstration recorder: scripted callbacks and scripted key events, headless."""
from __future__ import annotations

import numpy as np
import pytest

from envs.demonstrations import load_demonstrations
from envs.keyboard import DemonstrationRecorder, build_parser, main, record_keyboard

pygame = pytest.importorskip("pygame")

VALUES = np.array([[-1.0], [0.0], [1.0]], np.float32)


@pytest.fixture
def headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")


def test_recorder_scripted_callbacks(tmp_path):
    rec = DemonstrationRecorder("mountain_car_discrete", 2, 1, action_values=VALUES)
    o = [np.array([0.1 * i, 0.01 * i], np.float32) for i in range(10)]
    # Episode 1: 3 steps, terminal (play-style first obs_t: the (obs, info) tuple of reset).
    rec.callback((o[0], {}), o[1], 2, 0.0, False, False, {})
    rec.callback(o[1], o[2], 0, 0.0, False, False, {})
    rec.callback(o[2], o[3], 1, 0.75, True, False, {})
    # Episode 2: 2 steps, cut by the time limit.
    rec.callback(o[5], o[6], 0, 0.0, False, False, {})
    rec.callback(o[6], o[7], 0, 0.0, False, True, {})
    # Unfinished third episode is not saved.
    rec.callback(o[8], o[9], 2, 0.0, False, False, {})
    assert (rec.n_episodes, rec.lengths, rec.pending_steps) == (2, [3, 2], 1)
    path = rec.save(tmp_path / "d.npz", metadata={"who": "test"})
    d = load_demonstrations(path, env_id="mountain_car_discrete", obs_dim=2, action_dim=1)
    assert d.source == "keyboard" and d.obs.shape == (2, 3, 2)
    np.testing.assert_array_equal(d.lengths, [3, 2])
    np.testing.assert_array_equal(d.action[0, :, 0], [1.0, -1.0, 0.0])
    np.testing.assert_array_equal(d.action[1, :2, 0], [-1.0, -1.0])
    np.testing.assert_array_equal(d.obs[0], np.stack(o[0:3]))
    np.testing.assert_array_equal(d.next_obs[0], np.stack(o[1:4]))
    np.testing.assert_array_equal(d.reward[0], [0.0, 0.0, 0.75])
    np.testing.assert_array_equal(d.terminated, [[False, False, True], [False, False, False]])
    np.testing.assert_array_equal(d.truncated, [[False, False, False], [False, True, False]])
    np.testing.assert_array_equal(d.valid, [[True, True, True], [True, True, False]])
    # A step that does not continue the episode drops the unfinished one (with a warning).
    with pytest.warns(UserWarning):
        rec.callback(o[0], o[1], 1, 0.0, False, False, {})
    assert rec.pending_steps == 1
    with pytest.raises(ValueError):
        DemonstrationRecorder("x", 2, 1).to_demonstrations()


class ScriptedPerson:
    """Posts real pygame key events: hold RIGHT while v >= 0, LEFT while v < 0 (energy
    pumping); presses ESC once ``stop_after`` episodes are done and ``stop_steps`` more taken."""

    def __init__(self, rec, stop_after=None, stop_steps=10):
        self.rec, self.stop_after, self.stop_steps = rec, stop_after, stop_steps
        self.held = None

    def __call__(self, obs):
        key = pygame.K_RIGHT if obs[1] >= 0 else pygame.K_LEFT
        if (self.stop_after is not None and self.rec.n_episodes >= self.stop_after
                and self.rec.pending_steps >= self.stop_steps):
            pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_ESCAPE))
        elif key != self.held:
            if self.held is not None:
                pygame.event.post(pygame.event.Event(pygame.KEYUP, key=self.held))
            pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=key))
            self.held = key
        return pygame.event.get()


def _check_runs(d, n):
    assert d.n_episodes == n and d.source == "keyboard"
    for e in range(n):
        L = int(d.lengths[e])
        np.testing.assert_allclose(d.obs[e, 0], [-0.5, 0.0])          # bottom of the hill
        np.testing.assert_array_equal(d.obs[e, 1:L], d.next_obs[e, :L - 1])  # contiguous
        want = np.where(d.obs[e, :L, 1] >= 0, 1.0, -1.0)              # the keys held
        np.testing.assert_array_equal(d.action[e, :L, 0], want)
        assert d.terminated[e, L - 1] and not d.truncated[e].any()
        assert d.next_obs[e, L - 1, 0] >= 0.5 and d.reward[e, L - 1] > 0
        assert 80 < L < 200


def test_record_keyboard_scripted_keys_and_escape(tmp_path, headless):
    rec = DemonstrationRecorder("mountain_car_discrete", 2, 1, action_values=VALUES)
    out = tmp_path / "kb.npz"
    record_keyboard(out=str(out), episodes=3, fps=0, zoom=1.0, recorder=rec,
                    event_source=ScriptedPerson(rec, stop_after=2, stop_steps=10))
    assert rec.n_episodes == 2 and rec.pending_steps == 0     # the third run was aborted
    d = load_demonstrations(out, env_id="mountain_car_discrete")
    _check_runs(d, 2)
    np.testing.assert_array_equal(d.lengths, rec.lengths)


def test_time_limit_truncates_and_cli(tmp_path, headless):
    # A person who holds RIGHT forever never gets up the hill: truncated at --max-steps.
    def hold_right(obs):
        if not pygame.event.peek(pygame.KEYDOWN):
            pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_RIGHT))
        return pygame.event.get()

    out = tmp_path / "cli.npz"
    assert build_parser().parse_args(["--out", "x"]).max_steps == 2000
    rc = main(["--out", str(out), "--episodes", "1", "--fps", "0", "--max-steps", "60",
               "--zoom", "1"], event_source=hold_right)
    assert rc == 0
    d = load_demonstrations(out)
    assert list(d.lengths) == [60] and d.truncated[0, 59] and not d.terminated.any()
    np.testing.assert_array_equal(d.action[0, :, 0], np.ones(60))
