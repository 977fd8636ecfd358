"""XLA CPU runtime settings: flags that keep vmapped HEDGER programs from hanging, from
handing small reductions to a slow library kernel and from compiling slowly, and that compile
their loops into single kernels; and ``serial_codegen`` (no splitting of tiny gathers from a large memory across threads).

1. **Deadlock.** With jax/jaxlib 0.10.2 on the CPU, XLA's concurrency-optimised scheduler can
produce a program that deadlocks: every XLA worker thread waits for work, the host waits for
the result, and the process sits at 0 % CPU forever. Seen here with
``jax.jit(jax.vmap(train.init))`` over 5 seeds of continuous-action mountain car (the
Figure 3 quick variant), in 3 of 3 tries at 5 seeds on the 2-core machine (1 and 2 seeds
finished). ``--xla_cpu_multi_thread_eigen=false``, the usual advice for XLA CPU hangs, did not
help (2 of 2 still hung); ``--xla_cpu_enable_concurrency_optimized_scheduler=false`` did
(3, 5 and 8 seeds all finished, 4 of 4 tries). The flag only changes the order in which XLA
schedules independent operations, not what they compute.

2. **Small reductions.** jaxlib 0.10 hands reductions to YNNPACK kernels, which are slow on the
tiny (32 x 4 x 9) sums of a local fit: 3x slower batched over queries, and the largest single
cost of a vmapped training step over seeds (measured). ``NO_YNN_REDUCE_FLAG`` keeps them in
XLA's own code. Unknown flags abort the process, so it is only added for jaxlib versions
known to have it (``_YNN_FLAG_JAXLIB``).

3. **Compile time.** jaxlib 0.10 generates CPU code for fusions with its newer MLIR "fusion
emitters" by default. A HEDGER program is thousands of small fusions (the continuous-action
``make_train(...).train`` at 20,000 slots: ~13,500 StableHLO operations), and their code
generation was most of its compile time. ``LEGACY_EMITTERS_FLAG`` selects XLA's older
elemental emitters: the full continuous-action grid ``train`` compiled in 6.4 s instead of 9.2
s (8.9 instead of 14.4 CPU-seconds), the discrete one in 3.2 s instead of 5.1, and the
programs ran as fast or faster (paired, same process, per-compile ``compiler_options``:
training 1.01x / 1.03x discrete / continuous at 2e4 slots, 1.02x / 1.00x at 3e5; batched
predictions 1.11x at 1e4, 1.07x at 3e5; 1-16 vmapped seeds 0.97-1.03x; 2-core CPU). Results
agree to float32 rounding, not bit for bit: separately generated code may contract a
multiply-add differently (a prediction moved by at most 1 ULP in 189 of 4,096 queries).
Only added for jaxlib versions known to have the flag (``_LEGACY_EMITTERS_JAXLIB``).

4. **Loops as single kernels (default on CPU-only installs; ``HEDGER_JAX_LOOP_KERNELS=0``
turns it off).** XLA's CPU runtime runs a program as a sequence of compiled kernels, one call
per fused operation (~20-100 ns each), and a HEDGER training step is hundreds of tiny
operations. XLA can also compile a whole ``while`` loop into one kernel ("small while loop
hoisting"), by default only loops that touch a few kilobytes. ``LOOP_KERNELS_FLAG`` lifts
that size limit, so every loop with no custom call, sort or batched matrix product becomes
one kernel. With a one-level grid index (mountain car up to ~1e5 slots) the library's scan
then avoids those operations for single queries and vmapped batches below 64
(``hedger_jax.kselect``), so the episode rollout and the reverse replay become single
kernels. The same flag sets LLVM's loop-unroll threshold to ``LOOP_UNROLL_THRESHOLD`` (60
instead of 300): LLVM fully unrolled the kernels' many short loops, which made the
continuous ``train`` compile in ~20 s instead of ~14 s, and the smaller code also runs
faster. Measured (2-core AMD EPYC VM, separate processes, since XLA reads its flags once):
mountain-car training at 2e4 slots, discrete 52,000-73,000 points/s with the flag,
40,000-42,000 with loop kernels at LLVM's threshold, 33,000-37,000 without loop kernels;
continuous 11,600-13,300 / 9,900-10,700 / 6,500-7,600; unroll thresholds 0 / 30 / 100 / 150
were no better than 60. Full continuous ``train`` trace + compile: 12.4-16.6 s with the
flag, 18.1-22.7 s at LLVM's threshold, 11.0-15.0 s without loop kernels. Multi-level grids
(1e5 slots and up) select the k nearest on every scan trip; at LLVM's threshold the
sort-free form cost as much as the kernels saved (0.93x at 3e5), with the flag it gains
1.16-1.42x (paired, ``index._scan``), so they use it too. A single write also inserts into the
index's sorted recent list by a loop that moves only the entries after it, in place
(``index._insert_by_blocks``), instead of O(R) passes whose slices XLA copied with
``memmove`` inside the kernels (17 % of a discrete training step's time at 2e4 slots,
profiled). Results agree to float32 rounding with programs compiled without the flag.
It is not added where JAX may use an accelerator (``JAX_PLATFORMS`` names one, or a GPU/TPU
plugin is installed; ``HEDGER_JAX_LOOP_KERNELS=1`` adds it anyway): the unroll threshold is
an LLVM setting of the whole process, measured only for the CPU's code.
``loop_kernels_enabled`` says whether it is in effect.

``apply_safe_cpu_flags`` appends these flags to ``XLA_FLAGS``. ``import hedger_jax`` and
``import envs`` call it, so they take effect as long as JAX has not yet started its CPU
backend (JAX reads ``XLA_FLAGS`` when the first computation runs, not at ``import jax``).
A flag that ``XLA_FLAGS`` already names is left alone (your choice wins); nothing is changed
when the environment variable ``HEDGER_JAX_KEEP_XLA_FLAGS`` is set to a non-empty value other
than ``0``.
"""
from __future__ import annotations

import contextlib
import functools
import os
from typing import Any, Callable, Dict, List, MutableMapping, Optional, Tuple

#: The deadlock workaround appended to ``XLA_FLAGS``.
SAFE_CPU_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
#: Keep reductions out of YNNPACK (jaxlib 0.10).
NO_YNN_REDUCE_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_REDUCE"
#: jaxlib (major, minor) versions that know ``NO_YNN_REDUCE_FLAG`` (checked here).
_YNN_FLAG_JAXLIB = ((0, 10),)
#: XLA's older (elemental) fusion code generators: a third less compile time (jaxlib 0.10).
LEGACY_EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters=false"
#: jaxlib (major, minor) versions that know ``LEGACY_EMITTERS_FLAG`` (checked here).
_LEGACY_EMITTERS_JAXLIB = ((0, 10),)
#: Compile every eligible ``while`` loop into one kernel (see the module doc, item 4): the
#: size limit (bytes an iteration touches, by XLA's cost model) of XLA's CPU loop hoisting.
LOOP_KERNELS_OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: LLVM's loop-unroll cost threshold (an LLVM command-line option, which XLA passes on from
#: ``xla_backend_extra_options``; LLVM's default at -O3 is 300) and the value set with the
#: loop kernels: their code unrolled less compiles faster and runs faster (module doc, item 4).
LOOP_UNROLL_OPTION = "-unroll-threshold"
LOOP_UNROLL_THRESHOLD = 60
LOOP_KERNELS_FLAG = (f"--xla_backend_extra_options={LOOP_KERNELS_OPTION}={1 << 50},"
                     f"{LOOP_UNROLL_OPTION}={LOOP_UNROLL_THRESHOLD}")
#: ``HEDGER_JAX_LOOP_KERNELS``: "0" leaves ``LOOP_KERNELS_FLAG`` out, "1" adds it; unset (or
#: "auto") adds it unless JAX may run on an accelerator (``_accelerator_possible``).
LOOP_KERNELS_VARIABLE = "HEDGER_JAX_LOOP_KERNELS"
#: jaxlib (major, minor) versions that know ``LOOP_KERNELS_FLAG`` (checked here).
_LOOP_KERNELS_JAXLIB = ((0, 10),)
#: Modules whose presence means a JAX accelerator plugin is installed (PJRT plugins live in
#: the ``jax_plugins`` namespace package; the CUDA and ROCm plugins also have modules of their
#: own; TPUs use ``libtpu``).
_ACCELERATOR_MODULES = ("jax_plugins", "jax_cuda12_plugin", "jax_cuda13_plugin",
                        "jax_rocm60_plugin", "jax_rocm7_plugin", "libtpu")
#: Set this environment variable (to anything but "" or "0") to leave ``XLA_FLAGS`` alone.
OPT_OUT_VARIABLE = "HEDGER_JAX_KEEP_XLA_FLAGS"


def _jaxlib_version() -> Optional[Tuple[int, int]]:
    try:
        from importlib.metadata import version

        major, minor = version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except Exception:  # not installed, or an unusual version string
        return None


def cpu_flags(jaxlib_version: Optional[Tuple[int, int]] = None,
              environ: Optional[MutableMapping[str, str]] = None) -> List[str]:
    """The flags ``apply_safe_cpu_flags`` adds for this jaxlib (default: the installed one)
    and environment (``LOOP_KERNELS_VARIABLE``; default ``os.environ``)."""
    v = _jaxlib_version() if jaxlib_version is None else tuple(jaxlib_version)
    flags = [SAFE_CPU_FLAG]
    if v in _YNN_FLAG_JAXLIB:
        flags.append(NO_YNN_REDUCE_FLAG)
    if v in _LEGACY_EMITTERS_JAXLIB:
        flags.append(LEGACY_EMITTERS_FLAG)
    if v in _LOOP_KERNELS_JAXLIB and loop_kernels_wanted(environ):
        flags.append(LOOP_KERNELS_FLAG)
    return flags


def _accelerator_possible(environ: Optional[MutableMapping[str, str]] = None) -> bool:
    """Whether JAX may run this process on something other than the CPU: ``JAX_PLATFORMS``
    names another platform, or (unset) an accelerator plugin is installed. Checked without
    importing anything (``importlib.util.find_spec``)."""
    import importlib.util

    env = os.environ if environ is None else environ
    platforms = [p.strip().lower() for p in env.get("JAX_PLATFORMS", "").split(",") if p.strip()]
    if platforms:
        return any(p != "cpu" for p in platforms)
    for name in _ACCELERATOR_MODULES:
        try:
            if importlib.util.find_spec(name) is not None:
                return True
        except (ImportError, ValueError):
            continue
    return False


def loop_kernels_wanted(environ: Optional[MutableMapping[str, str]] = None) -> bool:
    """Whether to add ``LOOP_KERNELS_FLAG`` (module doc, item 4): ``LOOP_KERNELS_VARIABLE``
    "1" / "0" forces it on / off; unset or "auto", on unless an accelerator may be used (its
    LLVM unroll setting is for the CPU's code; on an accelerator the flag only costs)."""
    env = os.environ if environ is None else environ
    value = env.get(LOOP_KERNELS_VARIABLE, "").strip().lower()
    if value in ("1", "true", "on", "yes"):
        return True
    if value in ("0", "false", "off", "no"):
        return False
    return not _accelerator_possible(env)


#: Loops touching at least this many bytes per iteration count as "any size" for
#: ``loop_kernels_enabled`` (the training loops of a 10^6-slot memory stay below it).
_LOOP_KERNELS_MIN = 1 << 40


def loop_kernels_enabled(environ: Optional[MutableMapping[str, str]] = None) -> bool:
    """Whether JAX's CPU backend compiles loops of any size into single kernels: the default
    backend is the CPU and ``XLA_FLAGS`` sets ``LOOP_KERNELS_OPTION`` to at least 2^40 (as
    ``LOOP_KERNELS_FLAG`` does; ``import hedger_jax`` adds it unless told not to). Read when
    a program is traced; XLA reads the flag once, when the backend starts."""
    import re

    import jax

    env = os.environ if environ is None else environ
    found = re.findall(LOOP_KERNELS_OPTION + r"=(\d+)", env.get("XLA_FLAGS", ""))
    if not found or int(found[-1]) < _LOOP_KERNELS_MIN:
        return False
    return jax.default_backend() == "cpu"


def apply_safe_cpu_flags(environ: Optional[MutableMapping[str, str]] = None,
                         jaxlib_version: Optional[Tuple[int, int]] = None) -> bool:
    """Append ``cpu_flags()`` to ``environ["XLA_FLAGS"]`` (default ``os.environ``), each unless
    ``XLA_FLAGS`` already sets that flag.

    Returns True if a flag was added, False if nothing was (opt-out variable set, or every
    flag already set). Idempotent.
    """
    env = os.environ if environ is None else environ
    if env.get(OPT_OUT_VARIABLE, "") not in ("", "0"):
        return False
    flags = env.get("XLA_FLAGS", "")
    added = False
    for flag in cpu_flags(jaxlib_version, env):
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
            added = True
    if added:
        env["XLA_FLAGS"] = flags
    return added


# ------------------------------------------------------------------------------------------
# Serial code generation: no intra-op task splitting of the small ops of a training loop
# ------------------------------------------------------------------------------------------
#: ``HEDGER_JAX_SERIAL_CODEGEN``: "0" never, "1" always (on the CPU), unset/"auto" for
#: memories whose largest array reaches ``SERIAL_CODEGEN_MIN_BYTES``.
SERIAL_CODEGEN_VARIABLE = "HEDGER_JAX_SERIAL_CODEGEN"
#: Size (bytes) of a memory's largest array (``memory.largest_array_bytes``: the grid index's
#: copy of the points included) from which its training loop is compiled serially. Measured
#: with ``Hedger.learn`` (discrete mountain car, grid index, 2-core CPU): at 24,000 slots
#: (576 KB) serial code did twice the steps per CPU-second at the same wall-clock speed; at
#: 16,000 (384 KB) no consistent difference.
SERIAL_CODEGEN_MIN_BYTES = 1 << 19


@contextlib.contextmanager
def serial_codegen():
    """Compile with every thread of this process restricted to one CPU, then restore.

    Why: XLA's CPU compiler splits an operation into parallel tasks when its cost model says
    the operation touches enough bytes -- and for a gather it counts the *whole* array
    gathered from. A HEDGER step gathers ~32-300 entries from memory arrays of 10^5-10^6
    slots, so at large capacities nearly every gather, and the region-update scatter, becomes
    a two-task fork/join (17 per training step at capacity 200,000, measured on jax 0.10.2),
    each costing microseconds of thread hand-off for nanoseconds of work: training ran
    1.1-3x slower per CPU-second. The compiler reads the number of usable CPUs from the
    thread affinity when it compiles, and nothing in JAX's compile options sets it, so this
    context narrows the affinity while compiling. The executable it produces then runs
    on every CPU as usual (independent operations still run concurrently; only the
    splitting of single small operations is gone). Compilation itself is serial inside
    the context (about 1.4x slower on 2 cores).

    Only effective when compilation happens inside the context, so compile explicitly
    (``jax.jit(f).lower(*args).compile()``) or use ``jit_serial_codegen``; do not *run* long
    computations inside it (they would be confined to one CPU). JAX's backends are started
    before the affinity is narrowed. A no-op where the affinity cannot be changed (not
    Linux, or not permitted).
    """
    tasks = "/proc/self/task"
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir(tasks):
        yield
        return
    import jax

    # Start the backends first: a CPU client created inside the context would size its
    # thread pool from the narrowed affinity for the rest of the process.
    jax.devices()
    try:
        allowed = os.sched_getaffinity(0)
    except OSError:
        yield
        return
    one = {min(allowed)}
    saved = {}
    for name in os.listdir(tasks):
        tid = int(name)
        try:
            saved[tid] = os.sched_getaffinity(tid)
            os.sched_setaffinity(tid, one)
        except OSError:  # a thread that ended meanwhile, or no permission: leave it
            saved.pop(tid, None)
    try:
        yield
    finally:
        for name in os.listdir(tasks):
            tid = int(name)
            try:  # threads born inside the context get the process's original affinity
                os.sched_setaffinity(tid, saved.get(tid, allowed))
            except OSError:
                pass


def serial_codegen_wanted(array_bytes: int, environ: Optional[MutableMapping[str, str]] = None,
                          auto: bool = True) -> bool:
    """Whether to compile a program over a memory whose largest array has ``array_bytes``
    (``hedger_jax.memory.largest_array_bytes(config)``) with ``serial_codegen``.

    ``HEDGER_JAX_SERIAL_CODEGEN`` = "0" -> never, "1" -> always, otherwise (default "auto")
    when ``auto`` and ``array_bytes >= SERIAL_CODEGEN_MIN_BYTES``. Never off the CPU backend.
    Callers whose programs also contain large batched work (e.g. evaluating hundreds of
    episodes at once, which does gain from splitting) pass ``auto=False``.
    """
    import jax

    env = os.environ if environ is None else environ
    mode = env.get(SERIAL_CODEGEN_VARIABLE, "auto").strip().lower()
    if mode in ("0", "false", "off", "no") or jax.default_backend() != "cpu":
        return False
    if mode in ("1", "true", "on", "yes"):
        return True
    return bool(auto) and array_bytes >= SERIAL_CODEGEN_MIN_BYTES


class jit_serial_codegen:
    """``jax.jit(fn, **jit_kwargs)``, compiled inside ``serial_codegen`` where ``enabled``.

    ``enabled``: a bool, or a callable taking the dict of keyword (static) arguments of a call
    and returning one. Call it like the jitted function (array arguments positional, static
    arguments by keyword); where enabled, one executable per argument signature (pytree
    structure, shapes, dtypes, static values) is compiled on first use and reused. Where
    not enabled the call goes to ``jax.jit(fn, **jit_kwargs)`` unchanged.
    """

    def __init__(self, fn: Callable, enabled: Any = True, **jit_kwargs: Any):
        import jax

        functools.update_wrapper(self, fn)
        self._jitted = jax.jit(fn, **jit_kwargs)
        self._enabled = enabled
        self._compiled: Dict[Any, Any] = {}

    def lower(self, *args, **kwargs):
        return self._jitted.lower(*args, **kwargs)

    def __call__(self, *args, **kwargs):
        enabled = self._enabled(kwargs) if callable(self._enabled) else self._enabled
        if not enabled:
            return self._jitted(*args, **kwargs)
        import jax

        leaves, treedef = jax.tree_util.tree_flatten(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._jitted(*args, **kwargs)   # inside a transformation (eval_shape, vmap)
        sig = (treedef, tuple(sorted(kwargs.items())),
               tuple((getattr(x, "shape", None), str(getattr(x, "dtype", type(x))),
                      getattr(x, "weak_type", False)) for x in leaves))
        compiled = self._compiled.get(sig)
        if compiled is None:
            with serial_codegen():
                compiled = self._jitted.lower(*args, **kwargs).compile()
            self._compiled[sig] = compiled
        return compiled(*args)
