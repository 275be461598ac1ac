"""Run a study: every run of experiments/conf/study/<name>.yaml for each architecture and seed, then evaluate it.

    python -m experiments.study train_size archs=[rmomo,modumorph] seeds=[0,1,2] env=ft
    python -m experiments.study context_features archs=[rmomo] dry_run=true          # list the runs only
    python -m experiments.study train_size archs=[rmomo] -- preset=smoke robots=gen/train   # extra run overrides
    python -m experiments.study paper archs=[rmomo,metamorph,rmemo] seeds=[2] seeds_of.rmomo=[6,7]   # other seeds
    python -m experiments.study paper archs=[rmomo,metamorph] seeds=[4] stop_at_of.rmomo=245 -- stop_at=220

A study file lists `runs` (name -> overrides of experiments.run), and optionally `common` (overrides of every run),
`archs` and `seeds` (the defaults of archs= and seeds=; `seeds_of.<arch>=[...]` gives one architecture other
seeds, so that one plan holds the runs each model still needs, and `stop_at_of.<arch>=N` its own experiments.run
stop_at, so that each model stops where the runs it pools with were evaluated) and `evaluate` (the sets to evaluate
each run on, in order; `evaluate=[...]` for others, e.g. the zero-shot sets first: `evaluate=[test,variants]`).

A study's name with a task after it, `paper_ft` or `paper_incline`, is that study with env=<task>.

Run directories: <out>/<study>/<env>-<arch>-<run>-s<seed> (default out: runs/studies). Each run is an ordinary
`experiments.run` run: rerunning the study resumes unfinished runs; finished ones are not retrained, and a set
already evaluated at the run's last checkpoint (eval/<set>.json) is not evaluated again. `only=[a,b]` takes the
study's runs a and b alone; `time_limit_min=N` ends the invocation after about N minutes of training (the run in
training checkpoints, runs that did not finish are not evaluated, and of a finished batch only the evaluations that
fit, `eval_minutes` per set and run, in the study file's order of sets over the seeds, a set too long for the time
left giving way to shorter ones after it; rerun to go on):

    python -m experiments.study ab_rmomo_cell only=[scale_before,scale_after] seeds=[0,1] time_limit_min=9

In the last minutes of a run's training (evaluate.PrepareEvaluation: about 4 minutes of iterations left) a background
thread builds the envs of the sets the time limit will let it evaluate and compiles their sweeps, on the host's CPU
while the GPU trains; the evaluations then start at once, each set waiting for its own preparation alone if that is
still under way, and the time limit counts them at `EVAL_MINUTES_PREPARED` (one still being prepared at its
unprepared time less the time its preparation has already run, never below its prepared time). `prepare_eval=false`
turns this off.

The seeds of a run train side by side in one program (`seeds=[...]` of experiments.run; those at the same checkpoint
together), unless side_by_side=false. Afterwards: python -m experiments.report runs=[<out>/<study>] out=<dir>.

Several GPUs of one host: the study runs in one process per visible GPU (`workers=N` for another number, 1 for
one process), worker k on GPU k alone (CUDA_VISIBLE_DEVICES), each taking every N-th run of the plan (seeds last, so
two seeds go to two GPUs), training and evaluating its runs with no communication; their output lines come prefixed
[w<k>]. Independent runs, one per GPU, are the measured way to use several GPUs (docs/benchmarks.md, "Several
devices"):

    python -m experiments.study ab_precision only=[fp32] archs=[modumorph] seeds=[0,1] time_limit_min=9   # 2 GPUs

On several hosts (the same command on each, with the distributed settings of experiments.run after --: README,
"Several hosts") every process trains each run, process 0 alone evaluates it while the others wait.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

import yaml
from omegaconf import MISSING

from mjx_morph.eval.evaluate import PrepareEvaluation, evaluate_run, evaluated, resolve_set, wait_for_preparation
from mjx_morph.run import (CONF_DIR, RunDir, compose_run_config, default_callbacks, distributed, register,
                           to_schema, train, unhealthy_reason, use_compile_cache)
from mjx_morph.sim.env import EnvConfig
from mjx_morph.sim.tasks import TASKS

from . import cli


DEFAULT_ARCHS = ["rmomo", "modumorph"]
MIN_TRAIN_MIN = 1.0     # with time_limit_min: do not start (compile) a training with less time than this left
#: ... nor the evaluation of one set of one run, compilation included, measured one run per GPU (the longer of
#: H100 and H200): train (100 robots) 110-136 s on an H100, 71-80 s on an H200; val (32) 95 s and 54-57 s; test70
#: 63-75 s on both (sessions 19-20), 10-12 s of it the pair search that `device_job.sh prepare` now keeps in
#: .gpu/pairs; the variants (2400): env built in 77-79 s on an H100 host (29-30 s of it the search; ~25 s without it,
#: `put_model` spread over the cores: estimated), then 2 sweeps of 4800 envs x 1000 steps, the first with compilation
#: in 154 s (31 k env steps/s), the second ~100 s (estimated: it was cut by the call's end). Session 26 (four runs on
#: one host, a run that finished its training too soon to prepare): R-MeMo's test70 with the zero-state sweep (560
#: episodes) 90 s, the variants 325 s (env built in 67 s)
EVAL_MINUTES = {"train": 2.5, "val": 1.75, "test": 1.5, "variants": 5.5}
EVAL_SET_MIN = 2.5      # ... and of any other set (the largest of the ~100-robot sets)
#: ... and when its env and sweep were prepared while the run trained (PrepareEvaluation). Measured (session 22, one run
#: per H100 of 4): the variants 196-199 s, test70 27 s after them; plus loading the checkpoint for a run's first set
#: (~20 s, estimated); the others estimated from the sets' sizes. Tight on purpose: in the paper study's third call
#: ModuMorph leaves ~4 minutes, and an evaluation that overruns the study's limit still has the ~30 s before
#: device_job.sh's interrupt (what it interrupts is the last set, which a looser estimate would not have started).
EVAL_MINUTES_PREPARED = {"train": 1.0, "val": 0.75, "test": 0.75, "variants": 3.75}
EVAL_SET_MIN_PREPARED = 1.0


def eval_minutes(name: str, prepared: bool = False, preparing_s: float = 0.0) -> float:
    """The time a study's time limit sets aside for evaluating set `name` of one run (`prepared`: its env and sweep
    were prepared while the run trained; `preparing_s`: the seconds its preparation, still under way, has run, which
    come off the unprepared time down to the prepared one. Session 30: the variants of two runs, 9-12 s from
    prepared, were counted at their whole unprepared 5.5 minutes, did not fit the ~6 minutes left, and were lost with
    the machine)."""
    least = EVAL_MINUTES_PREPARED.get(name, EVAL_SET_MIN_PREPARED)
    if prepared:
        return least
    return max(least, EVAL_MINUTES.get(name, EVAL_SET_MIN) - preparing_s / 60.0)


def evaluations_that_fit(sets: list[str], minutes: float, prepared, preparing: dict[str, float] | None = None
                         ) -> list[int]:
    """The indices of the evaluations `sets` (one set name per (set, run), in order of priority) that fit `minutes`,
    each counted at `eval_minutes` (its prepared time for the sets in `prepared`; for one in `preparing`, {set:
    seconds its preparation has run}, less): each in turn is taken if it fits what the ones taken before it leave, so
    that one too long for the time left gives way to shorter ones after it."""
    preparing = preparing or {}
    fit = []
    for i, s in enumerate(sets):
        need = eval_minutes(s, s in prepared, preparing.get(s, 0.0))
        if need <= minutes:
            fit.append(i)
            minutes -= need
    return fit


@dataclasses.dataclass
class StudyConfig:
    name: str = MISSING                 # the study: a file of experiments/conf/study (without .yaml)
    archs: Optional[List[str]] = None   # None: the study file's `archs`, else [rmomo, modumorph]
    seeds: Optional[List[int]] = None   # None: the study file's `seeds`, else [0]
    seeds_of: Dict[str, List[int]] = dataclasses.field(default_factory=dict)   # other seeds for some of the archs,
                                        # e.g. 'seeds_of.rmomo=[6,7]': one plan with the runs each model still needs
    stop_at_of: Dict[str, int] = dataclasses.field(default_factory=dict)   # experiments.run's stop_at for some archs
                                        # (over one given after --), e.g. stop_at_of.rmomo=245: each model stops
                                        # where the runs it is compared with were evaluated
    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)   # env=<task> and env.<option>=... for every run
    out: str = "runs/studies"
    episodes: int = 4                   # evaluation episodes per robot
    evaluate: Optional[List[str]] = None   # the sets to evaluate every run on, in this order (None: the study file's
                                        # `evaluate`); with a time limit the first come first, e.g. [test,variants]
                                        # (a set that no longer fits gives way to shorter ones after it)
    dry_run: bool = False               # print the runs and stop
    side_by_side: bool = True           # train the seeds of a run in one program (experiments.run seeds=[...])
    run: List[str] = dataclasses.field(default_factory=list)   # extra experiments.run overrides (after --)
    only: Optional[List[str]] = None    # these runs of the study file alone (None: all)
    time_limit_min: Optional[float] = None   # end this invocation after about N minutes of training (resumable)
    workers: Optional[int] = None       # processes, one per GPU, each training every workers-th run (None: one per
                                        # visible GPU, at most one per run; 1 without GPUs or with several hosts)
    worker: Optional[int] = None        # set by the study for its workers: this process is worker k (0-based)
    prepare_eval: bool = True           # build the evaluations' envs and compile their sweeps in a background thread
                                        # during the last minutes of training (evaluate.PrepareEvaluation)


register("study_schema", StudyConfig)


@dataclasses.dataclass(frozen=True)
class StudyRun:
    dir: Path
    overrides: list[str]     # experiments.run overrides of this run alone
    sets: list[str]          # the sets to evaluate it on
    group: tuple[str, str]   # (arch, run name): the runs of a group differ only in their seed
    seed: int


STUDY_DIR = CONF_DIR / "study"


def study_file(name: str) -> Path:
    return STUDY_DIR / f"{name}.yaml"


def plan(c: StudyConfig) -> list[StudyRun]:
    """Every run of a study, grouped by architecture and run name, seeds last."""
    f = study_file(c.name)
    if not f.exists():
        known = sorted(p.stem for p in STUDY_DIR.glob("*.yaml"))
        raise ValueError(f"no study {c.name!r} ({f} does not exist); known: {', '.join(known)}")
    spec = yaml.safe_load(f.read_text())
    names = list(spec["runs"])
    unknown = [n for n in (c.only or []) if n not in names]
    if unknown or c.only == []:
        raise ValueError(f"only={c.only}: {f} has the runs {', '.join(names)}; expected a non-empty list of them")
    default = EnvConfig(task=c.env.task)
    env_over = [f"env={c.env.task}"] + [f"env.{k.name}={getattr(c.env, k.name)}" for k in dataclasses.fields(EnvConfig)
                                         if getattr(c.env, k.name) != getattr(default, k.name)]
    common = list(spec.get("common", []))        # overrides of every run of the study (before each run's own)
    sets = c.evaluate if c.evaluate is not None else spec.get("evaluate", ["train", "test"])
    archs = list(c.archs if c.archs is not None else spec.get("archs", DEFAULT_ARCHS))
    seeds_of, stop_at_of = dict(c.seeds_of), dict(c.stop_at_of)
    for key, given, what in (("seeds_of", seeds_of, "seeds"), ("stop_at_of", stop_at_of, "an iteration")):
        stray = [a for a in given if a not in archs]
        if stray:
            raise ValueError(f"{key}={given}: {', '.join(stray)} not among the study's architectures "
                             f"({', '.join(archs)}); expected {what} for some of them")
    seeds = c.seeds if c.seeds is not None else spec.get("seeds", [0])
    runs = []
    for arch in archs:
        extra = list(c.run)
        if arch in stop_at_of:
            extra = [o for o in extra if o.split("=")[0] != "stop_at"] + [f"stop_at={stop_at_of[arch]}"]
        for name, overrides in spec["runs"].items():
            if c.only is not None and name not in c.only:
                continue
            for seed in seeds_of.get(arch, seeds):
                d = Path(c.out) / c.name / f"{c.env.task}-{arch}-{name}-s{seed}"
                runs.append(StudyRun(d, [*env_over, f"arch={arch}", f"seed={seed}", f"run_dir={d}", *common,
                                         *overrides, *extra],
                                     list(sets), (arch, name), seed))
    return runs


def study_for_task(argv: list[str]) -> list[str]:
    """`<study>_<task>` (e.g. `paper_ft`, as issue 15 names the command) where no study file has that name: the study
    `<study>` with `env=<task>`, the same runs in the same directories (<out>/<study>/<task>-...) as `<study>
    env=<task>`, so either spelling resumes the other. A different env= beside it is refused."""
    if not argv or "=" in argv[0] or argv[0].startswith("-") or study_file(argv[0]).exists():
        return argv
    base, _, task = argv[0].rpartition("_")
    if task not in TASKS or not study_file(base).exists():
        return argv
    given = [a for a in argv[1:] if a.split("=")[0] == "env"]
    if given and given != [f"env={task}"]:
        raise ValueError(f"{argv[0]} is the study {base} on {task}, but {' '.join(given)} was given too; expected "
                         f"one task: `{base} env=<task>` or `{base}_<task>` alone")
    return [base, *([] if given else [f"env={task}"]), *argv[1:]]


def share(runs: list[StudyRun], workers: int, worker: int) -> list[StudyRun]:
    """Worker `worker`'s runs: every workers-th of the plan (grouped by architecture and run, seeds last, so the
    seeds of one run go to different workers)."""
    return runs[worker::workers]


def visible_gpus() -> tuple[list[str], str] | None:
    """The GPUs this process may use and where that was read (its CUDA_VISIBLE_DEVICES, else nvidia-smi -L), without
    starting JAX (which would take their memory); None without nvidia-smi (a CPU machine)."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g.strip() for g in visible.split(",") if g.strip()], f"CUDA_VISIBLE_DEVICES={visible}"
    if shutil.which("nvidia-smi"):
        listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
        return [str(i) for i, ln in enumerate(listed.splitlines()) if ln.startswith("GPU ")], "nvidia-smi -L"
    return None


def several_processes(c: StudyConfig) -> bool:
    """The runs are given the settings of several processes (hosts) among their experiments.run overrides."""
    return any(o.split("=")[0] in ("coordinator", "num_processes", "process_id") for o in c.run)


def default_workers(c: StudyConfig, runs: list[StudyRun]) -> int:
    """workers=None: one per visible GPU, at most one per run; 1 on a CPU machine and for runs of several processes."""
    found = visible_gpus()
    if several_processes(c) or os.environ.get("MJX_MORPH_NUM_PROCESSES") or found is None:
        return 1
    return max(1, min(len(found[0]), len(runs)))


def worker_devices(workers: int) -> list[str]:
    """CUDA_VISIBLE_DEVICES of each worker: one GPU each, from those this process may use (its own
    CUDA_VISIBLE_DEVICES, else every GPU nvidia-smi lists). Without nvidia-smi (a CPU machine) the workers share the
    CPU and the names are 0, 1, ..."""
    found = visible_gpus()
    if found is None:
        return [str(k) for k in range(workers)]
    gpus, source = found
    if len(gpus) < workers:
        raise ValueError(f"workers={workers}: only {len(gpus)} GPU(s) visible ({source}); expected at most one "
                         "worker per GPU")
    return gpus[:workers]


def worker_command(argv: list[str], workers: int, k: int) -> list[str]:
    """The command of worker k: this study's own arguments with workers=<workers> worker=k."""
    own = [a for a in argv if not a.startswith(("workers=", "worker="))]
    return [sys.executable, "-m", "experiments.study", *own, f"workers={workers}", f"worker={k}"]


def run_workers(argv: list[str], gpus: list[str]) -> None:
    """Start one study per GPU of `gpus` (worker k on gpus[k]), relay their output prefixed [w<k>] and wait for all
    of them."""
    workers = len(gpus)
    lock = threading.Lock()

    def relay(k: int, stream) -> None:
        for line in stream:
            with lock:
                print(f"[w{k}] {line}", end="", flush=True)

    procs, threads = [], []
    for k in range(workers):
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpus[k], "PYTHONUNBUFFERED": "1"}
        p = subprocess.Popen(worker_command(argv, workers, k), env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, bufsize=1)
        t = threading.Thread(target=relay, args=(k, p.stdout), daemon=True)
        t.start()
        procs.append(p)
        threads.append(t)
    try:
        codes = [p.wait() for p in procs]
    except KeyboardInterrupt:           # Ctrl-C reaches the workers too (one process group): let them checkpoint
        codes = [p.wait() for p in procs]
        raise
    finally:
        for t in threads:
            t.join(timeout=5)
    failed = [f"worker {k} (exit status {code})" for k, code in enumerate(codes) if code]
    if failed:
        raise ValueError(f"{', '.join(failed)} failed: see its [w<k>] lines above; rerun the same command to go on")
    print(f"[study] all {workers} workers ended", flush=True)


def batches(runs: list[StudyRun], side_by_side: bool) -> list[tuple[list[StudyRun], list[str]]]:
    """[(runs, experiments.run overrides)]: each group's seeds at the same checkpoint trained in one program."""
    out = []
    for group in dict.fromkeys(r.group for r in runs):
        members = [r for r in runs if r.group == group]
        if not side_by_side:
            out += [([r], r.overrides) for r in members]
            continue
        by_step: dict = {}
        for r in members:
            by_step.setdefault(RunDir(r.dir).latest_step(), []).append(r)
        for same in by_step.values():
            if len(same) == 1:
                out.append((same, same[0].overrides))
                continue
            first = same[0]
            template = str(first.dir)[: -len(f"-s{first.seed}")] + "-s{seed}"
            ov = [o for o in first.overrides if not o.startswith(("seed=", "run_dir="))]
            out.append((same, [*ov, f"seeds=[{','.join(str(r.seed) for r in same)}]", f'run_dir="{template}"']))
    return out


def run_study(c: StudyConfig, argv: Optional[list[str]] = None) -> None:
    if c.time_limit_min is not None and c.time_limit_min <= 0:
        raise ValueError(f"time_limit_min={c.time_limit_min}: expected a positive number of minutes or null")
    if (c.workers is not None and c.workers < 1) or (c.worker is not None and not (
            c.workers is not None and 0 <= c.worker < c.workers)):
        raise ValueError(f"workers={c.workers}, worker={c.worker}: expected workers >= 1 and worker in "
                         f"0..workers-1 (worker is set by the study for its own processes)")
    runs = plan(c)
    workers = c.workers if c.workers is not None else default_workers(c, runs)
    if c.worker is not None:
        runs = share(runs, workers, c.worker)
    configs = [compose_run_config(r.overrides) for r in runs]     # every run's config is checked before any runs
    if c.worker is None or c.dry_run:    # a worker's runs were listed by the study that started it
        for r in runs:
            print(f"python -m experiments.run {' '.join(r.overrides)}   # then evaluate {r.sets}")
    if workers > 1 and c.worker is None:
        if several_processes(c):
            raise ValueError("workers: runs of several processes (coordinator/num_processes/process_id) cannot be "
                             "spread over workers; use workers=1")
        gpus = worker_devices(workers)
        for k in range(workers):
            print(f"[study] worker {k} (CUDA_VISIBLE_DEVICES={gpus[k]}): "
                  + (", ".join(r.dir.name for r in share(runs, workers, k)) or "nothing to do"), flush=True)
        return None if c.dry_run else run_workers(list(argv or []), gpus)
    if c.dry_run:
        return
    checked = set()             # the evaluation sets exist for the runs' robots (before hours of training)
    for r, cfg in zip(runs, configs):
        key = (cfg.robots, cfg.robots_root, cfg.num_robots, tuple(r.sets))
        if key not in checked:
            checked.add(key)
            for name in r.sets:
                resolve_set(cfg, name)
    use_compile_cache(configs[0].compile_cache if configs else None)
    last = {r.dir: cfg.last_iteration() for r, cfg in zip(runs, configs)}
    deadline = None if c.time_limit_min is None else time.monotonic() + 60.0 * c.time_limit_min

    def unfinished(members: list[StudyRun]) -> list[str]:
        return [str(r.dir) for r in members if (RunDir(r.dir).latest_step() or 0) < last[r.dir]]

    def minutes_left() -> float:
        return math.inf if deadline is None else (deadline - time.monotonic()) / 60.0

    def sets_that_fit(members: list[StudyRun], train_left_s: float) -> list[str]:
        """The sets whose evaluation the time limit will leave time for once the training is done (what to prepare
        while it trains): the count after the training, below, with every set prepared."""
        jobs = [s for s in members[0].sets for _ in members]
        fit = evaluations_that_fit(jobs, minutes_left() - train_left_s / 60.0, jobs)
        return list(dict.fromkeys(jobs[i] for i in fit))

    told: set[str] = set()

    def stopped_unhealthy(members: list[StudyRun], overrides: list[str]) -> list[StudyRun]:
        """The runs of the batch that stopped because they start broken (`stop_unhealthy`, the loop's health check):
        they are neither trained further nor evaluated (each named once per invocation); the others go on."""
        if not compose_run_config(overrides).stop_unhealthy:
            return []
        sick = [(r, why) for r in members if (why := unhealthy_reason(r.dir))]
        for r, why in sick:
            if str(r.dir) not in told:
                told.add(str(r.dir))
                print(f"[study] {r.dir}: stopped, it starts broken ({why}); not trained further nor evaluated "
                      "(-- stop_unhealthy=false trains it on)", flush=True)
        return [r for r, _ in sick]

    todo = batches(runs, c.side_by_side)
    for i, (members, overrides) in enumerate(todo):
        print(f"[study] {i + 1}/{len(todo)}: {', '.join(str(r.dir) for r in members)}", flush=True)
        prep = None
        sick = stopped_unhealthy(members, overrides)
        if len(sick) == len(members):
            continue
        if unfinished(members):
            left = minutes_left()
            if left < MIN_TRAIN_MIN:
                print(f"[study] time limit: {left:.1f} min left; rerun the same command to go on", flush=True)
                return
            run_cfg = compose_run_config(overrides if deadline is None else [*overrides, f"time_limit_min={left:.2f}"])
            callbacks = None
            if c.prepare_eval and members[0].sets:
                prep = PrepareEvaluation(lambda train_left_s, m=members: sets_that_fit(m, train_left_s),
                                         episodes=c.episodes, log=functools.partial(print, flush=True))
                callbacks = [*default_callbacks(to_schema(run_cfg)), prep]
            train(run_cfg, callbacks=callbacks)
            sick = stopped_unhealthy(members, overrides)
            if len(sick) == len(members):
                wait_for_preparation(functools.partial(print, flush=True))
                continue
            short = unfinished([r for r in members if r not in sick])
            if short:                        # the time limit ended the training: a rerun resumes it
                print(f"[study] not finished: {', '.join(short)}; rerun the same command to go on", flush=True)
                return
        members = [r for r in members if r not in sick]
        # with a time limit, the (set, run) evaluations that fit, the study file's sets in order (each over the
        # batch's seeds; one that does not fit gives way to shorter ones after it), counting only those not yet
        # evaluated at the run's last checkpoint. Every process takes the same decision: whether a set is done is read
        # on the main process (the others may not see eval/) and agreed.
        # the sets whose preparation has ended count at their prepared time; the one still being prepared at its
        # unprepared time less what its preparation has run, a bound on what is left of it (evaluate_run waits for
        # each set's own preparation alone: session 28's runs waited 43-53 s for the variants' before test70,
        # prepared, could sweep)
        prepared = list(prep.prepared) if prep is not None else []
        preparing = prep.preparing() if prep is not None else {}
        steps = [RunDir(r.dir).latest_step() for r in members]        # what evaluate_run evaluates
        jobs, done = [], []
        for s in members[0].sets:
            for r, step in zip(members, steps):
                (done if distributed.agree(evaluated(r.dir, s, step, c.episodes)) else jobs).append((s, r))
        for r, step in zip(members, steps):
            if any(q is r for _, q in done):
                distributed.print_main(f"[study] {r.dir}: {', '.join(s for s, q in done if q is r)} already "
                                       f"evaluated at checkpoint {step}", flush=True)
        fit = evaluations_that_fit([s for s, _ in jobs], minutes_left(), prepared, preparing)
        if jobs and not fit:
            print(f"[study] time limit: evaluation of {', '.join(str(r.dir) for r in members)} left for the rerun",
                  flush=True)
            return
        if distributed.is_main():
            for r in members:                           # one evaluate_run (one checkpoint load) per run
                sets = [jobs[i][0] for i in fit if jobs[i][1] is r]
                if sets:
                    evaluate_run(r.dir, sets, episodes=c.episodes)
        wait_for_preparation(functools.partial(print, flush=True))     # one of a set not evaluated ends here
        distributed.barrier("evaluated")
        if len(fit) < len(jobs):
            taken = set(fit)
            left = ", ".join(f"{r.dir}: {s}" for i, (s, r) in enumerate(jobs) if i not in taken)
            print(f"[study] time limit: evaluation of {left} left for the rerun", flush=True)
            return
    print(f"[study] done; report: python -m experiments.report runs=[{Path(c.out) / c.name}] out=<dir>")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" in argv:                    # everything after -- is passed to every run
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
        argv.append("run=[" + ",".join(f"'{x}'" for x in extra) + "]")
    # seeds_of.<arch>=[...] and stop_at_of.<arch>=N add a key to a dict that starts empty: Hydra's `+` (the short
    # form is what users type)
    argv = [f"+{a}" if a.startswith(("seeds_of.", "stop_at_of.")) else a for a in argv]
    try:
        argv = study_for_task(argv)
    except ValueError as e:
        return cli.fail(e)
    return cli.main(lambda c: run_study(c, argv), "run_study", StudyConfig, __doc__, argv, positional="name")


if __name__ == "__main__":
    sys.exit(main())
