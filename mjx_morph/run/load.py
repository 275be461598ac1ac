"""Loading a finished (or interrupted) run for evaluation: its config, its objects and a checkpoint's train state."""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from ..ppo.trainer import TrainState
from .build import Experiment, build
from .config import RunConfig, read_run_config
from .run_dir import RunDir, RunDirError


class LoadedRun(NamedTuple):
    path: Path
    config: RunConfig
    experiment: Experiment
    state: TrainState
    step: int               # the checkpoint's iteration


def load_run(run_dir: str | Path, step: int | None = None) -> LoadedRun:
    """The run in `run_dir` at checkpoint `step` (default: the newest).

    The checkpoint is restored into the trainer's abstract state: nothing is compiled or run, so loading a run
    costs building its robot set and reading the arrays."""
    run_dir = Path(run_dir)
    cfg_file = run_dir / "config.yaml"
    if not cfg_file.exists():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = read_run_config(cfg_file)
    run = RunDir(run_dir)
    try:
        steps = run.manager.all_steps() if (run_dir / "checkpoints").exists() else []
        if not steps:
            raise FileNotFoundError(f"{run_dir / 'checkpoints'}: no checkpoint yet")
        if step is None:
            step = max(steps)
        elif step not in steps:
            raise FileNotFoundError(f"{run_dir / 'checkpoints'}: no checkpoint {step}; have {sorted(steps)}")
        exp = build(cfg)
        state = run.restore(step, exp.trainer.abstract_state())
    finally:
        run.close()
    return LoadedRun(run_dir, cfg, exp, state, int(step))


__all__ = ["LoadedRun", "RunDirError", "load_run"]
