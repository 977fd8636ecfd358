"""Progress of ``Hedger``'s learning calls: what the training loops report (a ``Chunk`` of
episodes, or one replayed episode) taken into the learner's memory, key and counters, the
memory checked after each, the optional progress bar, and the user's callback."""
from __future__ import annotations

import contextlib
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

import numpy as np

from hedger_jax.memory import memory_check

__all__ = ["Chunk", "progress_bar", "follow_phase_two", "follow_phase_one", "record_episodes"]


class Chunk(NamedTuple):
    """Episodes that one step of a phase-two loop ran.

    memory: the memory after them (the loop's input memory was donated); key: the learner's
    key after them (None: the loop drew its keys from the learner's stream instead); steps:
    env steps taken (); lengths: int32 (n,) and returns: float32 (n,), per episode.
    """

    memory: Any
    key: Optional[Any]
    steps: int
    lengths: np.ndarray
    returns: np.ndarray


@contextlib.contextmanager
def progress_bar(total: int, enabled: bool, desc: str) -> Iterator[Optional[Any]]:
    """A tqdm bar of ``total`` steps while the block runs (None when not ``enabled``)."""
    if not enabled:
        yield None
        return
    from tqdm.auto import tqdm   # only when asked for: importing it costs time

    bar = tqdm(total=total, desc=desc, unit="step")
    try:
        yield bar
    finally:
        bar.close()


# ------------------------------------------------------------------------------------------
# Taking the loops' reports into the learner
# ------------------------------------------------------------------------------------------
def follow_phase_two(model: Any, chunks: Iterator[Chunk], total: int, show: bool,
                     callback: Optional[Callable[[Dict[str, Any]], Any]]) -> None:
    """Take each chunk of a phase-two loop into the ``Hedger`` ``model`` (memory, key,
    counters, ``ep_info_buffer``, progress), check the memory (``memory_check``), and call
    ``callback`` every ``model.chunk_episodes`` episodes and at the end (``False`` stops)."""
    done, lengths, returns = 0, [], []
    with progress_bar(total, show, "HEDGER learn") as bar:
        try:
            for chunk in chunks:
                model.memory = chunk.memory
                model.key = model.key if chunk.key is None else chunk.key
                done += chunk.steps
                model.num_timesteps += chunk.steps
                model.num_episodes += len(chunk.lengths)
                lengths.extend(chunk.lengths)
                returns.extend(chunk.returns)
                if bar is not None:
                    bar.update(min(chunk.steps, total - bar.n))
                memory_check(model.memory)
                if len(lengths) < model.chunk_episodes and done < total:
                    continue
                info = dict(num_timesteps=model.num_timesteps, num_episodes=model.num_episodes,
                            memory_size=int(model.memory.size),
                            lengths=np.asarray(lengths, np.int32),
                            returns=np.asarray(returns, np.float32))
                record_episodes(model.ep_info_buffer, info["lengths"], info["returns"])
                lengths, returns = [], []
                if callback is not None and callback(info) is False:
                    break
        finally:
            record_episodes(model.ep_info_buffer, lengths, returns)  # a chunk cut by an error


def follow_phase_one(model: Any, steps: Iterator[Tuple[Any, int]], total: int, show: bool,
                     desc: str, count_episodes: bool) -> None:
    """Take each replayed episode (memory, training points) into the ``Hedger`` ``model``
    and check the memory; the bar counts ``total`` episodes or training points."""
    with progress_bar(total, show, desc) as bar:
        for memory, points in steps:
            model.memory = memory
            model.num_demo_timesteps += points
            if bar is not None:
                bar.update(1 if count_episodes else points)
            memory_check(model.memory)


def record_episodes(buffer: List[Dict[str, Any]], lengths: Any, returns: Any,
                    keep: int = 100) -> None:
    """Append {"r": return, "l": length} per episode to ``buffer``, keeping the last ``keep``."""
    buffer.extend({"r": float(r), "l": int(n)} for r, n in zip(returns, lengths))
    del buffer[:-keep]
