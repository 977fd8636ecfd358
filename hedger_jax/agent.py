"""Acting, episodes, the two learning phases, evaluation, and ``make_train``.

One seed's whole run is a pure function::

    train = make_train(env, hedger_config, run_config, phase1=demos).train
    state, results = jax.jit(jax.vmap(train))(jax.random.split(key, n_seeds))

``train(key, params=None)``: ``params`` is a ``HedgerParams`` of traced hyperparameters
(vmap over it for a sweep), or None for the configs' values as constants.

It knows environments only through the functional interface of ``envs.base`` (duck-typed:
``default_params``, ``reset``, ``step``, ``evaluation_starts``, ``action_space``,
``max_steps``; ``reset_to`` for a phase-1 policy with a start).

Phases (paper section 2.4):
  1. an example policy is in control -- recorded demonstrations (a ``Transition`` batch with
     leading axes (E, T)) or a piece of control code (``(policy, n_episodes)`` where
     ``policy`` has pure ``init(key)`` and ``act(key, obs, pstate) -> (action, pstate)``) --
     and HEDGER learns passively (reverse replay after each episode);
  2. the learner's own epsilon-greedy policy is in control and learning continues.

The run is cut into ``n_blocks`` blocks of phase-two episodes (``episodes_per_block``) or of
training points (``points_per_block``); the greedy policy is evaluated after phase 1 and after
every block. ``init`` / ``run_block`` expose the same computation block by block, so a
host-side driver can show progress between blocks without any host round-trip inside them.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax import bursts
from hedger_jax.backup import backup_sweeps
from hedger_jax.bursts import Burst
from hedger_jax.config import HedgerConfig
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.greedy import (greedy_action, greedy_action_from_uniform, greedy_candidates,
                               greedy_choice, greedy_draws)
from hedger_jax.loops import masked_fori_loop
from hedger_jax.memory import Memory, init_memory, refresh_index
from hedger_jax.params import HedgerParams, resolve
from hedger_jax.validation import expect_key
from hedger_jax.run_config import EXPLORATION, RunConfig  # noqa: F401 (re-exported)
from hedger_jax.replay_cache import (REUSE_MIN_CAPACITY, StepNeighbours, missing, record_shapes,
                                     replay_sets)
from hedger_jax.replay_cache import usable as replay_cache_usable
from hedger_jax.train import (Transition, next_floor, replay_floor_on, train_episode,
                              train_step)

class Evaluation(NamedTuple):
    """mean_steps: float32 () mean steps to the goal, failures counted as the cap;
    success_rate: float32 () fraction of episodes that reached the goal."""

    mean_steps: jax.Array
    success_rate: jax.Array


class RunState(NamedTuple):
    """Carry of a run between blocks. memory: ``Memory``; key: the run's PRNG key; points:
    int32 () training points seen; episodes: int32 () phase-two episodes run."""

    memory: Memory
    key: jax.Array
    points: jax.Array
    episodes: jax.Array


class BlockResult(NamedTuple):
    """One evaluation: after phase 1 (block 0) or after a block of phase two.

    evaluation: ``Evaluation``; points, episodes: int32 () totals at evaluation time;
    train_steps_mean: float32 () mean length of the block's training episodes (0 for block 0);
    memory_size: int32 (); flags: int32 () memory error bits.
    """

    evaluation: Evaluation
    points: jax.Array
    episodes: jax.Array
    train_steps_mean: jax.Array
    memory_size: jax.Array
    flags: jax.Array


def _success(info: Any, terminated: jax.Array) -> jax.Array:
    """Whether a step reached the goal, bool (): ``info["success"]`` or
    ``info["reached_goal"]`` when the env reports it (a terminal can also be a failure, e.g.
    a wall), else ``terminated``."""
    if isinstance(info, dict):
        for name in ("success", "reached_goal"):
            if name in info:
                return jnp.asarray(info[name], bool)
    return jnp.asarray(terminated, bool)


def run_params(config: HedgerConfig, run: "RunConfig", params: Optional[HedgerParams]):
    """``params`` (a ``HedgerParams``), or the config's and run config's values as
    constants when None."""
    return HedgerParams.defaults(config, run) if params is None else params


def random_action(config: HedgerConfig, key: jax.Array) -> jax.Array:
    """A uniformly random action (A,) from ``key``: from the discrete set or in the box."""
    return _random_action_from_uniform(config, jax.random.uniform(key, (config.action_dim,)))


def _random_action_from_uniform(config: HedgerConfig, u: jax.Array) -> jax.Array:
    """A uniformly random action (A,) from U[0, 1) draws u (A,) (u[0] only if discrete)."""
    if config.is_discrete:
        actions = jnp.asarray(config.discrete_actions, jnp.float32)
        n = actions.shape[0]
        return actions[jnp.minimum((u[0] * n).astype(jnp.int32), n - 1)]
    low = jnp.asarray(config.action_low, jnp.float32)
    high = jnp.asarray(config.action_high, jnp.float32)
    return jnp.minimum(low + u * (high - low), high)


def explore_action(config: HedgerConfig, run: RunConfig, memory: Memory, obs: jax.Array,
                   key: jax.Array, greedy_only: Any = False,
                   params: Optional[HedgerParams] = None) -> jax.Array:
    """Epsilon-greedy action (A,) for one observation (S,).

    All its randomness (the coin, the greedy policy's tie-breaks and fallback, the
    exploratory action) comes from one ``jax.random.uniform`` draw of ``key``.
    ``greedy_only`` (bool (), may be traced): instead, exactly ``greedy_action(config, memory,
    obs, key, params)[0]``, so one copy of the greedy search serves training and evaluation
    (``make_train``'s block). params: ``HedgerParams`` (epsilon, noise_std and HEDGER's
    settings), or None for the configs' values. Under ``exploration="bursts"``: the first
    step of a burst (its random action), none carried on (``explore_action_burst`` carries).
    """
    return _first_step(_explore(config, run, memory, obs, key, greedy_only, False, params,
                                _no_burst(config, run)), run)


def explore_action_burst(config: HedgerConfig, run: RunConfig, memory: Memory, obs: jax.Array,
                         key: jax.Array, burst: Burst, greedy_only: Any = False,
                         params: Optional[HedgerParams] = None):
    """``explore_action`` under ``exploration="bursts"`` (``hedger_jax.bursts``), carrying
    the episode's burst: -> (action (A,), the next step's ``Burst``). A held step searches
    nothing; ``greedy_only`` ignores (and ends) a burst."""
    return _explore(config, run, memory, obs, key, greedy_only, False, params, burst)


def explore_action_recorded(config: HedgerConfig, run: RunConfig, memory: Memory,
                            obs: jax.Array, key: jax.Array, greedy_only: Any = False,
                            params: Optional[HedgerParams] = None):
    """``explore_action`` and the neighbour sets its greedy search found, for the replay of
    the episode (``rollout`` records them, ``train_prefix`` reuses them):
    -> (action (A,), ``replay_cache.StepNeighbours``)."""
    return _first_step(_explore(config, run, memory, obs, key, greedy_only, True, params,
                                _no_burst(config, run)), run)


def _no_burst(config: HedgerConfig, run: RunConfig) -> Optional[Burst]:
    """No burst under way where the run explores in bursts, else None."""
    return bursts.start(config) if run.exploration == "bursts" else None


def _first_step(out, run: RunConfig):
    """``_explore``'s output without the next step's ``Burst`` (if it returned one)."""
    if run.exploration != "bursts":
        return out
    return out[:-1] if len(out) > 2 else out[0]


def _explore(config: HedgerConfig, run: RunConfig, memory: Memory, obs: jax.Array,
             key: jax.Array, greedy_only: Any, record: bool, params=None,
             burst: Optional[Burst] = None):
    """``explore_action`` (record False) or ``explore_action_recorded`` (record True); with
    a ``burst`` (``exploration="bursts"``), the next step's ``Burst`` is returned last."""
    p = run_params(config, run, params)
    a_dim = config.action_dim
    n_greedy = greedy_draws(config)
    # gaussian: Box-Muller pairs; bursts: the random action and the burst's length.
    n_explore = {"gaussian": 2 * a_dim, "bursts": a_dim + 1}.get(run.exploration, a_dim)
    if (run.exploration == "bursts") != (burst is not None):
        raise ValueError("exploration='bursts' acts with a Burst carried from step to step "
                         "(explore_action_burst, training_act); other explorations take none")
    u = jax.random.uniform(key, (1 + n_greedy + n_explore,))
    ue = u[1 + n_greedy:]
    u_greedy = u[1:1 + n_greedy]
    explore_now = u[0] < p.epsilon
    if greedy_only is not False:
        greedy_only = jnp.asarray(greedy_only, bool)
        u_greedy = jnp.where(greedy_only, jax.random.uniform(key, (n_greedy,)), u_greedy)
        explore_now = explore_now & ~greedy_only
    n_candidates = greedy_candidates(config).shape[0]

    def greedy(_):
        if not record:
            return greedy_action_from_uniform(config, memory, obs, u_greedy, params)[0]
        action, _, _, sets = greedy_choice(config, memory, obs, u_greedy, params)
        return action, StepNeighbours(memory.size, sets.candidates, sets.chosen,
                                      jnp.ones((), bool), sets.has_chosen)

    def explore(_):
        action = _random_action_from_uniform(config, ue[:a_dim])
        return (action, missing(config, n_candidates, memory.size)) if record else action

    if run.exploration == "random":
        # A random exploratory step needs no greedy search (under vmap both branches run).
        return jax.lax.cond(explore_now, explore, greedy, None)
    if run.exploration == "bursts":
        return _burst_step(config, memory, burst, explore_now, greedy_only, ue[a_dim],
                           explore, greedy, record, n_candidates)
    out = greedy(None)
    action = out[0] if record else out
    low = jnp.asarray(config.action_low, jnp.float32)
    high = jnp.asarray(config.action_high, jnp.float32)
    # Box-Muller from two of the step's uniform draws (1 - u in (0, 1]: finite).
    noise = p.noise_std * jnp.sqrt(-2.0 * jnp.log1p(-ue[:a_dim])) * jnp.cos(
        jnp.float32(2.0 * np.pi) * ue[a_dim:])
    action = jnp.where(explore_now, jnp.clip(action + noise, low, high), action)
    if not record:
        return action
    return action, out[1]._replace(has_chosen=out[1].has_chosen & ~explore_now)


def _burst_step(config: HedgerConfig, memory: Memory, burst: Burst, explore_now: jax.Array,
                greedy_only: Any, u_length: jax.Array, explore, greedy, record: bool,
                n_candidates: int):
    """One step of epsilon-greedy with bursts: the held action while a burst lasts, else
    ``explore`` (which starts a burst of ``bursts.duration(u_length)`` steps) or ``greedy``.
    -> (action, [record,] next Burst)."""
    held = burst.left > 0
    if greedy_only is not False:
        held = held & ~jnp.asarray(greedy_only, bool)

    def hold(_):
        return (burst.action, missing(config, n_candidates, memory.size)) if record \
            else burst.action

    out = jax.lax.switch(jnp.where(held, 0, jnp.where(explore_now, 1, 2)),
                         [hold, explore, greedy], None)
    action = out[0] if record else out
    length = jnp.where(explore_now, bursts.duration(u_length), 1)
    nxt = Burst(action, jnp.where(held, burst.left, length) - 1)
    return (action, out[1], nxt) if record else (action, nxt)


def training_act(config: HedgerConfig, run: RunConfig, memory: Memory, greedy_only: Any = False,
                 params: Optional[HedgerParams] = None):
    """The rollout's ``act(key, obs, act_state)`` of phase two: ``explore_action`` (reading,
    not carrying, the memory; under ``exploration="bursts"`` act_state is the episode's
    ``Burst``, its start the attribute ``initial_state``), with the greedy searches'
    neighbour sets recorded for ``train_prefix`` when neighbours are reused
    (``run.reuse_neighbours``, and only under ``full_policy="error"``). params:
    ``HedgerParams``, or None for the configs' values."""
    params = with_data_bandwidth(config, memory, params)     # once per rollout
    reuse = run.reuse_neighbours
    if reuse is None:
        reuse = config.capacity >= REUSE_MIN_CAPACITY
    carried = run.exploration == "bursts"     # act_state: the episode's Burst
    if reuse and replay_cache_usable(config):
        def act(key, obs, act_state):
            out = _explore(config, run, memory, obs, key, greedy_only, True, params,
                           act_state if carried else None)
            return out[0], (out[2] if carried else act_state), out[1]

        act.record_like = record_shapes(config, greedy_candidates(config).shape[0])
    else:
        def act(key, obs, act_state):
            out = _explore(config, run, memory, obs, key, greedy_only, False, params,
                           act_state if carried else None)
            return (out[0], out[1]) if carried else (out, act_state)
    if carried:
        act.initial_state = bursts.start(config)
    return act


def rollout(env: Any, env_params: Any, act, key: jax.Array, max_steps: int,
            obs0: jax.Array, state0: Any, act_state: Any = None):
    """Run one episode of at most ``max_steps`` with ``act(key, obs, act_state) -> (a, act_state)``.

    Stops early (``lax.while_loop``) once the episode terminated or was truncated; steps
    after the end are padding (valid=False). Returns (Transition with leading axis
    max_steps, length int32 ()). An ``act`` with a ``record_like`` attribute (a pytree of
    ``jax.ShapeDtypeStruct``, e.g. ``training_act``'s) returns (a, act_state, record) and has
    its records kept too: then (Transition, length, records with leading axis max_steps).
    ``act_state`` None: the act's ``initial_state`` attribute where it has one.
    """
    buf, t, _, records = _rollout(env, env_params, act, key, max_steps, obs0, state0,
                                  act_state)
    return (buf, t) if records is None else (buf, t, records)


def _rollout(env: Any, env_params: Any, act, key: jax.Array, max_steps: int,
             obs0: jax.Array, state0: Any, act_state: Any = None, limit: Any = None):
    """``rollout``, capped at ``limit`` steps (int32 (), may be traced and exceed max_steps,
    the buffer's length: later steps are not recorded) -> (buffer, length, success bool ():
    whether the episode reached its goal, as ``evaluate_policy`` counts it, records or
    None)."""
    limit = max_steps if limit is None else limit
    if act_state is None:
        act_state = getattr(act, "initial_state", None)
    obs_dim = obs0.shape[-1]
    a_dim = env.action_space.action_dim
    like = getattr(act, "record_like", None)      # known without tracing act once more
    records = None if like is None else jax.tree_util.tree_map(
        lambda x: jnp.zeros((max_steps,) + x.shape, x.dtype), like)
    buf = Transition(
        obs=jnp.zeros((max_steps, obs_dim), jnp.float32),
        action=jnp.zeros((max_steps, a_dim), jnp.float32),
        reward=jnp.zeros((max_steps,), jnp.float32),
        next_obs=jnp.zeros((max_steps, obs_dim), jnp.float32),
        terminated=jnp.zeros((max_steps,), bool),
        valid=jnp.zeros((max_steps,), bool),
    )

    def cond(c):
        t, done = c[0], c[1]
        return (t < limit) & ~done

    def body(c):
        t, done, obs, state, act_state, key, buf, success, records = c
        k_t = jax.random.fold_in(key, t)
        k_act, k_step = jax.random.fold_in(k_t, 0), jax.random.fold_in(k_t, 1)
        out = act(k_act, obs, act_state)
        if len(out) != (2 if records is None else 3):
            raise ValueError("rollout: act must return (action, act_state), or (action, "
                             "act_state, record) when it has a record_like attribute; got "
                             f"{len(out)} outputs")
        action, act_state = out[0], out[1]
        if records is not None:
            records = jax.tree_util.tree_map(lambda b, x: b.at[t].set(x, mode="drop"),
                                             records, out[2])
        action = jnp.asarray(action, jnp.float32).reshape((a_dim,))
        next_obs, state, reward, terminated, truncated, info = env.step(k_step, state, action,
                                                                        env_params)
        success = success | _success(info, terminated)
        truncated = truncated | (t + 1 >= limit)
        tr = Transition(obs, action, jnp.asarray(reward, jnp.float32), next_obs,
                        jnp.asarray(terminated, bool), jnp.ones((), bool))
        buf = jax.tree_util.tree_map(lambda b, x: b.at[t].set(x, mode="drop"), buf, tr)
        return (t + 1, terminated | truncated, next_obs, state, act_state, key, buf, success,
                records)

    init = (jnp.zeros((), jnp.int32), jnp.zeros((), bool), obs0, state0, act_state, key, buf,
            jnp.zeros((), bool), records)
    t, _, _, _, _, _, buf, success, records = jax.lax.while_loop(cond, body, init)
    return buf, t, success, records


def train_prefix(config: HedgerConfig, memory: Memory, episode: Transition, length: jax.Array,
                 neighbours: Optional[StepNeighbours] = None,
                 params: Optional[HedgerParams] = None, backup: Any = True):
    """Reverse replay of the first ``length`` steps of an episode (newest first).

    Same result as ``train_episode`` on an episode whose steps >= length are padding, but it
    only does ``length`` steps of work (``masked_fori_loop``: cheap under vmap over seeds
    with their own lengths). ``neighbours``: the rollout's record of the sets its greedy
    searches found (``rollout`` with ``explore_action_recorded``), when ``memory`` is the
    memory it acted with: the replay reuses them instead of searching
    (``hedger_jax.replay_cache``; the same sets). params: ``HedgerParams``, or None for the
    config's values. With ``backup_sweeps`` > 0 the replay is followed by that many
    memory-wide backups through a plan built now (``hedger_jax.backup``) where ``backup``
    (a bool, or a traced bool ()) holds. Returns the memory.
    """
    given = params
    params = with_data_bandwidth(config, memory, params)     # the rollout's width
    width = int(episode.valid.shape[0])
    p = resolve(config, params)

    def body(i, carry, active):
        mem, floor = carry if floored else (carry, None)
        t = jnp.maximum(length - 1 - i, 0)
        step = jax.tree_util.tree_map(lambda x: x[t], episode)
        cached = None
        if neighbours is not None:
            cached = replay_sets(neighbours, t, length) + (width,)
        valid = step.valid & active
        mem, info = train_step(config, mem, step._replace(valid=valid), cached, params, floor)
        if not floored:
            return mem
        return mem, jnp.where(active, next_floor(p, info, valid), floor)

    # A plain fori_loop under vmap would select between old and new memories after every step.
    # Without replay_floor the carry is the memory alone: the paper's program.
    floored = replay_floor_on(p)
    if not floored:
        memory = masked_fori_loop(length, body, memory)
    else:
        memory = masked_fori_loop(length, body, (memory, jnp.float32(-jnp.inf)))[0]
    if backup is False:
        return memory
    if config.backup_sweeps == 0 or backup is True:
        return backup_sweeps(config, memory, given)  # none unless config.backup_sweeps > 0
    return jax.lax.cond(jnp.asarray(backup, bool), lambda m: backup_sweeps(config, m, given),
                        lambda m: m, memory)


#: Default number of evaluation episodes stepped together (``evaluate_policy``'s ``lanes``):
#: fewer lanes than episodes, so finished episodes are not stepped while the longest runs.
EVAL_LANES = 32


def evaluate_policy(env: Any, env_params: Any, act, key: jax.Array, n_episodes: int,
                    max_steps: int, lanes: Optional[int] = None):
    """Run ``act(obs (S,), key) -> action (A,)`` (no learning) from ``n_episodes``
    ``env.evaluation_starts``, each until it ends or reaches ``max_steps``.

    Returns (steps float32 (n,), success bool (n,)): the steps to the goal of each episode,
    ``max_steps`` for one that did not reach it (a timeout or a failure such as a wall).

    ``lanes`` (static; default ``min(n, EVAL_LANES)``) episodes are stepped together (the
    policy lane after lane, the environment vmapped); when one ends, its lane starts the next
    waiting episode, until all have run. Episode i always starts from start i and draws its
    step-t randomness from key i folded with t, so the results do not depend on ``lanes``.
    """
    if lanes is not None and int(lanes) < 1:
        raise ValueError(f"lanes: must be >= 1, got {lanes}")
    k_starts, k_run = jax.random.split(key)
    obs0, states0 = env.evaluation_starts(k_starts, env_params, n_episodes)
    keys = jax.random.split(k_run, n_episodes)
    n = n_episodes
    w = min(int(lanes or EVAL_LANES), n)

    def one_act(obs, key):
        return jnp.reshape(act(obs, jax.random.fold_in(key, 0)), (env.action_space.action_dim,))

    def one_step(obs, state, key, action):
        next_obs, state, _, terminated, truncated, info = env.step(
            jax.random.fold_in(key, 1), state, action, env_params)
        return next_obs, state, terminated, truncated, _success(info, terminated)

    def lane_select(mask, new, old):
        return jax.tree_util.tree_map(
            lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b),
            new, old)

    def body(c):
        next_ep, ep, t, live, succeeded, obs, states, steps_out, success_out = c
        k_step = jax.vmap(jax.random.fold_in)(keys[ep], t)
        # The lanes' actions one after another (lax.map), their environment steps at once:
        # a vmapped policy would add a second, batched copy of the greedy search to the
        # program (the training rollout has the single-query one). Same results.
        acts = jax.lax.map(lambda ok: one_act(*ok), (obs, k_step))
        nobs, nstates, term, trunc, succ = jax.vmap(one_step)(obs, states, k_step, acts)
        succeeded = succeeded | succ
        t = t + 1
        ended = live & (term | trunc | (t >= max_steps))
        at = jnp.where(ended, ep, n)                                  # n: nothing recorded
        steps_out = steps_out.at[at].set(t, mode="drop")
        success_out = success_out.at[at].set(succeeded, mode="drop")
        # Lanes whose episode ended take the next waiting episodes, in lane order.
        new_ep = next_ep + jnp.cumsum(ended.astype(jnp.int32)) - 1
        refill = ended & (new_ep < n)
        start = jnp.minimum(new_ep, n - 1)
        obs = lane_select(refill, obs0[start], lane_select(live, nobs, obs))
        states = lane_select(refill, jax.tree_util.tree_map(lambda x: x[start], states0),
                             lane_select(live, nstates, states))
        ep = jnp.where(refill, new_ep, ep)
        t = jnp.where(refill, 0, t)
        succeeded = succeeded & ~ended
        live = (live & ~ended) | refill
        next_ep = next_ep + jnp.sum(ended.astype(jnp.int32))
        return next_ep, ep, t, live, succeeded, obs, states, steps_out, success_out

    first = jnp.arange(w, dtype=jnp.int32)
    init = (jnp.int32(w), first, jnp.zeros((w,), jnp.int32), jnp.ones((w,), bool),
            jnp.zeros((w,), bool), obs0[first],
            jax.tree_util.tree_map(lambda x: x[first], states0),
            jnp.full((n,), max_steps, jnp.int32), jnp.zeros((n,), bool))
    out = jax.lax.while_loop(lambda c: jnp.any(c[3]), body, init)
    steps, success = out[7], out[8]
    return jnp.where(success, steps, max_steps).astype(jnp.float32), success


def evaluate(env: Any, env_params: Any, config: HedgerConfig, memory: Memory, key: jax.Array,
             n_episodes: int, max_steps: int, *, refresh: bool = True,
             params: Optional[HedgerParams] = None) -> Evaluation:
    """Greedy policy, learning off, ``n_episodes`` from ``env.evaluation_starts`` (vmapped).

    The metric is the mean number of steps to the goal; an episode that does not reach it
    within ``max_steps`` (or fails, e.g. hits a wall) counts as ``max_steps``. ``refresh``
    (static): bring the neighbour index up to date first (``False`` where the caller just
    did: the search is exact either way). params: ``HedgerParams``, or None for the
    config's values. Returns ``Evaluation``.
    """
    if refresh:
        memory = refresh_index(config, memory)
    params = with_data_bandwidth(config, memory, params)     # once, not per step

    def act(obs, k):
        return greedy_action(config, memory, obs, k, params)[0]

    steps, success = evaluate_policy(env, env_params, act, key, n_episodes, max_steps)
    return Evaluation(jnp.mean(steps), jnp.mean(success.astype(jnp.float32)))


class Train(NamedTuple):
    """What ``make_train`` returns: ``train(key, params=None) -> (RunState, BlockResult with
    leading axis n_blocks + 1)`` and its pieces ``init(key, params=None) -> (RunState,
    BlockResult)`` (phase 1 and the first evaluation) and ``run_block(RunState,
    params=None) -> (RunState, BlockResult)``. params: ``HedgerParams`` (traced, e.g. a
    vmapped sweep), or None for the configs' values as constants."""

    train: Any
    init: Any
    run_block: Any


def _phase1_fn(env, env_params, config: HedgerConfig, phase1, max_steps: int):
    """Phase 1 as a function (memory, key, params) -> (memory, points int32 ()) for the
    chosen source: none, demonstrations, or an example policy."""
    if phase1 is None:
        return lambda memory, key, params: (memory, jnp.zeros((), jnp.int32))
    if isinstance(phase1, Transition):
        episodes = jax.tree_util.tree_map(jnp.asarray, phase1)
        if episodes.reward.ndim != 2:
            raise ValueError("phase1 demonstrations: expected a Transition with leading axes "
                             f"(episodes, steps), got reward shape {episodes.reward.shape}")

        def learn_demos(memory, key, params):
            del key

            def body(mem, ep):
                mem, _ = train_episode(config, mem, ep, params)
                return refresh_index(config, mem), None

            memory, _ = jax.lax.scan(body, memory, episodes)
            return memory, jnp.sum(episodes.valid).astype(jnp.int32)

        return learn_demos
    policy, n_episodes = phase1[0], int(phase1[1])
    start = phase1[2] if len(phase1) > 2 else None

    def learn_policy(memory, key, params):
        def body(carry, k):
            mem, points = carry
            k_reset, k_init, k_run = jax.random.split(k, 3)
            if start is None:
                obs0, s0 = env.reset(k_reset, env_params)
            else:
                obs0, s0 = env.reset_to(k_reset, env_params, jnp.asarray(start, jnp.float32))
            ep, length = rollout(env, env_params, policy.act, k_run, max_steps, obs0, s0,
                                 policy.init(k_init))
            mem = refresh_index(config, train_prefix(config, mem, ep, length, params=params))
            return (mem, points + length), None

        (memory, points), _ = jax.lax.scan(body, (memory, jnp.zeros((), jnp.int32)),
                                           jax.random.split(key, n_episodes))
        return memory, points

    return learn_policy


def _block_loop(env: Any, env_params: Any, config: HedgerConfig, run: RunConfig,
                max_steps: int, params: Optional[HedgerParams], n_episodes: jax.Array,
                target: jax.Array, evaluation: tuple):
    """(cond, body) of a block's loop over episodes: training episodes while fewer than
    ``n_episodes`` (or ``target`` points) were run, then the evaluation episodes from
    ``evaluation`` = (first observations (n, S), env states (n, ...), keys (n, 2)).

    The carry: (memory, points, episodes, training steps, key, evaluation episodes done,
    evaluation steps (n,), evaluation successes (n,))."""
    eval_obs0, eval_states0, eval_keys = evaluation
    n_eval = int(run.eval_episodes)

    def training(c):
        _, points, n_ep = c[:3]
        if run.episodes_per_block is not None:
            return n_ep < n_episodes
        return points < target

    def cond(c):
        return training(c) | (c[5] < n_eval)

    def body(c):
        memory, points, n_ep, steps, k, j, eval_steps, eval_success = c
        train_now = training(c)
        k_next, k_ep = jax.random.split(k)
        k_reset, k_run = jax.random.split(k_ep)
        obs0, s0 = env.reset(k_reset, env_params)
        e = jnp.minimum(j, n_eval - 1)
        obs0 = jnp.where(train_now, obs0, eval_obs0[e])
        s0 = jax.tree_util.tree_map(lambda a, b: jnp.where(train_now, a, b[e]), s0,
                                    eval_states0)
        # The data-chosen bandwidth (if any) read once, for the rollout and its replay.
        p_ep = with_data_bandwidth(config, memory, params)
        act = training_act(config, run, memory, ~train_now, p_ep)
        ep, length, success, record = _rollout(
            env, env_params, act, jnp.where(train_now, k_run, eval_keys[e]), max_steps,
            obs0, s0, limit=jnp.where(train_now, max_steps, run.eval_max_steps))
        memory = jax.lax.cond(
            train_now,
            lambda m: refresh_index(config, train_prefix(config, m, ep, length, record, p_ep)),
            lambda m: m, memory)
        learnt = jnp.where(train_now, length, 0)
        at = jnp.where(train_now, n_eval, j)                     # n_eval: not recorded
        eval_steps = eval_steps.at[at].set(
            jnp.where(success, length, run.eval_max_steps).astype(jnp.float32), mode="drop")
        eval_success = eval_success.at[at].set(success, mode="drop")
        return (memory, points + learnt, n_ep + train_now.astype(jnp.int32),
                steps + learnt, jnp.where(train_now, k_next, k),
                j + (~train_now).astype(jnp.int32), eval_steps, eval_success)

    return cond, body


def make_train(env: Any, config: HedgerConfig, run: RunConfig, *, env_params: Any = None,
               phase1: Any = None, phase1_max_steps: int = 1000) -> Train:
    """Build the pure functions of one seed's run (see the module docstring).

    phase1: ``None``; demonstrations as a ``Transition`` with leading axes (E, T) (see
      ``transitions_from_demonstrations``); or ``(policy, n_episodes[, start])`` for an example
      policy in control (episodes of at most ``phase1_max_steps``, from ``env.reset`` or from
      ``env.reset_to(start)``).
    env_params: the environment's parameters (default ``env.default_params()``).
    Returns ``Train``; each of its functions takes an optional ``HedgerParams``.
    """
    if env_params is None:
        env_params = env.default_params()
    max_steps = int(run.train_max_steps or env.max_steps)
    phase1_fn = _phase1_fn(env, env_params, config, phase1, phase1_max_steps)

    # The index is refreshed after every episode (phase 1's included), so the evaluations
    # need no refresh of their own: one copy of the refresh in the program.
    def do_eval(memory, key, points, episodes, mean_len, params):
        ev = evaluate(env, env_params, config, memory, key, run.eval_episodes,
                      run.eval_max_steps, refresh=False, params=params)
        return BlockResult(ev, points, episodes, mean_len, memory.size, memory.flags)

    def phase1(key, params):
        k_phase1, k_eval, k_run = jax.random.split(key, 3)
        memory, points = phase1_fn(init_memory(config), k_phase1, params)
        return RunState(memory, k_run, points, jnp.zeros((), jnp.int32)), k_eval

    n_eval = int(run.eval_episodes)

    def block(state: RunState, first: jax.Array, k_eval0: jax.Array, params):
        """One evaluation block: RunState -> (RunState, BlockResult). ``first`` (bool ()):
        the evaluation right after phase 1 (no episodes, the evaluation key ``k_eval0`` from
        ``phase1``, the run key kept).

        The block's training episodes, then its evaluation episodes, are one loop over
        episodes through one rollout, whose policy is epsilon-greedy while training and
        greedy while evaluating (``explore_action``'s ``greedy_only``): one copy of the
        greedy search in the program. The evaluation is ``evaluate``'s, episode for episode
        (same starts, keys and cap), run one episode at a time.
        """
        key, k_block, k_eval = jax.random.split(state.key, 3)
        key = jnp.where(first, state.key, key)
        k_eval = jnp.where(first, k_eval0, k_eval)
        n_episodes = jnp.where(first, 0, run.episodes_per_block or 0)
        target = state.points + jnp.where(first, 0, run.points_per_block or 0)
        k_starts, k_runs = jax.random.split(k_eval)                 # as evaluate_policy's
        eval_obs0, eval_states0 = env.evaluation_starts(k_starts, env_params, n_eval)
        eval_keys = jax.random.split(k_runs, n_eval)

        cond, body = _block_loop(env, env_params, config, run, max_steps, params, n_episodes,
                                 target, (eval_obs0, eval_states0, eval_keys))
        init_c = (state.memory, state.points, jnp.zeros((), jnp.int32),
                  jnp.zeros((), jnp.int32), k_block, jnp.zeros((), jnp.int32),
                  jnp.zeros((n_eval,), jnp.float32), jnp.zeros((n_eval,), bool))
        memory, points, n_ep, steps, _, _, eval_steps, eval_success = jax.lax.while_loop(
            cond, body, init_c)
        episodes = state.episodes + n_ep
        mean_len = steps.astype(jnp.float32) / jnp.maximum(n_ep, 1).astype(jnp.float32)
        new_state = RunState(memory, key, points, episodes)
        ev = Evaluation(jnp.mean(eval_steps), jnp.mean(eval_success.astype(jnp.float32)))
        return new_state, BlockResult(ev, points, episodes, mean_len, memory.size, memory.flags)

    def init(key, params: Optional[HedgerParams] = None):
        expect_key("key", key)
        state, k_eval = phase1(key, params)
        return state, do_eval(state.memory, k_eval, state.points, state.episodes,
                              jnp.float32(0.0), params)

    def run_block(state: RunState, params: Optional[HedgerParams] = None):
        return block(state, jnp.zeros((), bool), state.key, params)

    def train(key, params: Optional[HedgerParams] = None):
        expect_key("key", key)
        # One scan over the n_blocks + 1 evaluations (the first right after phase 1), so the
        # block appears once in the program; the same results as init then run_blocks.
        state, k_eval0 = phase1(key, params)
        firsts = jnp.arange(run.n_blocks + 1) == 0
        state, results = jax.lax.scan(lambda s, f: block(s, f, k_eval0, params), state, firsts)
        return state, results

    return Train(train, init, run_block)


def transitions_from_demonstrations(demos: Any) -> Transition:
    """A ``Transition`` batch (E, T, ...) from an ``envs.demonstrations.Demonstrations``-like
    object (fields obs, action, reward, next_obs, terminated, valid)."""
    return Transition(
        obs=jnp.asarray(demos.obs, jnp.float32),
        action=jnp.asarray(demos.action, jnp.float32),
        reward=jnp.asarray(demos.reward, jnp.float32),
        next_obs=jnp.asarray(demos.next_obs, jnp.float32),
        terminated=jnp.asarray(demos.terminated, bool),
        valid=jnp.asarray(demos.valid, bool),
    )
