"""The training loop around the jitted PPO iteration. It does no learning itself: it builds the run, resumes it,
calls the iteration, and reports through callbacks (metrics, progress bar, checkpoints, figures).

    train(cfg)                                  # cfg: RunConfig, or a composed Hydra config
    train(cfg, experiment=exp)                  # reuse an `Experiment` (its compiled functions) of the same config
    train(cfg, callbacks=[*default_callbacks(cfg), MyCallback()])

    train(cfg_with_seeds)                       # seeds=[0,1,2]: three runs side by side in one program (below)

A resumed run ends where an uninterrupted one would: the whole train state (parameters, optimiser, normalisers,
sampler, env and recurrent state, keys) is in the checkpoint. `stop_after` and `time_limit_min` end an invocation
early with a checkpoint, `stop_at` ends the run at that iteration for good (a rerun does nothing more); Ctrl-C ends
an invocation with a checkpoint too, and a Ctrl-C while the last checkpoint is written waits for it (`interrupts_held`).

Callbacks (`Callback`): `on_start(loop)` once, `on_iteration(loop, state, row)` after every iteration with the
metrics row, `on_stop(loop, state, reason)` once at the end, reason "done" (the invocation's last iteration ran),
"time_limit", "interrupted", "unhealthy" (`HealthWarnings` asked to stop) or "error". Only `run_iteration` touches
the device; everything here is plain Python.

Several seeds (`seeds=[0, 1, 2]`): one compiled program trains every seed (`Trainer(seeds=S)`, a vmapped train
state), and each seed is an ordinary run with its own run directory (`run_dir` with `{seed}` in it, default
runs/<task>-<arch>-s<seed>), config.yaml (with `seed` = that seed, as if trained alone), metrics and checkpoints: it
can be resumed, evaluated or reported alone. The callbacks are called once per seed (`loop.member`), with the state
of all seeds; `loop.own(state)` is that seed's.

Several processes (hosts; `mjx_morph/run/distributed.py`, started first thing in `train`): every process runs this
loop on its share of the devices and takes part in checkpoints; only process 0 prints, logs, draws and shows the
progress bar, and its clock decides the time limit. Ctrl-C saves no checkpoint then (the others could not join it).
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import jax

import numpy as np

from ..ppo.trainer import Trainer, TrainState, seed_keys, seed_state, stack_seeds
from ..sim import linalg
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
    member: int = 0     # which of the runs trained side by side (`seeds`) this one is
    members: int = 1    # how many runs are trained side by side
    seeded: bool = False  # the state given to callbacks holds every seed (a leading seed axis)

    def own(self, state: TrainState) -> TrainState:
        """This run's train state (the state callbacks get holds every seed's when `seeds` are side by side)."""
        return seed_state(state, self.member) if self.seeded else state


STALL_EXIT = 75          # the exit status of a process ended by StallWatchdog (EX_TEMPFAIL: try again)
STALL_FACTOR = 20.0      # ... once an iteration runs this many times the slowest before it (and stall_min)


class StallWatchdog:
    """Ends the process when one iteration runs `minutes` and STALL_FACTOR times the slowest iteration before it.
    A device that stalls (a collective waiting forever) blocks the loop inside the jitted call, where Python cannot
    interrupt it; without this the process holds the machine silently until something outside kills it. A rerun
    resumes from the last checkpoint. The first iteration of an invocation (compilation) is never watched."""

    def __init__(self, minutes: float | None):
        self.minutes = minutes
        self._timer: threading.Timer | None = None

    def arm(self, it: int, slowest: float) -> None:
        self.disarm()
        if not self.minutes:
            return
        limit = max(60.0 * self.minutes, STALL_FACTOR * slowest)

        def fire():
            before = f"{limit / slowest:.0f}x the slowest before it ({slowest:.1f} s)" if slowest else \
                "the first iteration timed"
            sys.stderr.write(f"\n[mjx_morph] iteration {it + 1} has run {limit / 60:.1f} min, {before}: the device "
                             f"looks stalled. Ending the process (exit status {STALL_EXIT}); a rerun resumes from the "
                             "last checkpoint (stall_min=null waits instead).\n")
            sys.stderr.flush()
            sys.stdout.flush()
            os._exit(STALL_EXIT)
        self._timer = threading.Timer(limit, fire)
        self._timer.daemon = True
        self._timer.start()

    def disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None


class Callback:
    """Hooks of the train loop; each does nothing unless overridden. A callback that sets `stop_requested` ends the
    invocation after the iteration (reason "unhealthy": `HealthWarnings`)."""

    stop_requested: bool = False

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
    """A tqdm bar with the mean episode return (over the seeds side by side), env steps/s (all seeds) and the ETA."""

    def on_start(self, loop):
        from tqdm import tqdm
        if loop.member == 0:
            self.returns = []
            self.bar = tqdm(total=loop.num_iters, initial=loop.start, unit="it", dynamic_ncols=True,
                            file=sys.stderr) if loop.start < loop.num_iters and distributed.is_main() else None

    def on_iteration(self, loop, state, row):
        if self.bar is None:
            return
        self.returns.append(row["episode_return"])
        if loop.member == loop.members - 1:
            ret = float(np.nanmean(self.returns)) if np.isfinite(self.returns).any() else float("nan")
            self.bar.set_postfix(ret=f"{ret:.1f}", sps=f"{row['sps'] * loop.members:,.0f}", refresh=False)
            self.bar.update(1)
            self.returns = []

    def on_stop(self, loop, state, reason):
        if self.bar is not None and loop.member == loop.members - 1:
            self.bar.close()


class ProgressLines(Callback):
    """Where there is no bar (`progress=false`: logs, pipes, study workers), one plain line every `minutes`: the
    iteration, env steps, the mean episode return (over the seeds side by side), env steps/s (all seeds) and the
    time to the invocation's last iteration at the mean iteration time so far. `clock` is for tests."""

    def __init__(self, minutes: float, clock=time.monotonic):
        self.seconds, self.clock = 60.0 * minutes, clock

    def on_start(self, loop):
        if loop.member == 0:
            self.last, self.returns, self.walls = self.clock(), [], []

    def on_iteration(self, loop, state, row):
        it, now = int(row["iteration"]), self.clock()
        compiled = it == loop.start + 1         # an invocation's first iteration compiles; its own line says so
        if loop.member == 0:
            self.returns = []
            if not compiled:
                self.walls.append(row["wall_s"])
        self.returns.append(row["episode_return"])
        if compiled:
            self.last = now
        if loop.member < loop.members - 1 or now - self.last < self.seconds:
            return
        self.last = now
        ret = float(np.nanmean(self.returns)) if np.isfinite(self.returns).any() else float("nan")
        left = f", {(loop.stop - it) * float(np.mean(self.walls)) / 60.0:.1f} min to iteration {loop.stop}" \
            if self.walls else ""
        print(f"[mjx_morph] iteration {it}/{loop.stop}: {int(row['env_steps']):,} env steps, return {ret:.1f}, "
              f"{row['sps'] * loop.members:,.0f} env steps/s{left}", flush=True)


UNHEALTHY = "unhealthy.txt"     # in a run directory: the health warning that stopped it (stop_unhealthy=true)


def unhealthy_reason(run_dir: str | Path) -> str | None:
    """The first health warning that stopped the run in `run_dir` (its unhealthy.txt), None for a run not stopped."""
    f = Path(run_dir) / UNHEALTHY
    return f.read_text().strip().splitlines()[0] if f.exists() else None


class HealthWarnings(Callback):
    """One warning line per run (and kind) when its first iterations look broken rather than slow: value estimates
    beyond `max_value` in size (the critic predicts scaled returns, O(1-10) in every run so far: a model input out
    of scale shows here first; session 44's R-MeMo read 4.6e5 in iteration 1 from a context of 1e8), or the KL stop
    letting at most one minibatch run in each of the run's first `stuck` iterations (the policy then hardly moves).
    With `stop` (the run's `stop_unhealthy`, default true) the warning goes to the run directory's unhealthy.txt as
    well, and the loop ends the invocation once every run side by side has warned (`stop_requested`), with a
    checkpoint: GPU time is not spent on a run that cannot learn, and a rerun refuses to resume it."""

    def __init__(self, max_value: float = 100.0, stuck: int = 5, stop: bool = False):
        self.max_value, self.stuck, self.stop = float(max_value), int(stuck), bool(stop)
        self.warned: set[tuple[int, str]] = set()
        self.first: dict[int, list[float]] = {}         # per seed: minibatches applied in its first iterations
        self.stop_requested = False

    def _warn(self, loop, kind: str, text: str):
        if (loop.member, kind) not in self.warned:
            self.warned.add((loop.member, kind))
            who = f" ({loop.run.path.name})" if loop.members > 1 else ""
            print(f"[mjx_morph] warning{who}: {text}", flush=True)
            if self.stop:
                if distributed.is_main():
                    with (loop.run.path / UNHEALTHY).open("a") as fh:
                        fh.write(f"{text}\n")
                self.stop_requested = len({member for member, _ in self.warned}) == loop.members

    def on_iteration(self, loop, state, row):
        it, value = int(row["iteration"]), float(row.get("value_mean", 0.0))
        if not abs(value) <= self.max_value:            # NaN too
            self._warn(loop, "value", f"iteration {it}'s value estimates average {value:.3g}, where scaled returns "
                       "keep them within a few units: is a model input out of scale (contexts, observations)?")
        tr = loop.experiment.trainer
        if it <= self.stuck and tr.num_minibatches * tr.cfg.epochs > 1:   # a run's first iterations (unseen on resume)
            seen = self.first.setdefault(loop.member, [])
            seen.append(float(row.get("minibatches", 0.0)))
            if it == self.stuck and len(seen) == it and max(seen) <= 1:
                self._warn(loop, "stuck", f"the KL stop let at most one minibatch run in each of the first {it} "
                           "iterations: the policy hardly moves (metrics.csv: epochs_run, approx_kl, v_loss)")


class Checkpoints(Callback):
    """An Orbax checkpoint every `every` iterations, at the invocation's last iteration, and when the invocation
    ends early (time limit, Ctrl-C)."""

    def __init__(self, every: int):
        self.every = max(1, int(every))

    def on_iteration(self, loop, state, row):
        it = int(row["iteration"])
        if it % self.every == 0 or it == loop.stop:
            loop.run.save(it, loop.own(state))

    def on_stop(self, loop, state, reason):
        state = loop.own(state)
        it = int(state.iteration)
        if reason == "interrupted" and distributed.several():
            return          # every process would have to save, and the others were not interrupted with this one
        if reason in ("time_limit", "interrupted", "unhealthy") and it > (loop.run.latest_step() or 0):
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


@contextlib.contextmanager
def interrupts_held(note: str):
    """Ctrl-C (SIGINT) while the body runs is held, `note` printed, and KeyboardInterrupt raised once the body has
    ended (a second Ctrl-C is held too: the device tool sends one to the command and one to its process group, and
    it kills the command 20 s later anyway). Only the main thread can set signal handlers: elsewhere, a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []

    def hold(signum, frame):
        if not held:
            print(f"\n{note}", file=sys.stderr, flush=True)
        held.append(signum)
    before = signal.signal(signal.SIGINT, hold)
    if before is None:                  # a handler set outside Python: Python's own is the nearest to restore
        before = signal.default_int_handler
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
    if held:
        raise KeyboardInterrupt


def default_callbacks(cfg: RunConfig) -> list[Callback]:
    progress = [ProgressBar()] if cfg.progress else [ProgressLines(cfg.progress_every_min)] \
        if cfg.progress_every_min else []
    return [MetricsLog(), *progress, HealthWarnings(stop=cfg.stop_unhealthy), Checkpoints(cfg.checkpoint_every),
            Summary()]


def run_iteration(trainer: Trainer, state: TrainState, phase_timing: bool) -> tuple[TrainState, list[dict[str, float]]]:
    """One PPO iteration on the device, timed: -> (new state, one metrics row per seed, without the iteration
    counters). With `phase_timing` the rollout and the update run as two jitted calls, so each phase's rate is known.
    `sps` is each run's env steps per second of wall time (seeds side by side share the time)."""
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
    common = {"sps": steps / (t2 - t0), **phases, "wall_s": t2 - t0}
    metrics = jax.device_get(metrics)
    if trainer.num_seeds is None:
        return state, [{**{k: float(v) for k, v in metrics.items()}, **common}]
    return state, [{**{k: float(v[i]) for k, v in metrics.items()}, **common} for i in range(trainer.num_seeds)]


def member_configs(cfg: RunConfig) -> list[RunConfig]:
    """The runs of `cfg`: itself, or one per seed of `seeds` (each with its `seed`, no `seeds`, and its run
    directory: `run_dir` with `{seed}` replaced, or the default one)."""
    seeds = [cfg.seed] if cfg.seeds is None else list(cfg.seeds)
    return [dataclasses.replace(cfg, seed=s, seeds=None,
                                run_dir=None if cfg.run_dir is None else cfg.run_dir.replace("{seed}", str(s)))
            for s in seeds]


def _resume_step(cfg: RunConfig, runs: list[RunDir]) -> int | None:
    """The checkpoint every run resumes from (None: a fresh start); seeds side by side must agree on it."""
    if cfg.resume_step is not None:
        for run in runs:
            if cfg.resume_step not in run.steps():
                raise RunDirError(f"{run.path / 'checkpoints'}: no checkpoint {cfg.resume_step} to resume from; "
                                  f"have {run.steps() or 'none'}")
        return cfg.resume_step
    latest = [run.latest_step() for run in runs]
    if len(set(latest)) > 1:
        where = ", ".join(f"{run.path} at {s or 'no checkpoint'}" for run, s in zip(runs, latest))
        raise RunDirError(f"seeds={cfg.seeds}: the runs to train side by side are at different iterations ({where}); "
                          "resume them separately, or side by side only those at the same iteration. Nothing was "
                          "changed")
    return latest[0]


def train(cfg: Any, experiment: Experiment | None = None, callbacks: Sequence[Callback] | None = None
          ) -> Path | list[Path]:
    """Train (or resume) the run of `cfg`; returns its run directory (with `seeds`: the list of the seeds' run
    directories)."""
    began = time.perf_counter()          # time_limit_min counts from here: building and compiling included
    cfg = to_schema(cfg)
    cfg.check()
    distributed.initialize(cfg)         # several processes: before any JAX computation (the device list)
    members = member_configs(cfg)
    seeded = cfg.seeds is not None
    runs = [RunDir(m.run_dir or m.default_run_dir(), to_dict(m), IDENTITY, FREE, tuple(m.allow_changes))
            for m in members]
    if len({run.path for run in runs}) < len(runs):
        raise ValueError(f"seeds={cfg.seeds}: the seeds' run directories coincide ({runs[0].path}); put {{seed}} "
                         "in run_dir")
    marked = [(run.path, why) for run in runs if (why := unhealthy_reason(run.path))]
    if marked and cfg.stop_unhealthy:
        raise RunDirError(f"{marked[0][0] / UNHEALTHY}: this run stopped because it starts broken ({marked[0][1]}). "
                          "Find the cause and start a new run, or rerun with stop_unhealthy=false to train it on; "
                          "nothing was changed")
    exp = experiment if experiment is not None else build(cfg)     # validates the robots, the model, the geometry
    if cfg.expect_physics and not exp.env.digest.startswith(cfg.expect_physics):
        raise ValueError(f"expect_physics={cfg.expect_physics}: this config builds other physics, model digest "
                         f"{exp.env.digest} (task {cfg.env.task}, robots {exp.robot_set}, env.iterations="
                         f"{cfg.env.iterations}): the robots, the simulator options or the code's physics (git log -- "
                         "mjx_morph/sim mjx_morph/unimal) differ from the runs it should match; nothing was written")
    for run in runs:                    # a resume trains on the physics it trained on (before compiling anything)
        if run.latest_step() is not None:
            run.check_digest(exp.env.digest, tuple(cfg.allow_changes))
    trainer = exp.trainer
    if trainer.num_seeds != (len(members) if seeded else None):
        raise ValueError(f"the experiment's trainer runs seeds={trainer.num_seeds}, the config "
                         f"{len(members) if seeded else None}: build it from this config")
    pc = trainer.cfg
    chol = linalg.resolve(cfg.env.linalg)          # what MJX runs with here ("auto" stands for one per backend)
    print(f"[mjx_morph] {exp.model.arch} on {cfg.env.task}: {exp.env.num_robots} robots ({exp.robot_set}; physics "
          f"{exp.env.digest[:8]}, Cholesky {chol}), "
          f"{exp.model.num_params():,} parameters, {pc.num_envs} envs x {pc.rollout_len} steps = "
          f"{pc.steps_per_iter:,} steps/iteration, {trainer.num_iters} iterations on {trainer.num_devices} "
          f"{jax.devices()[0].platform} device(s)"
          + (f" of {jax.process_count()} processes" if distributed.several() else "")
          + (f"; seeds {list(cfg.seeds)} side by side, run dirs {', '.join(str(r.path) for r in runs)}" if seeded
             else f"; run dir {runs[0].path}"), flush=True)
    t0 = time.perf_counter()
    print("[mjx_morph] compiling and running the initial state (env resets, parameter init)...", end=" ", flush=True)
    keys = seed_keys(cfg.seeds) if seeded else jax.random.PRNGKey(cfg.seed)
    state = jax.block_until_ready(trainer.init(keys))
    print(f"{time.perf_counter() - t0:.0f} s", flush=True)
    latest = _resume_step(cfg, runs)
    if latest is not None:
        # the checkpoints may come from another device count, or from seeds trained alone
        if seeded:
            state = trainer.place(stack_seeds([run.restore(latest, trainer.abstract_state()) for run in runs]))
        else:
            state = trainer.place(runs[0].restore(latest, state))
    # everything is read and checked: only now are the run directories written
    for run in runs:
        run.create()
        for change in run.changes:
            print(f"[mjx_morph] {run.path.name}: resuming with a changed setting: {change} (recorded in "
                  "config_history.yaml)", flush=True)
        if cfg.resume_step is not None:
            moved = run.set_aside_after(cfg.resume_step)
            if moved:
                print(f"[mjx_morph] checkpoints {moved} moved to {run.path / 'checkpoints.orphaned'}", flush=True)
        run.truncate_metrics(latest or 0)      # rows after the checkpoint (or of a start that never saved one)
        run.record_invocation(latest or 0, trainer.num_devices, exp.env.digest, chol)
        if latest is not None:
            print(f"[mjx_morph] resumed from {run.path / 'checkpoints' / str(latest)} (iteration {latest})",
                  flush=True)
    start = latest or 0
    stop = min(trainer.num_iters, start + cfg.stop_after) if cfg.stop_after else trainer.num_iters
    if cfg.stop_at is not None:
        stop = max(start, min(stop, cfg.stop_at))
    loops = [Loop(m, run, exp, start, stop, trainer.num_iters, i, len(members), seeded)
             for i, (m, run) in enumerate(zip(members, runs))]
    callbacks = default_callbacks(cfg) if callbacks is None else list(callbacks)
    # time_limit_min: end the invocation once the next iteration would not fit (1.5x the slowest one seen)
    deadline = began + 60.0 * cfg.time_limit_min if cfg.time_limit_min else None
    for loop in loops:
        for cb in callbacks:
            cb.on_start(loop)
    it, slowest, reason = start, 0.0, "error"
    watchdog = StallWatchdog(cfg.stall_min)
    try:
        while it < stop:
            if deadline is not None and it > start and distributed.agree(
                    time.perf_counter() + 1.5 * slowest > deadline):
                reason = "time_limit"
                break
            if it == start:
                print("[mjx_morph] compiling the train step (the first iteration includes it)...", flush=True)
            if it > start:                 # the first iteration of an invocation compiles: not watched
                watchdog.arm(it, slowest)
            state, rows = run_iteration(trainer, state, cfg.phase_timing)
            watchdog.disarm()
            if it == start:
                print(f"[mjx_morph] first iteration, compilation included: {rows[0]['wall_s']:.0f} s", flush=True)
            it += 1
            if it > start + 1:             # the first iteration of an invocation includes compilation
                slowest = max(slowest, rows[0]["wall_s"])
            for loop, row in zip(loops, rows):
                row = {"iteration": it, "env_steps": it * pc.steps_per_iter, **row}
                for cb in callbacks:
                    cb.on_iteration(loop, state, row)
            if any(cb.stop_requested for cb in callbacks):
                reason = "unhealthy"
                break
        else:
            reason = "done"
    except KeyboardInterrupt:
        reason = "interrupted"
        raise
    finally:
        watchdog.disarm()
        # the last checkpoint is written whatever Ctrl-C comes meanwhile (session 29: a run that stopped at its time
        # limit got the device tool's Ctrl-C seconds later, luckily after its save): held, then raised
        with interrupts_held("[mjx_morph] Ctrl-C: held until the last checkpoint is written"):
            for loop in loops:
                for cb in callbacks:
                    cb.on_stop(loop, state, reason)
                loop.run.close()
            if reason == "unhealthy":
                print(f"\n[mjx_morph] stopped at iteration {it}: the run starts broken (the warning above, also in "
                      f"{', '.join(str(loop.run.path / UNHEALTHY) for loop in loops)}); checkpoint saved. Find the "
                      "cause; stop_unhealthy=false trains on", file=sys.stderr, flush=True)
            if reason in ("time_limit", "interrupted"):
                what = "time limit reached" if reason == "time_limit" else "interrupted"
                saved = "checkpoint saved" if reason == "time_limit" or not distributed.several() else \
                    "no checkpoint saved (several processes: a rerun resumes from the last periodic one)"
                print(f"\n[mjx_morph] {what} at iteration {it}; {saved}. "
                      f"Rerun the same command to resume.", file=sys.stderr, flush=True)
    return [run.path for run in runs] if seeded else runs[0].path
