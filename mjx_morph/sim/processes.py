"""CPU work of an env build spread over this host's cores: the self-collision pair search (`selfcontact`), the
shared tree's merge orders (`supertree`), and compiling each padded robot and MJX's `put_model` of it (`model`). Each
costs from ~1 ms to seconds a robot in one process, so a set of thousands (the 2400 variants) took minutes before it
was spread.

Processes are started with "spawn" (a child forked from a process running JAX's threads could deadlock), which
re-imports the caller's main module in each child: a script needs the `if __name__ == "__main__":` guard. A pool
that breaks anyway leaves the work to this process, with a warning. The children run JAX on the CPU only, so that
none of them takes memory on the accelerator the training process holds.
"""
from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import warnings
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Sequence, TypeVar

PARALLEL_FROM = 16     # items of one call from which they are spread over processes, by default (a process costs
                       # ~1-3 s to start: its imports)
MAX_PROCESSES = 16     # ... over at most this many (the GPU machines have 16 cores per GPU)
BACKGROUND_NICE = 10   # how much lower a background thread's work runs (`lower_thread_priority`)

T = TypeVar("T")
R = TypeVar("R")


def processes_for(items: int, parallel_from: int = PARALLEL_FROM) -> int:
    """Processes for `items` pieces of work: 1 below `parallel_from` (where starting processes costs more than it
    saves), else one per core this process may use, at most `MAX_PROCESSES` and at most `items`."""
    if items < parallel_from:
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, MAX_PROCESSES, items))


def process_map(fn: Callable[[T], R], items: Sequence[T], processes: int, what: str) -> list[R]:
    """[fn(x) for x in items], in `processes` spawned processes when more than 1 (`fn` and the items must pickle);
    `what` names the work in the warning of a broken pool."""
    items = list(items)
    if processes > 1 and len(items) > 1:
        try:
            with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_cpu_only) as pool:
                return list(pool.map(fn, items, chunksize=max(1, len(items) // (4 * processes))))
        except BrokenProcessPool as e:
            warnings.warn(f"{what} could not use {processes} processes ({e}); doing its {len(items)} items in "
                          f"this one", RuntimeWarning, stacklevel=3)
    return [fn(x) for x in items]


def lower_thread_priority(increment: int = BACKGROUND_NICE) -> bool:
    """Lower the calling thread's CPU priority: on Linux its nice value goes up by `increment`, and the processes and
    threads it starts afterwards inherit it. For host work in a background thread while the process trains (the
    evaluations prepared in a run's last minutes): its env build's processes and its compilation then yield the
    cores to the training's own threads, which launch the GPU's kernels. Measured on a 2-core CPU, a JAX loop in the
    main thread kept 78% of its rate beside such work at +10, 50% at the same priority. Returns False where this is
    not supported (not Linux); the thread's priority cannot be raised back without privileges."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
    except OSError:
        return False
    return True


def _cpu_only() -> None:
    import jax
    jax.config.update("jax_platforms", "cpu")
