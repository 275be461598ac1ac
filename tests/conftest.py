"""Shared fixtures. Tests that need the original robots skip with a message when they are absent.

Compiled programs go to a persistent XLA cache (.pytest_cache/xla, or $MJX_MORPH_XLA_CACHE; set it empty for none),
shared with the CLI subprocesses the tests start: compilation is most of the suite's time, and a rerun of the suite
on the 2-core CPU machine took 6.5 min instead of 13.8. A program is found there only if it lowers to the same text,
and JAX's lowering depends on what the process traced before (its in-memory caches: after an evaluation, the smoke
train step lowered with a few helper functions no longer shared, missed the cache and compiled again, 49 s): each
test module, and each value built once per session, starts from empty in-memory caches (`jax.clear_caches`), so that a
program lowers as in a fresh process and is compiled once per suite.

Every program, in this process and in the processes the tests start (they inherit the environment), compiles with
`FAST_COMPILE`'s options (`XLA_FLAGS`, set before JAX starts): XLA's newer CPU fusion emitters off (the suite ran
~25% shorter, session 36), and LLVM at optimisation level 0 without its expensive passes, which only the programs
jitted with `FAST_COMPILE` had before, not the eager operations (~5,000 small programs a suite: parameter
initialisation, indexing) nor any program compiled without it (19:04 -> 14:39 from an empty cache, session 65).
The first slows the CPU demo's optimised train step (session 36) and the second makes slower code by design, so only
the tests set them for every program (the measurements: docs/benchmarks.md, "CPU notes", sessions 36 and 65)."""
from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

#: FAST_COMPILE's options (mjx_morph/ppo/trainer.py) for every program of the suite, also those compiled without them
CPU_FLAGS = ["--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0",
             "--xla_llvm_disable_expensive_passes=true"]
_flags = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join([_flags, *(f for f in CPU_FLAGS if f not in _flags)]).strip()

import jax  # noqa: E402  (after XLA_FLAGS)
import pytest

from mjx_morph.run import use_compile_cache  # noqa: E402
from mjx_morph.unimal.sets import unimals_root  # noqa: E402

NO_UNIMALS = ("the original robots (../shared/unimals_100 or $MJX_MORPH_UNIMALS) are not available; "
              "this test needs them")


@pytest.fixture(scope="session")
def unimals():
    root = unimals_root()
    if root is None:
        pytest.skip(NO_UNIMALS)
    return root


ROOT = Path(__file__).resolve().parents[1]
# self-collision pair searches kept beside the compiled programs (keyed by selfcontact.py's source), shared by the
# workers and the processes the tests start, so a rerun of the suite skips them (docs/benchmarks.md, "CPU notes",
# session 37); the tests of the disk cache itself point it elsewhere
os.environ["MJX_MORPH_PAIR_CACHE"] = str(ROOT / ".pytest_cache" / "pairs")
os.environ.setdefault("MJX_MORPH_XLA_CACHE", str(ROOT / ".pytest_cache" / "xla"))
use_compile_cache(os.environ["MJX_MORPH_XLA_CACHE"], min_compile_s=1.0)


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_per_module():
    jax.clear_caches()      # the module's programs lower as in a fresh process (the module docstring says why)


def smoke_config(*overrides: str):
    """The smoke training config (2 generated robots, tiny networks, 3 iterations) with extra overrides."""
    from mjx_morph.run import compose_run_config
    return compose_run_config(["preset=smoke", "robots=gen/train", "progress=false", *overrides])


def once_per_session(tmp_path_factory, name: str, build):
    """`build(folder)`'s JSON value, computed once per test session also when pytest-xdist runs it in several
    processes: the first process to ask builds it in a folder all of them share, holding a lock; the others wait for
    it and read the value back (the smoke runs and their evaluation took ~130 s of CPU twice, once per process)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent                  # the session's folder, above each worker's own
    done = root / f"{name}.json"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)    # released when the file closes, also if build raises
        if not done.exists():
            jax.clear_caches()          # lowered as in a fresh process, its programs are found by the others
            done.write_text(json.dumps(build(root)))
        return json.loads(done.read_text())


def _smoke_run(tmp_path_factory, name: str, *overrides: str):
    from mjx_morph.run import train

    def build(root):
        d = root / name
        train(smoke_config(f"run_dir={d}", *overrides))
        return str(d)
    d = once_per_session(tmp_path_factory, name, build)
    return Path(d), smoke_config(f"run_dir={d}", *overrides)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory):
    """One finished smoke run of rmomo, shared by the training, evaluation, report and render tests (trained once per
    session; in the process that trained it, its compiled train step is cached, so other smoke runs of the same config
    compile nothing, and the other processes read it from the persistent compilation cache). Tests copy it before
    changing it."""
    return _smoke_run(tmp_path_factory, "smoke-rmomo")


@pytest.fixture(scope="session")
def smoke_run_ff(tmp_path_factory):
    """The same smoke run for the feed-forward MetaMorph."""
    return _smoke_run(tmp_path_factory, "smoke-metamorph", "arch=metamorph")


EVAL_STEPS = 30   # episode length of the evaluations in the tests


@pytest.fixture(scope="session")
def evaluated_runs(tmp_path_factory, smoke_run, smoke_run_ff):
    """Both smoke runs evaluated on short episodes: rmomo on train, its variants and (labelled) test = the train
    robots again; metamorph on train and test. Shared by the evaluation and report tests (once per session)."""
    from mjx_morph.eval.evaluate import evaluate_run

    def build(root):
        log: list[str] = []
        kw = dict(episodes=2, seed=0, zero_state_steps=10, episode_length=EVAL_STEPS, trace_steps=EVAL_STEPS,
                  log=log.append)
        evaluate_run(smoke_run[0], ["train", "variants", "test:train"], zero_state_sets=("train", "test"), **kw)
        evaluate_run(smoke_run_ff[0], ["train", "test:train"], **kw)
        return log
    EVAL_LOG[:] = once_per_session(tmp_path_factory, "evaluated-runs", build)
    return smoke_run[0], smoke_run_ff[0]


EVAL_LOG: list[str] = []   # what evaluated_runs printed
