"""Evaluate a trained run on robot sets and write per-robot results into its run directory.

    evaluate_run("runs/ft-rmomo-s0", sets=("train", "test", "variants"), episodes=4)

writes, per set, `<run_dir>/eval/<tag>.csv` (one row per episode) and `<run_dir>/eval/<tag>.json` (summary: mean
return and normalised return with 95% confidence intervals over robots, per-robot means, per change type for
variants, fall/timeout/instability counts, the reward per timestep of the first steps, and the same with the
recurrent state held at zero for the first `zero_state_steps` steps for recurrent models, on the sets tagged in
`zero_state_sets`: by default the test set alone, which is all the report reads it from, so that train and val cost one
sweep, not two), and the env's `model_digest` (the physics it simulated, `UnimalEnv.digest`). `train_seed` is the
run's training seed, `eval_seed` the seed of the evaluation episodes' start states (files written before session 10
have only `seed`, which was the evaluation seed).

Set names: `train` (the robots the run trained on, `num_robots` included), `test` and `val` (the held-out robots
of the run's robot family: `unimal100/test70` / `unimal100/val` for the original robots, `gen/test` for the
generated ones), `variants` (the 24 dynamics/kinematics variants of each train robot, one sweep, summarised per change
type too; `variants/<change>`: one change type),
or any set name or path that `load_set` knows (tag: the name with "/" replaced by "_"); `<tag>:<set>` evaluates
a set under another label (e.g. `test:path/to/robots`, so that reports treat it as the test set).

Normalised return (the paper's per-task range over robots, `stats.normalised`): (R - min) / (max - min) with ft
52/5008, incline -74/3751, csr 71/3000, obstacle 126/2403.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Sequence

import jax
import numpy as np

from ..run import FAST_COMPILE, Callback, RunConfig, load_run, make_env_for, to_dict, train_robots
from ..run.run_dir import at_float32
from ..sim.processes import lower_thread_priority
from ..unimal.morphology import Morphology
from ..unimal.sets import load_set
from ..unimal.variants import CHANGE_TYPES, variant_change
from .stats import ci95, normalised
from .sweep import Sweeper, SweepResult



@dataclasses.dataclass
class EvalSet:
    tag: str                                  # file stem under <run_dir>/eval
    name: str                                 # robot set name
    robots: tuple[Morphology, ...]
    groups: dict[str, list[int]] | None = None  # variants: change type -> robot indices


#: Sweepers (a set's env and its compiled sweep) kept across evaluate_run calls of one process, keyed by what the
#: sweep's program depends on: the seeds of a study's run share robots and model, so only the first compiles.
_SWEEPERS: OrderedDict[str, Sweeper] = OrderedDict()
_SWEEPERS_LOCK = threading.Lock()
SWEEPERS_KEPT = 4
_PREPARING: threading.Thread | None = None    # the background preparation of PrepareEvaluation, if one was started
_PENDING: dict[str, threading.Event] = {}     # ... and the sets (tags) it has yet to finish, each set when it ends
PREPARE_LEAD_S = 240.0      # PrepareEvaluation starts when about this much training is left (4 min: the variants'
                            # env build and compilation take ~1.5 min on an H100 host)
TRACE_STEPS = 500           # steps of the reward-per-timestep trace


class PreparedShapes(NamedTuple):
    params: object
    obs_rms: object


def set_tag(name: str) -> str:
    """The file stem under <run_dir>/eval that set `name` is written to (resolve_set's EvalSet.tag)."""
    return name.partition(":")[0] if ":" in name else name.replace("/", "_")


def evaluated(run_dir: str | Path, name: str, step: int, episodes: int) -> bool:
    """Whether <run_dir>/eval holds set `name` evaluated at checkpoint `step` with `episodes` episodes per robot."""
    f = Path(run_dir) / "eval" / f"{set_tag(name)}.json"
    try:
        s = json.loads(f.read_text())
    except (OSError, ValueError):
        return False
    return s.get("checkpoint") == step and s.get("episodes") == episodes


def resolve_set(cfg: RunConfig, name: str) -> EvalSet:
    """A set name of `experiments.evaluate` (a shortcut or any `load_set` name) -> the robots to evaluate."""
    if ":" in name:                                   # "<tag>:<set>": a set evaluated under another label
        tag, _, inner = name.partition(":")
        return dataclasses.replace(resolve_set(cfg, inner), tag=tag)
    root, outside = cfg.robots_root, cfg.allow_outside_design_space
    train_name, trained = train_robots(cfg)
    family = train_name.split("/")[0] if train_name.split("/")[0] in ("unimal100", "gen") else None
    if name == "train":
        return EvalSet("train", train_name, trained)
    if name in ("test", "val"):
        if family == "unimal100":
            full = "unimal100/test70" if name == "test" else "unimal100/val"
        elif family == "gen" and name == "test":
            full = "gen/test"
        else:
            raise ValueError(f"robots={name}: the run trained on {train_name!r}, which has no {name} set; "
                             f"name one explicitly (e.g. robots=[unimal100/test70])")
        return EvalSet(name, full, load_set(full, root, allow_outside_design_space=outside).robots)
    head, _, change = name.partition("/variants")
    if name.startswith("variants") or "/variants" in name:
        if name.startswith("variants"):                  # variants[/<change>] of the robots the run trained on
            base_name, change, keep = train_name, name[len("variants"):], {m.name for m in trained}
        else:                                            # <set>/variants[/<change>]: of a whole set
            base_name, keep = head, None
        change = change.strip("/")
        full = f"{base_name}/variants" + (f"/{change}" if change else "")
        robots = [m for m in load_set(full, root, allow_outside_design_space=outside).robots
                  if keep is None or variant_change(m.name)[0] in keep]
        groups = {c: [i for i, m in enumerate(robots) if variant_change(m.name)[1] == c] for c in CHANGE_TYPES}
        return EvalSet(set_tag(name), full, tuple(robots), {c: g for c, g in groups.items() if g})
    rs = load_set(name, root, allow_outside_design_space=outside)
    return EvalSet(set_tag(name), name, rs.robots)


def _per_robot(res: SweepResult, robot_of: np.ndarray, names: Sequence[str]) -> dict[str, float]:
    """Mean return of each robot that has episodes in `res`."""
    return {nm: float(res.ret[robot_of == i].mean()) for i, nm in enumerate(names) if (robot_of == i).any()}


def _summary(res: SweepResult, per_robot: dict[str, float], task: str) -> dict:
    means = np.array(list(per_robot.values()))
    norm = normalised(means, task)
    return {"robots": len(per_robot), "episodes_total": int(res.ret.size),
            "mean_return": float(means.mean()), "ci95_return": ci95(means),
            "mean_normalised": float(norm.mean()), "ci95_normalised": ci95(norm),
            "mean_length": float(res.length.mean()), "fall_fraction": float(res.fell.mean()),
            "out_of_bounds_fraction": float(res.out_of_bounds.mean()), "timeout_fraction": float(res.timeout.mean()),
            "instabilities": int(res.unstable.sum())}


def _select(res: SweepResult, mask: np.ndarray) -> SweepResult:
    """The episodes of `res` where `mask` (N,) is true."""
    return SweepResult(*[x[..., mask] for x in res])


def evaluate_run(run_dir: str | Path, sets: Iterable[str | EvalSet] = ("train", "test", "variants"), episodes: int = 4,
                 seed: int = 0, zero_state_steps: int = 100, zero_state_sets: Sequence[str] = ("test",),
                 step: int | None = None, max_envs: int | None = None,
                 episode_length: int | None = None, trace_steps: int = TRACE_STEPS,
                 log: Callable[[str], None] = print) -> dict[str, dict]:
    """Evaluate the run's checkpoint `step` (default: newest) on each set; returns {tag: summary} and writes the
    files described in the module docstring."""
    for key, value, least in (("episodes", episodes, 1), ("zero_state_steps", zero_state_steps, 0),
                              ("trace_steps", trace_steps, 0), ("max_envs", max_envs, 1),
                              ("episode_length", episode_length, 1)):
        if value is not None and value < least:
            raise ValueError(f"{key}={value}: expected {'a positive number' if least else '0 or more'}")
    run_dir = Path(run_dir)
    loaded = load_run(run_dir, step)
    cfg, model, trainer, ts, step = loaded.config, loaded.experiment.model, loaded.experiment.trainer, \
        loaded.state, loaded.step
    task = cfg.env.task
    env_over = {"episode_length": int(episode_length)} if episode_length else {}
    # every set is resolved (names checked, robots read) before anything is written; an EvalSet is taken as it is
    eval_sets = [name if isinstance(name, EvalSet) else resolve_set(cfg, name) for name in sets]
    out_dir = run_dir / "eval"
    out_dir.mkdir(exist_ok=True)
    env_steps = step * trainer.cfg.steps_per_iter
    summaries = {}
    meter = _Meter(log)
    ahead: threading.Thread | None = None
    for i, es in enumerate(eval_sets):
        t0 = time.perf_counter()
        names = [m.name for m in es.robots]
        if ahead is not None:
            ahead.join()                                  # the set prepared while the last one ran
        _await_pending(es.tag, log)                       # ... or while the run trained: this set's preparation alone
        sweeper = _sweeper_for(cfg, model, es, env_over, trace_steps, log)
        # the next set's env build and compilation run on the host while this set's sweeps run on the device (a
        # set not yet kept: session 27's variants built their env for ~60 s after test70's sweep)
        ahead = None
        if i + 1 < len(eval_sets) and not _kept(cfg, eval_sets[i + 1], env_over, trace_steps) \
                and not _is_pending(eval_sets[i + 1].tag):
            ahead = threading.Thread(target=_prepare_set, name="prepare-next-set", daemon=True,
                                     args=(cfg, model, ts, eval_sets[i + 1], episodes, env_over, trace_steps,
                                           max_envs, log, f"{es.tag}'s sweeps ran"))
            ahead.start()
        robot_of = np.repeat(np.arange(len(names), dtype=np.int32), episodes)
        episode_of = np.tile(np.arange(episodes, dtype=np.int32), len(names))
        chunk = _chunk(len(robot_of), max_envs)
        compiling = not sweeper.compiled(chunk)
        zero_sweep = es.groups is None and model.recurrent and zero_state_steps > 0 and es.tag in zero_state_sets
        sweeps = 1 + int(zero_sweep)
        meter.start(es.tag, len(names) * episodes * sweeps, sweeper.steps, chunk, compiling)
        res = sweeper(ts.params, ts.obs_rms, robot_of, episode_of, seed=seed, max_envs=chunk, progress=meter.chunk)
        per_robot = _per_robot(res, robot_of, names)
        per_change = {change: _summary(_select(res, np.isin(robot_of, idx)),
                                       {names[i]: per_robot[names[i]] for i in idx}, task)
                      for change, idx in (es.groups or {}).items()}
        summary = {"run_dir": str(run_dir), "arch": model.arch, "task": task, "set": es.name, "tag": es.tag,
                   "checkpoint": step, "env_steps": env_steps, "episodes": episodes,
                   "train_seed": cfg.seed, "eval_seed": seed,
                   "episode_length": sweeper.env.config.episode_length, "model_digest": sweeper.env.digest,
                   **_summary(res, per_robot, task),
                   **({"per_change": per_change} if per_change else {}), "per_robot": per_robot}
        summary["reward_trace"] = res.reward.mean(axis=1).tolist()
        summary["alive_trace"] = (np.arange(res.reward.shape[0])[:, None] < res.length[None, :]).mean(axis=1).tolist()
        if zero_sweep:
            z = sweeper(ts.params, ts.obs_rms, robot_of, episode_of, seed=seed, zero_state_steps=zero_state_steps,
                        max_envs=chunk, progress=meter.chunk)
            summary["zero_state_steps"] = int(zero_state_steps)
            summary["reward_trace_zero_state"] = z.reward.mean(axis=1).tolist()
            summary["mean_return_zero_state"] = float(z.ret.mean())
        summary = at_float32(summary)               # what eval/<tag>.json holds, returned as written
        _write(out_dir, es, res, robot_of, episode_of, summary, task)
        summaries[es.tag] = summary
        extra = "".join(f"; {c} {s['mean_return']:.1f}" for c, s in summary.get("per_change", {}).items())
        log(f"[mjx_morph] {es.tag} ({es.name}, {len(names)} robots x {episodes} episodes): mean return "
            f"{summary['mean_return']:.1f} ± {summary['ci95_return']:.1f}, normalised {summary['mean_normalised']:.3f}"
            f"{extra} ({time.perf_counter() - t0:.0f} s)")
    return summaries


CPU_CHUNK = 64     # episodes per jitted sweep call on a CPU (progress every few minutes instead of none for hours)
MAX_CHUNK = 5000   # ... and on an accelerator (bounds the memory of one call)


def _sweeper_for(cfg: RunConfig, model, es: EvalSet, env_over: dict, trace_steps: int,
                 log: Callable[[str], None]) -> Sweeper:
    """The sweeper of set `es` (its env and sweep program): one kept from an earlier evaluation or preparation in
    this process when the program would be the same (the same robots under another label, another seed of the same
    model), else a new one, its env built here."""
    key = _sweeper_key(cfg, es, env_over, trace_steps)
    with _SWEEPERS_LOCK:
        sweeper = _SWEEPERS.pop(key, None)
    if sweeper is None:
        t0 = time.perf_counter()
        log(f"[mjx_morph] {es.tag}: building the env of {len(es.robots)} robots ({es.name})")
        env = make_env_for(cfg, es.robots, **env_over)
        sm = getattr(env, "sm", None)
        pairs = getattr(sm, "self_contact", None)
        phases = sm.build_line() if sm is not None else ""
        log(f"[mjx_morph] {es.tag}: env built in {time.perf_counter() - t0:.0f} s"
            + (f" ({phases})" if phases else "") + (f"; {pairs.line()}" if pairs is not None else ""))
        sweeper = Sweeper(env, model, trace_steps, compiler_options=FAST_COMPILE if cfg.fast_compile else None)
    elif sweeper.prepared:
        log(f"[mjx_morph] {es.tag}: env and sweep prepared while {sweeper.prepared}")
        sweeper.prepared = ""
    with _SWEEPERS_LOCK:
        _SWEEPERS[key] = sweeper                          # the most recently used last
        while len(_SWEEPERS) > SWEEPERS_KEPT:
            _SWEEPERS.popitem(last=False)
    return sweeper


def _sweeper_key(cfg: RunConfig, es: EvalSet, env_over: dict, trace_steps: int) -> str:
    """What a set's sweep program depends on (`_SWEEPERS`' key)."""
    return repr((to_dict(cfg.env), cfg.arch, to_dict(cfg.model), cfg.precision, cfg.fast_compile, cfg.robots_root,
                 cfg.allow_outside_design_space, tuple(m.name for m in es.robots), sorted(env_over.items()),
                 trace_steps))


def _kept(cfg: RunConfig, es: EvalSet, env_over: dict, trace_steps: int) -> bool:
    """Whether this process keeps a sweeper for set `es` (one evaluated or prepared before)."""
    with _SWEEPERS_LOCK:
        return _sweeper_key(cfg, es, env_over, trace_steps) in _SWEEPERS


def _chunk(episodes: int, max_envs: int | None) -> int:
    """Episodes per jitted sweep call. All of a set's episodes in one sweep, each change type's summary read off it
    (the variants' 9600 episodes in 2 chunks of 4800 envs fill a GPU that one change type's 1600 would not); on a CPU
    at most CPU_CHUNK episodes per call, so that progress shows."""
    most = CPU_CHUNK if jax.default_backend() == "cpu" else MAX_CHUNK
    return max_envs or -(-episodes // -(-episodes // most))     # equal chunks of at most `most`


def prepare_evaluation(cfg: RunConfig, model, like, sets: Sequence[str], episodes: int = 4,
                       episode_length: int | None = None, trace_steps: int = TRACE_STEPS,
                       log: Callable[[str], None] = print,
                       on_start: Callable[[str], None] | None = None,
                       on_set: Callable[[str, bool], None] | None = None) -> list[str]:
    """Build the envs of `sets` and compile their sweeps ahead of an `evaluate_run` with the same `episodes`,
    `episode_length` and `trace_steps` (and no `max_envs`), for a train state shaped like `like` (`.params` and
    `.obs_rms`: arrays or jax.ShapeDtypeStruct). Meant for a background thread while the run trains
    (`PrepareEvaluation`); the sweepers are kept for the evaluate_run of this process, which waits for each set's
    preparation to end before it evaluates the set (`start_preparation`), not for the others. Errors are logged,
    never raised: evaluate_run then does the work itself. `on_start(name)` is called as each set's preparation
    starts, `on_set(name, ok)` as it ends (the sets one after the other). Returns the sets prepared."""
    env_over = {"episode_length": int(episode_length)} if episode_length else {}
    done = []
    for name in sets:
        if on_start is not None:
            on_start(name)
        try:
            es = resolve_set(cfg, name)
        except Exception as e:             # noqa: BLE001 - the training goes on; evaluate_run redoes this set
            log(f"[mjx_morph] {name}: preparing the evaluation failed ({type(e).__name__}: {e}); it is built when "
                "the evaluation starts")
            ok = False
        else:
            ok = _prepare_set(cfg, model, like, es, episodes, env_over, trace_steps, None, log, "the run trained")
        if ok:
            done.append(name)
        if on_set is not None:
            on_set(name, ok)
        _end_pending(name)                 # its evaluation may start (start_preparation ends the rest at the end)
    return done


def start_preparation(cfg: RunConfig, model, like, sets: Sequence[str], episodes: int = 4,
                      log: Callable[[str], None] = print, target: Callable | None = None) -> threading.Thread:
    """Run `prepare_evaluation` (or `target`, which calls it with the same arguments) in a background thread, the
    sets marked pending first, so that an evaluate_run started at any time after this returns waits for a set's
    preparation before it evaluates that set, and for no other."""
    global _PREPARING
    sets = list(sets)
    with _SWEEPERS_LOCK:
        for name in sets:
            _PENDING[set_tag(name)] = threading.Event()

    def run():
        try:
            (target or prepare_evaluation)(cfg, model, like, sets, episodes, log=log)
        finally:                    # whatever `target` does, no evaluation waits for a set that is not coming
            for name in sets:
                _end_pending(name)
    _PREPARING = threading.Thread(target=run, name="prepare-evaluation", daemon=True)
    _PREPARING.start()
    return _PREPARING


def _end_pending(name: str) -> None:
    with _SWEEPERS_LOCK:
        event = _PENDING.pop(set_tag(name), None)
    if event is not None:
        event.set()


def _is_pending(tag: str) -> bool:
    with _SWEEPERS_LOCK:
        return tag in _PENDING


def _await_pending(tag: str, log: Callable[[str], None]) -> None:
    """Wait until the training-time preparation of set `tag` has ended, if one is under way."""
    with _SWEEPERS_LOCK:
        event = _PENDING.get(tag)
    if event is not None and not event.is_set():
        t0 = time.perf_counter()
        log(f"[mjx_morph] {tag}: waiting for its evaluation being prepared...")
        event.wait()
        log(f"[mjx_morph] {tag}: ... ready after {time.perf_counter() - t0:.0f} s")


def _prepare_set(cfg: RunConfig, model, like, es: EvalSet, episodes: int, env_over: dict, trace_steps: int,
                 max_envs: int | None, log: Callable[[str], None], during: str) -> bool:
    """Build set `es`'s env and compile its sweep for a train state shaped like `like`, and keep the sweeper for the
    evaluation of this process (`_sweeper_for`); `during` says what ran meanwhile ("the run trained"), for the logs.
    False, logged, on an error: the evaluation then builds the set itself."""
    try:
        t0 = time.perf_counter()
        sweeper = _sweeper_for(cfg, model, es, env_over, trace_steps, log)
        sweeper.precompile(like.params, like.obs_rms, _chunk(len(es.robots) * episodes, max_envs))
        sweeper.prepared = during
        log(f"[mjx_morph] {es.tag}: evaluation prepared while {during} ({time.perf_counter() - t0:.0f} s)")
        return True
    except Exception as e:                 # noqa: BLE001 - what runs meanwhile goes on
        log(f"[mjx_morph] {es.tag}: preparing the evaluation failed ({type(e).__name__}: {e}); it is built when "
            "the evaluation starts")
        return False


def wait_for_preparation(log: Callable[[str], None] = print) -> None:
    """Wait until the preparation that a PrepareEvaluation started (if any) has ended, all of its sets."""
    global _PREPARING
    thread, _PREPARING = _PREPARING, None
    if thread is not None and thread.is_alive():
        t0 = time.perf_counter()
        log("[mjx_morph] waiting for the evaluation being prepared...")
        thread.join()
        log(f"[mjx_morph] ... ready after {time.perf_counter() - t0:.0f} s")


class PrepareEvaluation(Callback):
    """Prepares the evaluation (`prepare_evaluation`) in a background thread once the run's training is estimated
    to end within `lead_s` seconds (iterations left x the median of the last iterations' wall time), so that the
    evaluation after training starts at once: the env build and compilation (on an H100 host ~1.5 minutes of the
    variants' ~5, most of test70's ~1.25) run on the host's CPU while the GPU trains. `sets(seconds)` names the sets
    to prepare given the seconds of training estimated left (a study: those its time limit will let it evaluate);
    nothing is prepared while it names none. One process only (evaluation runs on one). `prepared` names the sets
    prepared so far (each added as its preparation ends; all of them after `wait_for_preparation`)."""

    def __init__(self, sets: Callable[[float], Sequence[str]], episodes: int = 4, lead_s: float = PREPARE_LEAD_S,
                 log: Callable[[str], None] = print):
        self.sets, self.episodes, self.lead_s, self.log = sets, episodes, lead_s, log
        self.walls: list[float] = []
        self.started = False
        self.prepared: list[str] = []        # the sets prepared, once the preparation has ended
        self._current: tuple[str, float] | None = None     # the set being prepared now, since when (monotonic)

    def _prepare(self, cfg, model, like, names, episodes, log) -> None:
        # below the training's priority: session 22 measured the training's iterations 15-24 s slower in all while
        # four runs on one host prepared the variants at the training's priority
        lower_thread_priority()

        def on_start(name: str) -> None:
            self._current = (name, time.monotonic())

        def on_set(name: str, ok: bool) -> None:
            self._current = None
            if ok:
                self.prepared.append(name)
        try:
            prepare_evaluation(cfg, model, like, names, episodes, log=log, on_start=on_start, on_set=on_set)
        finally:
            self._current = None

    def preparing(self) -> dict[str, float]:
        """{set: seconds its preparation has run} for the set being prepared now ({} when none is)."""
        current = self._current
        return {} if current is None else {current[0]: time.monotonic() - current[1]}

    def on_iteration(self, loop, state, row):
        it = int(row["iteration"])
        if self.started or loop.member != 0 or jax.process_count() > 1:
            return
        if it > loop.start + 1:                  # an invocation's first iteration compiles
            self.walls.append(float(row["wall_s"]))
        if len(self.walls) < 3:
            return
        left_s = (loop.stop - it) * float(np.median(self.walls[-10:]))
        if left_s > self.lead_s:
            return
        names = list(self.sets(left_s))
        if not names:
            return
        own = loop.own(state)
        # shapes and dtypes alone: the next iteration donates these arrays, and their placement (several devices
        # while training) is not the evaluation's (one)
        like = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=x.weak_type),
                            jax.eval_shape(lambda p, o: PreparedShapes(p, o), own.params, own.obs_rms))
        self.started = True
        self.log(f"[mjx_morph] preparing the evaluation of {', '.join(names)} while training (about "
                 f"{left_s:.0f} s of training left)")
        start_preparation(loop.config, loop.experiment.model, like, names, self.episodes, log=self.log,
                          target=self._prepare)


class _Meter:
    """Progress of a set's sweeps: its size before it starts, then after each chunk the env steps/s and the time
    left (the first chunk of a new program includes its compilation, so later chunks set the estimate)."""

    def __init__(self, log: Callable[[str], None]):
        self.log, self.rate = log, None           # env steps/s of compiled chunks, kept across sets

    def start(self, tag: str, episodes: int, steps: int, chunk: int, compiling: bool) -> None:
        self.tag, self.total, self.done, self.compiling = tag, episodes * steps, 0, compiling
        est = f"; about {_duration(self.total / self.rate)} at {self.rate:,.0f} env steps/s" if self.rate else ""
        est += "; the first chunk includes compilation" if compiling else ""
        self.log(f"[mjx_morph] {tag}: {episodes} episodes x {steps} steps = {self.total:,} env steps in chunks of "
                 f"{chunk} episodes{est}")

    def chunk(self, index: int, count: int, episodes: int, steps: int, seconds: float) -> None:
        work = episodes * steps
        self.done += work
        compiled_here, self.compiling = self.compiling, False
        if not compiled_here:
            self.rate = work / seconds
        left = f", about {_duration((self.total - self.done) / self.rate)} left" if self.rate else ""
        self.log(f"[mjx_morph]   {self.tag}: {self.done:,}/{self.total:,} env steps ({work / seconds:,.0f}/s"
                 f"{', compilation included' if compiled_here else ''}){left}")


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def _write(out_dir: Path, es: EvalSet, res: SweepResult, robot_of: np.ndarray, episode_of: np.ndarray,
           summary: dict, task: str) -> None:
    norm = normalised(res.ret, task)
    with (out_dir / f"{es.tag}.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["robot", "base", "change", "episode", "return", "normalised", "length", "fell", "out_of_bounds",
                    "timeout", "unstable"])
        for i, r in enumerate(robot_of):
            name = es.robots[int(r)].name
            base, change = (variant_change(name)[:2] if es.groups else (name, ""))
            w.writerow([name, base, change, int(episode_of[i]), f"{res.ret[i]:.4f}", f"{norm[i]:.5f}",
                        int(res.length[i]), int(res.fell[i]), int(res.out_of_bounds[i]), int(res.timeout[i]),
                        int(res.unstable[i])])
    (out_dir / f"{es.tag}.json").write_text(json.dumps(summary, indent=1))
