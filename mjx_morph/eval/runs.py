"""Finished run directories: finding them and reading what they hold.

    dirs = find_run_dirs(["runs/studies/train_size"])       # run directories at or below the given paths
    runs = [read_run(d) for d in dirs]                      # config.yaml, metrics.csv, eval/<tag>.json, devices.yaml
    classify(runs)                                          # run.kind: main | size | context | other
    name_variants(runs)                                     # run.name: arch, plus the settings that tell apart
                                                            # runs of one task and arch (an A/B study's arms)

Per run directory (read only): `config.yaml` (required), `metrics.csv` of `mjx_morph.ppo.loop`, `eval/<tag>.json`
of `mjx_morph.eval.evaluate`, `devices.yaml` (the devices of each invocation; absent in older runs) and `physics.yaml`
(a run's physics computed afterwards, `experiments.digest`); problems with the optional files are kept in
`Run.notes` rather than raised.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import yaml

from ..layout import CONTEXT_GROUPS as _GROUPS
from ..run.run_dir import flatten_config, invoked_values, matches_key, read_computed_physics, read_invocations

CONTEXT_GROUPS: tuple[str, ...] = tuple(_GROUPS)     # in column order: the order of the groups in figures


class NotARunDir(ValueError):
    def __init__(self, path):
        super().__init__(f"{path}: not a run directory (no config.yaml)")
        self.path = path


def find_run_dirs(paths: Iterable[str | Path]) -> list[Path]:
    """Run directories (with config.yaml) among `paths`; a directory without config.yaml is searched for run
    directories below it. Raises NotARunDir for a path that is neither."""
    found: list[Path] = []
    for p in paths:
        p = Path(p)
        if (p / "config.yaml").is_file():
            found.append(p)
            continue
        below: list[Path] = []
        if p.is_dir():
            for dirpath, dirnames, files in os.walk(p):
                if "config.yaml" in files and Path(dirpath) != p:
                    below.append(Path(dirpath))
                    dirnames[:] = []
                    continue
                dirnames[:] = sorted(d for d in dirnames
                                     if not d.startswith(".") and d not in ("checkpoints", "tb", "eval"))
        if not below:
            raise NotARunDir(p)
        found.extend(sorted(below))
    seen, out = set(), []
    for p in found:
        key = p.resolve()
        if key not in seen:
            seen.add(key)
            out.append(p)
    return out


@dataclass
class Manifest:
    """A list of runs kept as data (`results/claims.yaml`): the runs a report pools, the looks its claims have had,
    the runs that wait for the next look, and those on file but left out, each with why (`read_manifest`)."""
    path: Path
    runs: list[Path]                       # the run directories the report pools
    looks: Any                             # the report's `looks`: an int or {<model> | <task>/<model>: k}
    pending: list[Path]                    # on file, pooled only from the next look on
    excluded: dict[Path, str]              # on file, never pooled: run directory -> why


MANIFEST_KEYS = ("looks", "runs", "pending", "excluded")


def read_manifest(path: str | Path) -> Manifest:
    """Read a manifest: YAML with `runs` and `pending` (lists of globs of run directories, or folders holding them,
    relative to the manifest's folder; one of them not empty), `looks` (as the report's `looks=`) and `excluded`
    ({glob: why}). Every entry must match something, and no run may be reached twice (by two entries or two lists):
    a seed pooled twice, or pooled and excluded, is an error naming the file, the entry and the run."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such manifest")
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping with keys {', '.join(MANIFEST_KEYS)}")
    unknown = sorted(set(data) - set(MANIFEST_KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {', '.join(unknown)} (expected {', '.join(MANIFEST_KEYS)})")
    base, owner = path.parent, {}

    def expand(key: str, entries, indexed: bool = True) -> list[Path]:
        out = []
        for i, entry in enumerate(entries):
            label = f"{key}[{i}] {entry!r}" if indexed else f"{key} {entry!r}"
            where = f"{path}: {label}"
            if not isinstance(entry, str) or not entry:
                raise ValueError(f"{where}: expected a glob of run directories relative to {base}")
            matches = sorted(base.glob(entry))
            try:
                dirs = find_run_dirs(matches) if matches else []
            except NotARunDir as e:
                raise ValueError(f"{where}: {e}") from None
            if not dirs:
                raise ValueError(f"{where}: matches no run directory below {base}")
            for d in dirs:
                if d.resolve() in owner:
                    raise ValueError(f"{where}: {d} is already reached by {owner[d.resolve()]}")
                owner[d.resolve()] = label
                out.append(d)
        return out

    def listed(key: str) -> list:
        v = data.get(key) or []
        if not isinstance(v, list):
            raise ValueError(f"{path}: {key}: expected a list of globs, got {type(v).__name__}")
        return v

    excluded_raw = data.get("excluded") or {}
    if not isinstance(excluded_raw, dict):
        raise ValueError(f"{path}: excluded: expected a mapping {{glob: why}}, got {type(excluded_raw).__name__}")
    excluded = {}
    for entry, why in excluded_raw.items():
        if not isinstance(why, str) or not why.strip():
            raise ValueError(f"{path}: excluded {entry!r}: say why it is left out")
        excluded.update({d: why for d in expand("excluded", [entry], indexed=False)})
    runs, pending = expand("runs", listed("runs")), expand("pending", listed("pending"))
    if not runs and not pending:        # pending alone: runs trained before a design's first look
        raise ValueError(f"{path}: runs: expected at least one run, pooled (runs) or waiting for a look (pending)")
    return Manifest(path, runs, data.get("looks", 1), pending, excluded)


def _float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def read_metrics(path: Path) -> dict[str, np.ndarray]:
    """Columns of metrics.csv as float arrays (empty dict when the file is missing or has no rows)."""
    f = path / "metrics.csv"
    if not f.exists():
        return {}
    with f.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    cols = list(rows[0].keys())
    return {c: np.array([_float(r.get(c)) for r in rows]) for c in cols if c is not None}


@dataclass
class Run:
    path: Path
    cfg: dict
    metrics: dict[str, np.ndarray] = field(default_factory=dict)
    evals: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)      # problems reading this run
    invocations: list[dict] = field(default_factory=list)   # devices.yaml: one entry per start or resume
    physics_computed: str | None = None                 # physics.yaml's digest: computed afterwards, for a run that
                                                        # recorded none (`experiments.digest`)
    kind: str = "main"                                  # main | size | context | other: see classify()
    variant: str = ""                                   # what sets this run apart from others of its task and
                                                        # arch (name_variants), e.g. "scale_after_cell=true"

    @property
    def name(self) -> str:
        """The group the report pools seeds over: the architecture, plus its variant if any."""
        return f"{self.arch}, {self.variant}" if self.variant else self.arch

    @property
    def task(self) -> str:
        return str((self.cfg.get("env") or {}).get("task", "?"))

    @property
    def arch(self) -> str:
        return str(self.cfg.get("arch", "?"))

    @property
    def seed(self):
        return self.cfg.get("seed")

    @property
    def num_robots(self) -> int | None:
        v = self.cfg.get("num_robots")
        return int(v) if v else None

    @property
    def context(self) -> tuple[str, ...] | None:
        """Kept context feature groups (None: all)."""
        v = (self.cfg.get("env") or {}).get("context_features")
        if v is None:
            return None
        v = [v] if isinstance(v, str) else list(v)
        if set(CONTEXT_GROUPS) <= set(v):
            return None
        order = {g: i for i, g in enumerate(CONTEXT_GROUPS)}
        return tuple(sorted(v, key=lambda g: (order.get(g, len(order)), g)))

    @property
    def context_label(self) -> str:
        return "all" if self.context is None else ("+".join(self.context) or "none")

    @property
    def train_size(self) -> int:
        if self.num_robots:
            return self.num_robots
        n = (self.evals.get("train") or {}).get("robots")
        return int(n) if isinstance(n, (int, float)) and n > 0 else 100

    @property
    def final_steps(self) -> float:
        s = self.metrics.get("env_steps")
        if s is not None and np.isfinite(s).any():
            return float(np.nanmax(s))
        steps = [e.get("env_steps") for e in self.evals.values() if isinstance(e.get("env_steps"), (int, float))]
        return float(max(steps)) if steps else float("nan")

    @property
    def physics(self) -> list[str]:
        """The model digests the run trained on (`UnimalEnv.digest`: the physics simulated); [] for runs before
        session 45. More than one: resumed with allow_changes=[model_digest]."""
        return invoked_values(self.invocations, "model_digest")

    @property
    def devices(self) -> list[str]:
        """The device kinds the run was trained on (e.g. ["NVIDIA H200"]); [] when unknown."""
        return invoked_values(self.invocations, "device_kind")

    @property
    def iterations(self) -> int:
        return len(self.metrics.get("iteration", []))

    def short_of_stop(self) -> tuple[int, int] | None:
        """(the last iteration in metrics.csv, the one config.yaml ends the run at: RunConfig.last_iteration) where
        the first is short of the second: a run stopped by a time limit, to be resumed or moved to a later lease;
        None where it got there, or where config.yaml no longer fits today's schema and cannot say."""
        from ..run.config import ConfigError, to_schema      # hydra: loaded only when asked
        try:
            end = to_schema(self.cfg).last_iteration()
        except ConfigError:
            return None
        it = self.metrics.get("iteration")
        reached = int(it[-1]) if it is not None and len(it) and np.isfinite(it[-1]) else 0
        return (reached, end) if reached < end else None

    def eval_steps(self, tag: str) -> float | None:
        """The env steps of the checkpoint evaluated in eval/<tag>.json (None: no such file, or one that does not
        say)."""
        v = (self.evals.get(tag) or {}).get("env_steps")
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None

    def per_robot(self, tag: str) -> dict[str, float]:
        pr = (self.evals.get(tag) or {}).get("per_robot") or {}
        return {k: float(v) for k, v in pr.items() if isinstance(v, (int, float)) and math.isfinite(v)}

    # metrics-derived numbers
    def final_train_return(self) -> float:
        """Mean episode return of the last ~5% of iterations."""
        return self.train_return()

    def train_return(self, up_to_steps: float = math.inf) -> float:
        """Mean episode return of the last ~5% of the iterations at or below `up_to_steps` env steps (all of them by
        default: the final training return)."""
        y = self.metrics.get("episode_return")
        if y is None:
            return float("nan")
        if math.isfinite(up_to_steps):
            s = self.metrics.get("env_steps")
            if s is None:
                return float("nan")
            y = y[s <= up_to_steps]
        y = y[np.isfinite(y)]
        if not y.size:
            return float("nan")
        k = max(1, int(math.ceil(0.05 * y.size)))
        return float(y[-k:].mean())

    #: an iteration slower than this many times the run's median wall time holds a compilation (a call's first
    #: iteration) or a checkpoint wait: left out of the phase rates
    SLOW_ITERATION = 3.0

    def call_first_iterations(self) -> set[int]:
        """The iteration each start or resume of the run ran first (devices.yaml's `start_iteration` + 1), which
        holds that call's compilation; {1} when devices.yaml recorded none."""
        firsts = {int(i["start_iteration"]) + 1 for i in self.invocations
                  if isinstance(i.get("start_iteration"), int)}
        return firsts or {1}

    def phase_rates(self) -> list[dict]:
        """Env steps/s per phase as the benchmark notes give them: the iterations that ran all `ppo.epochs` epochs
        (the worst case) and those the KL stop cut short (a real run's rate), each the median over its iterations of
        metrics.csv's `rollout_sps`, `update_sps` and `sps` (end to end) and the mean epochs run, leaving out the
        iterations slower than SLOW_ITERATION x the median wall time; then the whole run: its env steps over the
        time of every iteration but each call's first (`call_first_iterations`), the rollout's and the update's time
        taken from their rates. [] when metrics.csv lacks those columns."""
        m = self.metrics
        if any(k not in m for k in ("rollout_sps", "update_sps", "sps", "wall_s", "epochs_run", "iteration",
                                    "env_steps")):
            return []
        full = float((self.cfg.get("ppo") or {}).get("epochs", 8))
        w, epochs = m["wall_s"], m["epochs_run"]
        kept = np.isfinite(w) & (w <= self.SLOW_ITERATION * np.nanmedian(w))
        out = []
        for phase, sel in (("all epochs", epochs >= full), ("KL stop active", epochs < full)):
            sel = sel & kept
            if sel.any():
                out.append({"phase": phase, "iterations": int(sel.sum()), "left_out": int((~kept).sum()),
                            "rollout_sps": float(np.nanmedian(m["rollout_sps"][sel])),
                            "update_sps": float(np.nanmedian(m["update_sps"][sel])),
                            "sps": float(np.nanmedian(m["sps"][sel])), "epochs": float(np.nanmean(epochs[sel]))})
        steps = np.diff(m["env_steps"], prepend=0.0)            # the env steps each iteration added
        whole = ~np.isin(m["iteration"], sorted(self.call_first_iterations())) & np.isfinite(w) & np.isfinite(steps)
        if whole.any():
            n = steps[whole].sum()
            out.append({"phase": "whole run", "iterations": int(whole.sum()), "left_out": int((~whole).sum()),
                        "rollout_sps": float(n / (steps[whole] / m["rollout_sps"][whole]).sum()),
                        "update_sps": float(n / (steps[whole] / m["update_sps"][whole]).sum()),
                        "sps": float(n / w[whole].sum()), "epochs": float(np.nanmean(epochs[whole]))})
        return out

    #: the first minibatch's ratio after a rollout further than this from 1 is flagged: acting and training see the
    #: same states, so fp32 keeps it to ~1e-7 and bf16 to ~1e-4 (the two phases' matmuls round differently)
    RATIO_TOLERANCE = 1e-3

    def health(self) -> dict | None:
        """The bookkeeping checks over the run's iterations (metrics.csv): the largest |ratio - 1| and |KL| of the
        first minibatch after each rollout, the unstable episodes (the simulator's, reset and counted), the first
        iteration the KL stop cut short (None: never), the largest |value_mean|, the iterations with a non-finite
        loss, KL or value, and `flags`, what a reader should look at (empty: nothing). None without those columns."""
        m = self.metrics
        if any(k not in m for k in ("first_ratio", "first_kl", "epochs_run")):
            return None

        def largest(x) -> float:
            x = np.abs(x[np.isfinite(x)])
            return float(x.max()) if x.size else float("nan")

        full = float((self.cfg.get("ppo") or {}).get("epochs", 8))
        cut = np.flatnonzero(m["epochs_run"] < full)
        it = m.get("iteration", np.arange(1, len(m["epochs_run"]) + 1))
        bad = np.zeros(len(m["epochs_run"]), bool)
        for k in ("loss", "approx_kl", "value_mean", "first_ratio"):
            if k in m:
                bad |= ~np.isfinite(m[k])
        h = {"ratio_off": largest(m["first_ratio"] - 1), "kl": largest(m["first_kl"]),
             "unstable": int(np.nansum(m["instabilities"])) if "instabilities" in m else None,
             "first_kl_stop": int(it[cut[0]]) if cut.size else None,
             "value_max": largest(m["value_mean"]) if "value_mean" in m else float("nan"),
             "nonfinite": int(bad.sum())}
        h["flags"] = [f for f, on in [
            (f"first-minibatch ratio off 1 by {h['ratio_off']:.1e}", not h["ratio_off"] <= self.RATIO_TOLERANCE),
            (f"non-finite metrics in {h['nonfinite']} iterations", h["nonfinite"] > 0),
            (f"{h['unstable']} unstable episodes", bool(h["unstable"])),
            (f"physics changed: {' → '.join(d[:8] for d in self.physics)}", len(self.physics) > 1)] if on]
        short = self.short_of_stop()
        if short:
            h["flags"].append(f"stopped at iteration {short[0]} of {short[1]}")
        return h

    def wall_hours(self) -> float:
        w = self.metrics.get("wall_s")
        return float(np.nansum(w) / 3600) if w is not None else float("nan")

    def hours_per_100m(self) -> float:
        s = self.final_steps
        return self.wall_hours() / s * 1e8 if s and np.isfinite(s) else float("nan")

    def mean_sps(self) -> float:
        """Mean env steps/s of the iterations after the first (which includes compilation)."""
        s = self.metrics.get("sps")
        if s is None or not s.size:
            return float("nan")
        s = s[1:] if s.size > 1 else s
        s = s[np.isfinite(s)]
        return float(s.mean()) if s.size else float("nan")


def read_run(path: str | Path) -> Run:
    """The Run of a run directory. Raises NotARunDir without config.yaml, ValueError (or yaml.YAMLError) when it is
    not a mapping; unreadable metrics.csv or eval files become notes."""
    path = Path(path)
    f = path / "config.yaml"
    if not f.is_file():
        raise NotARunDir(path)
    cfg = yaml.safe_load(f.read_text())
    if not isinstance(cfg, dict):
        raise ValueError(f"{f}: not a mapping")
    run = Run(path, cfg)
    try:
        run.metrics = read_metrics(path)
    except (OSError, csv.Error) as e:
        run.notes.append(f"metrics.csv unreadable ({e})")
    if not run.metrics:
        run.notes.append("no metrics.csv rows: left out of the learning curves and compute numbers")
    for g in sorted((path / "eval").glob("*.json")) if (path / "eval").is_dir() else []:
        try:
            d = json.loads(g.read_text())
            if not isinstance(d, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as e:
            run.notes.append(f"{g.name} unreadable ({e})")
            continue
        run.evals[g.stem] = d
    try:
        run.invocations = read_invocations(path)
    except ValueError as e:
        run.notes.append(f"devices.yaml unreadable ({e})")
    try:
        computed = read_computed_physics(path)
    except ValueError as e:
        run.notes.append(str(e))
    else:
        if computed and not run.physics:      # the run's own record stands (write_computed_physics refuses these)
            run.physics_computed = computed["model_digest"]
    return run


def classify(runs: Sequence[Run]) -> None:
    """Set each run's kind. Per task, the main robot count is "all" (num_robots null) when some run of the task
    uses all robots, else the largest num_robots of the task's runs (so a report of smoke runs or of a
    training-set-size study alone still has main runs). Runs with all context features at that count are main,
    at other counts size; runs with context_features set are context runs at that count, else other."""
    for task in {r.task for r in runs}:
        rs = [r for r in runs if r.task == task]
        level = None if any(r.num_robots is None for r in rs) else max(r.num_robots for r in rs)
        for r in rs:
            if r.context is None:
                r.kind = "main" if r.num_robots == level else "size"
            else:
                r.kind = "context" if r.num_robots == level else "other"


#: config keys (dotted, or prefixes) that make a variant of an architecture: how it was trained and simulated
VARIANT_KEYS = ("model", "ppo", "precision", "env")
#: ...except these: they have their own place in the report (task, context features) or say nothing of training
#: (env.linalg: how MJX's Cholesky is computed, the same equations to float rounding and the same physics digest; a
#: resume may change it, run.config.FREE; session 62's R-MoMo seed on pallas learned no worse than those on jax)
NOT_VARIANT_KEYS = ("env.task", "env.context_features", "env.linalg")


def _config_defaults() -> dict:
    """Today's RunConfig defaults, flattened ("model.scale_context": None, "precision": "fp32", ...)."""
    from ..run.config import RunConfig, to_dict      # hydra and the model zoo: loaded only when names are given
    return flatten_config(to_dict(RunConfig()))


def _value(v) -> str:
    if v is None:
        return "null"          # a model option left to make_model's own reading (config.yaml's value, verbatim)
    return str(v).lower() if isinstance(v, bool) else str(v)


def name_variants(runs: Sequence[Run]) -> None:
    """Set each run's `variant`: the training keys (VARIANT_KEYS) whose values differ among the runs of its task and
    architecture, as "key=value" with the key's last part (e.g. "scale_after_cell=true, precision=bf16"); "" when all
    runs of the group agree. A key missing from some run's config (a run older than the key) counts at its default
    in today's RunConfig, the value that keeps the behaviour the run had (so a run from before `model.scale_context`
    stands apart from a run with it true); a key today's RunConfig lacks (since removed) is compared only where
    every run of the group has it."""
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault((r.task, r.arch), []).append(r)
    in_scope = lambda k: matches_key(k, VARIANT_KEYS) and not matches_key(k, NOT_VARIANT_KEYS)
    defaults = _config_defaults()
    for rs in groups.values():
        flats = [flatten_config(r.cfg) for r in rs]
        shared = set.intersection(*(set(f) for f in flats))
        flats = [{**defaults, **f} for f in flats]
        keys = sorted(k for k in shared | set(defaults) if in_scope(k) and len({repr(f[k]) for f in flats}) > 1)
        for r, f in zip(rs, flats):
            r.variant = ", ".join(f"{k.rsplit('.', 1)[-1]}={_value(f[k])}" for k in keys)
