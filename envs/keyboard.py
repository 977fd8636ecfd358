"""Keyboard demonstrations: a person drives the mountain car and the run is saved to a file.

The paper's phase-1 examples were 11 runs by 3 people at the keyboard, every run from the bottom
of the hill (x = -0.5, v = 0), discrete actions, *not* capped at 200 steps. This module records
such runs:

    python -m envs.keyboard --out demos.npz --episodes 3

Keys: LEFT arrow (or ``a``) pushes left (action -1), RIGHT arrow (or ``d``) pushes right (+1),
nothing (or both) is 0. ESC or closing the window stops; the unfinished episode is dropped and
the finished ones are saved. Each episode waits for an arrow key (pressed, or still held from the previous
run) before the car moves (``--no-wait`` to start at once); the time limit is ``--max-steps`` (2000 by default, far above
any human run, so runs are effectively uncapped; a run that hits it is saved as truncated).

Two parts, kept apart so that the logic is testable without a window:

* :class:`DemonstrationRecorder` receives one callback per step (the signature of
  ``gymnasium.utils.play.play``'s ``callback``), accumulates transitions episode by episode
  (from reset to terminated/truncated) and writes them with
  ``envs.demonstrations.save_demonstrations`` (``source="keyboard"``).
* :func:`record_keyboard` is a small pygame loop: it steps a
  ``envs.gym_adapter.FunctionalGymEnv`` around ``MountainCar(max_steps=...)`` started through
  ``reset_to`` at the bottom of the hill, shows ``render_rgb`` frames and feeds the recorder.
  It is used instead of ``gymnasium.utils.play.play`` because ``play`` cannot stop after N
  episodes, cannot pass reset options, hands the callback the ``(obs, info)`` tuple of
  ``reset`` as the first ``obs_t``, and switches matplotlib to the TkAgg backend on import.
  The recorder still works as a ``play`` callback (it unpacks that tuple)::

      env = make_keyboard_env()
      rec = DemonstrationRecorder.for_env(env)
      gymnasium.utils.play.play(env, callback=rec.callback, keys_to_action=keys_to_action(),
                                noop=1)   # every episode starts at the bottom (reset_options)
      rec.save("demos.npz")

pygame is imported only when a window is opened (``import envs.keyboard`` does not need it).
"""
from __future__ import annotations

import argparse
import sys
import warnings
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

from envs.demonstrations import Demonstrations, save_demonstrations

__all__ = ["DemonstrationRecorder", "make_keyboard_env", "record_keyboard", "keys_to_action",
           "action_index_from_keys", "main"]

#: Discrete mountain-car action indices (``ActionSpace.values`` = (-1, 0, +1)).
LEFT, NOOP, RIGHT = 0, 1, 2


class DemonstrationRecorder:
    """Accumulates per-step callbacks into episodes and saves them as ``Demonstrations``.

    Args:
      env_id: the functional env's ``name`` stored in the file (e.g. "mountain_car_discrete").
      obs_dim, action_dim: sizes of one observation / action value.
      action_values: float32 (n_actions, action_dim) to turn discrete action *indices* (what a
        Gymnasium ``Discrete`` space and ``play`` hand over) into action values; ``None`` when
        the callbacks already receive action values.
      source: the file's ``source`` string.

    Per step, call :meth:`callback`; an episode ends on ``terminated or truncated``. Only
    finished episodes are saved; an unfinished one is dropped (:meth:`abort_episode`).
    """

    def __init__(self, env_id: str, obs_dim: int, action_dim: int,
                 action_values: Optional[np.ndarray] = None, source: str = "keyboard"):
        self.env_id = str(env_id)
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.action_values = (None if action_values is None
                              else np.asarray(action_values, np.float32).reshape(-1, action_dim))
        self.source = source
        self._episodes: List[Dict[str, np.ndarray]] = []
        self._current: List[tuple] = []

    @classmethod
    def for_env(cls, gym_env, source: str = "keyboard") -> "DemonstrationRecorder":
        """A recorder matching a ``FunctionalGymEnv`` (env_id, sizes, discrete index mapping)."""
        fenv = gym_env.unwrapped.env
        aspace = fenv.action_space
        values = aspace.values_array() if aspace.is_discrete else None
        return cls(fenv.name, fenv.obs_dim, aspace.action_dim, values, source)

    # ---- per step ---------------------------------------------------------------------
    def _action_value(self, action: Any) -> np.ndarray:
        if self.action_values is not None:
            idx = int(np.asarray(action).reshape(()))
            if not 0 <= idx < len(self.action_values):
                raise ValueError(f"action index {idx} out of range [0, {len(self.action_values)})")
            return self.action_values[idx]
        return np.asarray(action, np.float32).reshape(self.action_dim)

    def _obs(self, obs: Any) -> np.ndarray:
        if isinstance(obs, tuple):  # gymnasium.utils.play passes reset's (obs, info)
            obs = obs[0]
        return np.asarray(obs, np.float32).reshape(self.obs_dim)

    def callback(self, obs_t, obs_tp1, action, rew, terminated, truncated, info=None) -> None:
        """One transition ``obs_t --action--> (rew, obs_tp1)`` (``gymnasium.utils.play``
        signature). ``obs_t`` of a step that does not continue the current episode (its
        ``obs_t`` differs from the previous ``obs_tp1``) starts a new one: the unfinished
        episode is dropped with a warning."""
        o, o2 = self._obs(obs_t), self._obs(obs_tp1)
        if self._current and not np.array_equal(self._current[-1][3], o):
            warnings.warn("DemonstrationRecorder: step does not continue the current episode; "
                          f"dropping its {len(self._current)} unfinished steps")
            self._current = []
        terminated, truncated = bool(terminated), bool(truncated)
        self._current.append((o, self._action_value(action), float(rew), o2, terminated,
                              truncated and not terminated))
        if terminated or truncated:
            self._close_episode()

    def abort_episode(self) -> int:
        """Drop the unfinished episode; returns how many steps were dropped."""
        n = len(self._current)
        self._current = []
        return n

    def _close_episode(self) -> None:
        obs, act, rew, nobs, term, trunc = zip(*self._current)
        self._episodes.append({
            "obs": np.stack(obs), "action": np.stack(act),
            "reward": np.asarray(rew, np.float32), "next_obs": np.stack(nobs),
            "terminated": np.asarray(term, bool), "truncated": np.asarray(trunc, bool)})
        self._current = []

    # ---- results ----------------------------------------------------------------------
    @property
    def n_episodes(self) -> int:
        """Finished episodes."""
        return len(self._episodes)

    @property
    def lengths(self) -> List[int]:
        """Steps of each finished episode."""
        return [len(e["reward"]) for e in self._episodes]

    @property
    def pending_steps(self) -> int:
        """Steps of the unfinished episode."""
        return len(self._current)

    def to_demonstrations(self) -> Demonstrations:
        """The finished episodes, padded to the longest: arrays (E, T, ...) with ``valid``."""
        if not self._episodes:
            raise ValueError("DemonstrationRecorder: no finished episode to save")
        E, T = len(self._episodes), max(self.lengths)
        out = {
            "obs": np.zeros((E, T, self.obs_dim), np.float32),
            "action": np.zeros((E, T, self.action_dim), np.float32),
            "reward": np.zeros((E, T), np.float32),
            "next_obs": np.zeros((E, T, self.obs_dim), np.float32),
            "terminated": np.zeros((E, T), bool),
            "truncated": np.zeros((E, T), bool),
            "valid": np.zeros((E, T), bool),
        }
        for e, ep in enumerate(self._episodes):
            n = len(ep["reward"])
            for k, v in ep.items():
                out[k][e, :n] = v
            out["valid"][e, :n] = True
        return Demonstrations(**out, env_id=self.env_id, source=self.source)

    def save(self, path, metadata: Optional[dict] = None) -> str:
        """Write the finished episodes with ``save_demonstrations``; returns the path."""
        return save_demonstrations(path, self.to_demonstrations(), metadata=metadata)


# ---- the window ------------------------------------------------------------------------

def keys_to_action() -> Dict[tuple, int]:
    """``gymnasium.utils.play`` mapping: pygame key tuples -> discrete action index."""
    import pygame

    return {(pygame.K_LEFT,): LEFT, (pygame.K_RIGHT,): RIGHT,
            (ord("a"),): LEFT, (ord("d"),): RIGHT}


def action_index_from_keys(pressed) -> int:
    """Currently pressed pygame keys -> action index: left only -> 0 (-1), right only -> 2 (+1),
    none or both -> 1 (0)."""
    import pygame

    left = bool({pygame.K_LEFT, ord("a")} & set(pressed))
    right = bool({pygame.K_RIGHT, ord("d")} & set(pressed))
    if left and not right:
        return LEFT
    if right and not left:
        return RIGHT
    return NOOP


def make_keyboard_env(max_steps: int = 2000, start=(-0.5, 0.0)):
    """The recording env: ``FunctionalGymEnv(MountainCar(continuous=False, max_steps))`` whose
    every reset starts at ``start`` (default the bottom of the hill) through ``reset_to``;
    render mode ``"rgb_array"``."""
    from envs.gym_adapter import FunctionalGymEnv
    from envs.mountain_car import MountainCar

    return FunctionalGymEnv(MountainCar(continuous=False, max_steps=max_steps),
                            render_mode="rgb_array",
                            reset_options={"start": np.asarray(start, np.float32)})


def record_keyboard(out: Optional[str] = None, episodes: int = 3, max_steps: int = 2000,
                    fps: int = 30, zoom: float = 2.0, seed: int = 0, wait_for_start: bool = True,
                    start=(-0.5, 0.0), recorder: Optional[DemonstrationRecorder] = None,
                    event_source: Optional[Callable[[np.ndarray], Sequence[Any]]] = None,
                    metadata: Optional[dict] = None) -> DemonstrationRecorder:
    """Open a window, let a person drive ``episodes`` runs, save them to ``out`` (if given).

    Args:
      fps: steps per second (0: as fast as possible, for tests).
      event_source: ``f(obs) -> pygame events`` polled once per frame; default
        ``pygame.event.get()`` (tests post scripted key events from it).
      metadata: extra keys for the file (merged with max_steps/start/fps).
    Returns the recorder (its finished episodes are what was saved).
    """
    import pygame

    env = make_keyboard_env(max_steps=max_steps, start=start)
    rec = recorder if recorder is not None else DemonstrationRecorder.for_env(env)
    poll = event_source if event_source is not None else (lambda _obs: pygame.event.get())
    pygame.display.init()
    font = None
    try:
        pygame.font.init()
        font = pygame.font.Font(None, 24)
    except Exception:  # no font module: draw without text
        font = None
    obs, _ = env.reset(seed=seed)
    frame = env.render()
    size = (int(frame.shape[1] * zoom), int(frame.shape[0] * zoom))
    screen = pygame.display.set_mode(size)
    pygame.display.set_caption("HEDGER mountain car: LEFT/RIGHT to push, ESC to stop")
    clock = pygame.time.Clock()
    pressed: set = set()
    action_keys = {pygame.K_LEFT, pygame.K_RIGHT, ord("a"), ord("d")}

    def draw(lines):
        surf = pygame.surfarray.make_surface(np.ascontiguousarray(env.render().swapaxes(0, 1)))
        screen.blit(pygame.transform.scale(surf, size), (0, 0))
        if font is not None:
            for i, text in enumerate(lines):
                screen.blit(font.render(text, True, (0, 0, 0)), (8, 8 + 22 * i))
        pygame.display.flip()

    def handle(events) -> tuple:
        """-> (quit requested, an action key went down)."""
        quit_, started = False, False
        for ev in events:
            if ev.type == pygame.QUIT or (ev.type == pygame.KEYDOWN and ev.key == pygame.K_ESCAPE):
                quit_ = True
            elif ev.type == pygame.KEYDOWN and ev.key in action_keys:
                pressed.add(ev.key)
                started = True
            elif ev.type == pygame.KEYUP:
                pressed.discard(ev.key)
        return quit_, started

    quit_ = False
    try:
        for ep in range(episodes):
            if ep > 0:
                obs, _ = env.reset(seed=seed + ep)
            if wait_for_start:
                while True:
                    draw([f"episode {ep + 1}/{episodes}: press LEFT or RIGHT to start",
                          "ESC: stop"])
                    quit_, started = handle(poll(obs))
                    if quit_ or started or pressed:  # a new press, or a key still held
                        break
                    clock.tick(fps or 30)
            if quit_:
                break
            t = 0
            while True:
                quit_, _ = handle(poll(obs))
                if quit_:
                    dropped = rec.abort_episode()
                    if dropped:
                        print(f"episode {ep + 1}: stopped after {dropped} steps, not saved",
                              file=sys.stderr)
                    break
                a = action_index_from_keys(pressed)
                obs2, r, term, trunc, info = env.step(a)
                rec.callback(obs, obs2, a, r, term, trunc, info)
                obs, t = obs2, t + 1
                draw([f"episode {ep + 1}/{episodes}  step {t}",
                      f"x = {obs[0]:+.3f}  v = {obs[1]:+.4f}"])
                if fps:
                    clock.tick(fps)
                if term or trunc:
                    print(f"episode {ep + 1}: {t} steps ({'goal' if term else 'time limit'})",
                          file=sys.stderr)
                    break
            if quit_:
                break
    finally:
        pygame.display.quit()
        env.close()
    if out is not None and rec.n_episodes:
        meta = {"max_steps": int(max_steps), "start": [float(s) for s in start],
                "fps": int(fps)}
        meta.update(metadata or {})
        rec.save(out, metadata=meta)
    return rec


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m envs.keyboard",
                                description="Drive the mountain car with the arrow keys and save "
                                            "the runs as HEDGER demonstrations.")
    p.add_argument("--out", required=True, help="demonstrations file to write (.npz)")
    p.add_argument("--episodes", type=int, default=3, help="runs to record (default 3)")
    p.add_argument("--max-steps", type=int, default=2000,
                   help="time limit per run (default 2000: effectively uncapped)")
    p.add_argument("--fps", type=int, default=30, help="steps per second (default 30)")
    p.add_argument("--zoom", type=float, default=2.0, help="window scale (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-wait", action="store_true",
                   help="start each run at once instead of at the first arrow key")
    return p


def main(argv: Optional[Sequence[str]] = None, event_source=None) -> int:
    args = build_parser().parse_args(argv)
    if args.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    rec = record_keyboard(out=args.out, episodes=args.episodes, max_steps=args.max_steps,
                          fps=args.fps, zoom=args.zoom, seed=args.seed,
                          wait_for_start=not args.no_wait, event_source=event_source)
    if rec.n_episodes:
        print(f"saved {rec.n_episodes} episodes (lengths {rec.lengths}) to {args.out}")
        return 0
    print("no finished episode: nothing saved", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
