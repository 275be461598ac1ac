"""The training loop around the jitted PPO iteration. It does no learning itself: it builds the run, resumes it,
calls the iteration, and reports through callbacks (metrics, progress bar, checkpoints, figures).

    train(cfg)                                  # cfg: RunConfig, or a composed Hydra config
    train(cfg, experiment=exp)                  # reuse an `Experiment` (its compiled functions) of the same config
    train(cfg, callbacks=[*default_callbacks(cfg), MyCallback()])

A resumed run ends where an uninterrupted one would: the whole train state (parameters, optimiser, normalisers,
sampler, env and recurrent state, keys) is in the checkpoint. `stop_after` and `time_limit_min` end an invocation
early with a checkpoint, `stop_at` ends the run at that iteration for good (a rerun does nothing more); Ctrl-C does too.

Callbacks (`Callback`): `on_start(loop)` once, `on_iteration(loop, state, row)` after every iteration with the
metrics row, `on_stop(loop, state, reason)` once at the end, reason "done" (the invocation's last iteration ran),
"time_limit", "interrupted" or "error". Only `run_iteration` touches the device; everything here is plain Python.

Several processes (hosts; `mjx_morph/run/distributed.py`, started first thing in `train`): every process runs this
loop on its share of the devices and takes part in checkpoints; only process 0 prints, logs, draws and shows the
progress bar, and its clock decides the time limit. Ctrl-C saves no checkpoint then (the others could not join it).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import jax

from ..ppo.trainer import Trainer, TrainState
from . import distributed
from .build import Experiment, build
from .config import FREE, IDENTITY, RunConfig, to_dict, to_schema
from .distributed import print_main as print    # with several processes only process 0 prints
from .figures import learning_curve
from .run_dir import RunDir, RunDirError


@dataclasses.dataclass
class Loop:
    """What callbacks see of the loop."""
    config: RunConfig
    run: RunDir
    experiment: Experiment
    start: int          # iterations already done when this invocation started (a resumed run: > 0)
    stop: int           # the iteration this invocation ends at (unless the time limit comes first)
    num_iters: int      # iterations of the whole run


class Callback:
    """Hooks of the train loop; each does nothing unless overridden."""

    def on_start(self, loop: Loop) -> None:
        pass

    def on_iteration(self, loop: Loop, state: TrainState, row: dict[str, float]) -> None:
        pass

    def on_stop(self, loop: Loop, state: TrainState, reason: str) -> None:
        pass


class MetricsLog(Callback):
    """One row per iteration in metrics.csv and TensorBoard."""

    def on_iteration(self, loop, state, row):
        loop.run.log(row)


class ProgressBar(Callback):
    """A tqdm bar with the mean episode return, env steps/s and the ETA."""

    def on_start(self, loop):
        from tqdm import tqdm
        self.bar = tqdm(total=loop.num_iters, initial=loop.start, unit="it", dynamic_ncols=True, file=sys.stderr) \
            if loop.start < loop.num_iters and distributed.is_main() else None

    def on_iteration(self, loop, state, row):
        if self.bar is not None:
            self.bar.set_postfix(ret=f"{row['episode_return']:.1f}", sps=f"{row['sps']:,.0f}", refresh=False)
            self.bar.update(1)

    def on_stop(self, loop, state, reason):
        if self.bar is not None:
            self.bar.close()


class Checkpoints(Callback):
    """An Orbax checkpoint every `every` iterations, at the invocation's last iteration, and when the invocation
    ends early (time limit, Ctrl-C)."""

    def __init__(self, every: int):
        self.every = max(1, int(every))

    def on_iteration(self, loop, state, row):
        it = int(row["iteration"])
        if it % self.every == 0 or it == loop.stop:
            loop.run.save(it, state)

    def on_stop(self, loop, state, reason):
        it = int(state.iteration)
        if reason == "interrupted" and distributed.several():
            return          # every process would have to save, and the others were not interrupted with this one
        if reason in ("time_limit", "interrupted") and it > (loop.run.latest_step() or 0):
            loop.run.save(it, state)


class Summary(Callback):
    """At the end of a finished invocation: the learning curve figure and a closing line."""

    def on_stop(self, loop, state, reason):
        if reason != "done" or not distributed.is_main():
            return
        rows = loop.run.read_metrics()
        exp = loop.experiment
        png = learning_curve(rows, loop.run.path / "learning_curve.png",
                             title=f"{exp.model.arch} on {loop.config.env.task} ({exp.env.num_robots} robots)")
        if rows:
            last = rows[-1]
            print(f"[mjx_morph] done: {int(last['env_steps']):,} env steps; last mean episode return "
                  f"{last.get('episode_return', float('nan')):.2f}; learning curve {png}", flush=True)


def default_callbacks(cfg: RunConfig) -> list[Callback]:
    return [MetricsLog(), *([ProgressBar()] if cfg.progress else []), Checkpoints(cfg.checkpoint_every), Summary()]


def run_iteration(trainer: Trainer, state: TrainState, phase_timing: bool) -> tuple[TrainState, dict[str, float]]:
    """One PPO iteration on the device, timed: -> (new state, metrics row without the iteration counters).
    With `phase_timing` the rollout and the update run as two jitted calls, so each phase's rate is known."""
    steps = trainer.cfg.steps_per_iter
    t0 = time.perf_counter()
    if phase_timing:
        state, batch, m1 = trainer.rollout(state)
        jax.block_until_ready(batch)
        t1 = time.perf_counter()
        state, m2 = trainer.update(state, batch)
        metrics = {**m1, **m2}
        jax.block_until_ready(state.params)
        t2 = time.perf_counter()
        phases = {"rollout_sps": steps / (t1 - t0), "update_sps": steps / (t2 - t1)}
    else:
        state, metrics = trainer.iteration(state)
        jax.block_until_ready(state.params)
        t2 = time.perf_counter()
        phases = {"rollout_sps": float("nan"), "update_sps": float("nan")}
    row = {**{k: float(v) for k, v in jax.device_get(metrics).items()}, "sps": steps / (t2 - t0), **phases,
           "wall_s": t2 - t0}
    return state, row


def train(cfg: Any, experiment: Experiment | None = None, callbacks: Sequence[Callback] | None = None) -> Path:
    """Train (or resume) the run of `cfg`; returns its run directory."""
    cfg = to_schema(cfg)
    cfg.check()
    distributed.initialize(cfg)         # several processes: before any JAX computation (the device list)
    run = RunDir(cfg.run_dir or cfg.default_run_dir(), to_dict(cfg), IDENTITY, FREE, tuple(cfg.allow_changes))
    exp = experiment if experiment is not None else build(cfg)     # validates the robots, the model, the geometry
    trainer = exp.trainer
    pc = trainer.cfg
    print(f"[mjx_morph] {exp.model.arch} on {cfg.env.task}: {exp.env.num_robots} robots ({exp.robot_set}), "
          f"{exp.model.num_params():,} parameters, {pc.num_envs} envs x {pc.rollout_len} steps = "
          f"{pc.steps_per_iter:,} steps/iteration, {trainer.num_iters} iterations on {trainer.num_devices} "
          f"{jax.devices()[0].platform} device(s)"
          + (f" of {jax.process_count()} processes" if distributed.several() else "") + f"; run dir {run.path}",
          flush=True)
    t0 = time.perf_counter()
    print("[mjx_morph] compiling and running the initial state (env resets, parameter init)...", end=" ", flush=True)
    state = jax.block_until_ready(trainer.init(jax.random.PRNGKey(cfg.seed)))
    print(f"{time.perf_counter() - t0:.0f} s", flush=True)
    latest = run.latest_step() if cfg.resume_step is None else cfg.resume_step
    if cfg.resume_step is not None and cfg.resume_step not in run.steps():
        raise RunDirError(f"{run.path / 'checkpoints'}: no checkpoint {cfg.resume_step} to resume from; "
                          f"have {run.steps() or 'none'}")
    if latest is not None:
        state = trainer.place(run.restore(latest, state))     # the checkpoint may come from another device count
    # everything is read and checked: only now is the run directory written
    run.create()
    for change in run.changes:
        print(f"[mjx_morph] resuming with a changed setting: {change} (recorded in config_history.yaml)", flush=True)
    if cfg.resume_step is not None:
        moved = run.set_aside_after(cfg.resume_step)
        if moved:
            print(f"[mjx_morph] checkpoints {moved} moved to {run.path / 'checkpoints.orphaned'}", flush=True)
    run.truncate_metrics(latest or 0)          # rows after the checkpoint (or of a start that never saved one)
    if latest is not None:
        print(f"[mjx_morph] resumed from {run.path / 'checkpoints' / str(latest)} (iteration {latest})", flush=True)
    start = int(state.iteration)
    stop = min(trainer.num_iters, start + cfg.stop_after) if cfg.stop_after else trainer.num_iters
    if cfg.stop_at is not None:
        stop = max(start, min(stop, cfg.stop_at))
    loop = Loop(cfg, run, exp, start, stop, trainer.num_iters)
    callbacks = default_callbacks(cfg) if callbacks is None else list(callbacks)
    # time_limit_min: end the invocation once the next iteration would not fit (1.5x the slowest one seen)
    deadline = time.perf_counter() + 60.0 * cfg.time_limit_min if cfg.time_limit_min else None
    for cb in callbacks:
        cb.on_start(loop)
    it, slowest, reason = start, 0.0, "error"
    try:
        while it < stop:
            if deadline is not None and it > start and distributed.agree(
                    time.perf_counter() + 1.5 * slowest > deadline):
                reason = "time_limit"
                break
            if it == start:
                print("[mjx_morph] compiling the train step (the first iteration includes it)...", flush=True)
            state, row = run_iteration(trainer, state, cfg.phase_timing)
            if it == start:
                print(f"[mjx_morph] first iteration, compilation included: {row['wall_s']:.0f} s", flush=True)
            it = int(state.iteration)
            if it > start + 1:             # the first iteration of an invocation includes compilation
                slowest = max(slowest, row["wall_s"])
            row = {"iteration": it, "env_steps": it * pc.steps_per_iter, **row}
            for cb in callbacks:
                cb.on_iteration(loop, state, row)
        else:
            reason = "done"
    except KeyboardInterrupt:
        reason = "interrupted"
        raise
    finally:
        for cb in callbacks:
            cb.on_stop(loop, state, reason)
        run.close()
        if reason in ("time_limit", "interrupted"):
            what = "time limit reached" if reason == "time_limit" else "interrupted"
            saved = "checkpoint saved" if reason == "time_limit" or not distributed.several() else \
                "no checkpoint saved (several processes: a rerun resumes from the last periodic one)"
            print(f"\n[mjx_morph] {what} at iteration {int(state.iteration)}; {saved}. "
                  f"Rerun the same command to resume.", file=sys.stderr, flush=True)
    return run.path
