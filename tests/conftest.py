"""Shared fixtures. Tests that need the original robots skip with a message when they are absent.

Compiled programs go to a persistent XLA cache (.pytest_cache/xla, or $MJX_MORPH_XLA_CACHE; set it empty for none),
shared with the CLI subprocesses the tests start: compilation is most of the suite's time, and a rerun of the suite
on the 2-core CPU machine took 6.5 min instead of 13.8."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from mjx_morph.run import use_compile_cache
from mjx_morph.unimal.sets import unimals_root

NO_UNIMALS = ("the original robots (../shared/unimals_100 or $MJX_MORPH_UNIMALS) are not available; "
              "this test needs them")


@pytest.fixture(scope="session")
def unimals():
    root = unimals_root()
    if root is None:
        pytest.skip(NO_UNIMALS)
    return root


ROOT = Path(__file__).resolve().parents[1]
os.environ["MJX_MORPH_PAIR_CACHE"] = ""     # every test searches its self-collision pairs (none kept on disk)
os.environ.setdefault("MJX_MORPH_XLA_CACHE", str(ROOT / ".pytest_cache" / "xla"))
use_compile_cache(os.environ["MJX_MORPH_XLA_CACHE"], min_compile_s=1.0)


def smoke_config(*overrides: str):
    """The smoke training config (2 generated robots, tiny networks, 3 iterations) with extra overrides."""
    from mjx_morph.run import compose_run_config
    return compose_run_config(["preset=smoke", "robots=gen/train", "progress=false", *overrides])


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory):
    """One finished smoke run of rmomo, shared by the training, evaluation, report and render tests (its compiled
    train step is cached per process, so other smoke runs of the same config compile nothing)."""
    from mjx_morph.run import train
    d = tmp_path_factory.mktemp("runs") / "smoke-rmomo"
    cfg = smoke_config(f"run_dir={d}")
    train(cfg)
    return d, cfg


@pytest.fixture(scope="session")
def smoke_run_ff(tmp_path_factory):
    """The same smoke run for the feed-forward MetaMorph."""
    from mjx_morph.run import train
    d = tmp_path_factory.mktemp("runs") / "smoke-metamorph"
    cfg = smoke_config(f"run_dir={d}", "arch=metamorph")
    train(cfg)
    return d, cfg


EVAL_STEPS = 30   # episode length of the evaluations in the tests


@pytest.fixture(scope="session")
def evaluated_runs(smoke_run, smoke_run_ff):
    """Both smoke runs evaluated on short episodes: rmomo on train, its variants and (labelled) test = the train
    robots again; metamorph on train and test. Shared by the evaluation and report tests."""
    from mjx_morph.eval.evaluate import evaluate_run
    kw = dict(episodes=2, seed=0, zero_state_steps=10, episode_length=EVAL_STEPS, trace_steps=EVAL_STEPS,
              log=EVAL_LOG.append)
    evaluate_run(smoke_run[0], ["train", "variants", "test:train"], zero_state_sets=("train", "test"), **kw)
    evaluate_run(smoke_run_ff[0], ["train", "test:train"], **kw)
    return smoke_run[0], smoke_run_ff[0]


EVAL_LOG: list[str] = []   # what evaluated_runs printed
