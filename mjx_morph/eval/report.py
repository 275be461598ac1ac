"""Figures, tables and a markdown report from finished runs.

    build_report(["runs/ft-rmomo-s0", "runs/ft-modumorph-s0"], "reports/ft")    # -> reports/ft/report.md
    python -m experiments.report runs=[runs/ft-rmomo-s0,runs/ft-modumorph-s0] out=reports/ft

Inputs, per run directory (read only): `config.yaml`, `metrics.csv` and `eval/<tag>.json` of
`mjx_morph.eval.evaluate` (any of them but config.yaml may be missing: what needs it is left out and listed in the
report's "Missing" section).

Runs are grouped by task (`env.name`), architecture (`arch.name`) and kind (`classify`):
- main: all train robots (`num_robots` null; if no run of the task has that, the task's largest num_robots) and
  all context features (`context_features` absent, null or every group); seeds of a task and architecture pool;
- size: all context features and another `num_robots` (training-set-size runs); in the size figure a full-set
  run stands at its robot count (the `robots` of its eval/train.json, else 100) unless a run names that count;
- context: `context_features` a list of kept groups (single-context-feature runs) at the main robot count,
  compared with the main runs.

Statistics: the per-robot mean returns of eval/<tag>.json are averaged over the seeds of a group (over the seeds
that evaluated the robot), and mean and 95% CI (`ci95`, Student t) are taken over robots; normalised returns use
`normalised` (the paper's per-task range) and are pooled across tasks as (task, robot) pairs. Learning curves:
each seed's episode return against env steps, lightly smoothed, interpolated onto a common grid; mean and 95% CI
over the seeds covering each grid point (no band with one seed).

Outputs in `out/`: PNG figures, CSV tables and `report.md` (runs, figures with captions, tables, missing).
"""
from __future__ import annotations

import csv
import datetime
import json
import math
import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import yaml

from ..layout import CONTEXT_GROUPS as _GROUPS
from ..unimal.variants import CHANGE_TYPES, variant_change
from . import plots
from .evaluate import TASK_RANGES, ci95, normalised

SETS = ("train", "test", "val", "variants")
CONTEXT_GROUPS: tuple[str, ...] = tuple(_GROUPS)     # in column order: the order of the groups in figures
TASK_ORDER = tuple(TASK_RANGES)
CONF = Path(__file__).resolve().parents[2] / "experiments" / "conf"
DEFAULT_COMPARE = ("rmomo", "modumorph")
CURVE_POINTS = 200


class NotARunDir(ValueError):
    def __init__(self, path):
        super().__init__(f"{path}: not a run directory (no config.yaml)")
        self.path = path


# ---- reading runs ----------------------------------------------------------------------------------------------
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
    kind: str = "main"                                  # main | size | context | other: see classify()

    @property
    def task(self) -> str:
        return str((self.cfg.get("env") or {}).get("name", "?"))

    @property
    def arch(self) -> str:
        return str((self.cfg.get("arch") or {}).get("name", "?"))

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
        v = self.cfg.get("context_features")
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
    def iterations(self) -> int:
        return len(self.metrics.get("iteration", []))

    def per_robot(self, tag: str) -> dict[str, float]:
        pr = (self.evals.get(tag) or {}).get("per_robot") or {}
        return {k: float(v) for k, v in pr.items() if isinstance(v, (int, float)) and math.isfinite(v)}

    # metrics-derived numbers
    def final_train_return(self) -> float:
        """Mean episode return of the last ~5% of iterations."""
        y = self.metrics.get("episode_return")
        if y is None:
            return float("nan")
        y = y[np.isfinite(y)]
        if not y.size:
            return float("nan")
        k = max(1, int(math.ceil(0.05 * y.size)))
        return float(y[-k:].mean())

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


def load_run(path: str | Path) -> Run:
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


# ---- statistics ------------------------------------------------------------------------------------------------
def _norm(x, task: str) -> np.ndarray:
    if task not in TASK_RANGES:
        return np.full(np.shape(x), np.nan)
    return normalised(x, task)


def seed_average(runs: Sequence[Run], tag: str) -> dict[str, float]:
    """Robot name -> its mean return averaged over the runs (seeds) that evaluated it on `tag`."""
    acc: dict[str, list[float]] = defaultdict(list)
    for r in runs:
        for k, v in r.per_robot(tag).items():
            acc[k].append(v)
    return {k: float(np.mean(v)) for k, v in acc.items()}


@dataclass
class Stat:
    mean: float
    ci: float
    norm: float
    norm_ci: float
    robots: int
    seeds: int


def stat_of(values: Sequence[float], task: str | None, seeds: int, norm_values=None) -> Stat:
    v = np.asarray(values, float)
    n = _norm(v, task) if norm_values is None else np.asarray(norm_values, float)
    return Stat(float(v.mean()) if v.size else float("nan"), ci95(v), float(n.mean()) if n.size else float("nan"),
                ci95(n), int(v.size), seeds)


def set_stat(runs: Sequence[Run], tag: str, task: str) -> Stat | None:
    """Mean and CI over robots of the seed-averaged per-robot returns on `tag` (None: no run has it). Without
    per-robot numbers: the seeds' mean returns (CI over seeds, or the file's CI for one seed)."""
    have = [r for r in runs if tag in r.evals]
    if not have:
        return None
    pr = seed_average(have, tag)
    if pr:
        return stat_of(list(pr.values()), task, len(have))
    means = [float(r.evals[tag].get("mean_return", np.nan)) for r in have]
    st = stat_of(means, task, len(have))
    if len(have) == 1:
        st.ci = float(have[0].evals[tag].get("ci95_return", np.nan))
        st.norm_ci = float(have[0].evals[tag].get("ci95_normalised", np.nan))
        st.robots = int(have[0].evals[tag].get("robots", 0) or 0)
    return st


def change_stats(runs: Sequence[Run], task: str) -> dict[str, Stat]:
    """Variant returns per change type: {change: Stat} over the variant robots of that type."""
    have = [r for r in runs if "variants" in r.evals]
    pr = seed_average(have, "variants")
    by: dict[str, list[float]] = defaultdict(list)
    for name, v in pr.items():
        try:
            by[variant_change(name)[1]].append(v)
        except ValueError:
            continue
    if by:
        return {c: stat_of(by[c], task, len(have)) for c in CHANGE_TYPES if c in by}
    out = {}
    for c in CHANGE_TYPES:          # no per-robot names: the files' per-change summaries
        pcs = [r.evals["variants"].get("per_change", {}).get(c) for r in have]
        pcs = [p for p in pcs if isinstance(p, dict) and "mean_return" in p]
        if pcs:
            st = stat_of([p["mean_return"] for p in pcs], task, len(pcs))
            if len(pcs) == 1:
                st.ci, st.norm_ci = float(pcs[0].get("ci95_return", np.nan)), float(pcs[0].get("ci95_normalised",
                                                                                               np.nan))
            out[c] = st
    return out


def robot_difference(runs_a: Sequence[Run], runs_b: Sequence[Run], tag: str = "test",
                     task: str | None = None) -> list[tuple[str, float, float, float]]:
    """[(robot, a, b, a - b)] over the robots both evaluated, seed-averaged, sorted by difference (largest first);
    normalised returns when `task` is given."""
    a, b = seed_average(runs_a, tag), seed_average(runs_b, tag)
    rows = []
    for k in a:
        if k in b:
            va, vb = a[k], b[k]
            if task is not None:
                va, vb = float(_norm(va, task)), float(_norm(vb, task))
            rows.append((k, va, vb, va - vb))
    return sorted(rows, key=lambda r: (-r[3], r[0]))


def _smooth(y: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average over k points (shorter at the ends)."""
    if k <= 1 or y.size < 3:
        return y
    c = np.concatenate([[0.0], np.cumsum(y)])
    i = np.arange(y.size)
    lo, hi = np.maximum(0, i - k // 2), np.minimum(y.size, i + k // 2 + 1)
    return (c[hi] - c[lo]) / (hi - lo)


def mean_curve(curves: Sequence[tuple[np.ndarray, np.ndarray]], points: int = CURVE_POINTS, smooth: bool = True):
    """(grid, mean, lo, hi, count) of curves (x, y) interpolated onto a common grid; mean over the curves that cover
    a grid point, lo/hi = mean -/+ ci95 where at least two do (else nan)."""
    curves = [(np.asarray(x, float), np.asarray(y, float)) for x, y in curves]
    curves = [(x[np.isfinite(y) & np.isfinite(x)], y[np.isfinite(y) & np.isfinite(x)]) for x, y in curves]
    curves = [(x, y) for x, y in curves if x.size]
    if not curves:
        e = np.zeros(0)
        return e, e, e, e, e
    grid = np.linspace(min(x[0] for x, _ in curves), max(x[-1] for x, _ in curves), points)
    ys = np.full((len(curves), points), np.nan)
    for i, (x, y) in enumerate(curves):
        if smooth:
            y = _smooth(y, max(1, y.size // 50))
        inside = (grid >= x[0]) & (grid <= x[-1])
        ys[i, inside] = np.interp(grid[inside], x, y)
    count = np.isfinite(ys).sum(0)
    mean = np.array([np.nanmean(c) if n else np.nan for c, n in zip(ys.T, count)])
    half = np.array([ci95(c[np.isfinite(c)]) if n >= 2 else np.nan for c, n in zip(ys.T, count)])
    return grid, mean, mean - half, mean + half, count


_PARAMS_CACHE: dict[str, int] = {}


def _conf_yaml(group: str, name: str) -> dict:
    f = CONF / group / f"{name}.yaml"
    try:
        d = yaml.safe_load(f.read_text()) if f.is_file() else {}
    except yaml.YAMLError:
        d = {}
    return d if isinstance(d, dict) else {}


def param_count(cfg: dict) -> int:
    """Trainable parameters of a run's model (mjx_morph.nets.model_from_config + Model.num_params, traced with
    jax.eval_shape), from its resolved config over the defaults of experiments/conf/{arch,env}/<name>.yaml."""
    from omegaconf import OmegaConf

    from ..nets import model_from_config
    arch, env = dict(cfg.get("arch") or {}), dict(cfg.get("env") or {})
    arch_full = {**_conf_yaml("arch", str(arch.get("name"))), **arch}
    arch_full["model"] = {**(_conf_yaml("arch", str(arch.get("name"))).get("model") or {}),
                          **(arch.get("model") or {})}
    env_full = {**_conf_yaml("env", str(env.get("name"))), **env}
    env_full = {"hfield_obs": bool(env_full.get("hfield_obs", False)),
                "decoder_dims": list(env_full.get("decoder_dims") or [])}
    overrides = dict(cfg.get("model_overrides") or {})
    key = json.dumps([arch_full, env_full, overrides], sort_keys=True, default=str)
    if key not in _PARAMS_CACHE:
        model = model_from_config(OmegaConf.create(arch_full), OmegaConf.create(env_full), **overrides)
        _PARAMS_CACHE[key] = model.num_params()
    return _PARAMS_CACHE[key]


# ---- the report ------------------------------------------------------------------------------------------------
def _fmt(x, nd: int = 1) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return f"{x:.{nd}f}"


def _pm(m, ci, nd: int = 1) -> str:
    if m is None or not math.isfinite(m):
        return "–"
    return f"{m:.{nd}f} ± {ci:.{nd}f}" if ci is not None and math.isfinite(ci) else f"{m:.{nd}f}"


def _csv_value(v):
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return "" if v is None else v


def _steps(x: float) -> str:
    if not math.isfinite(x):
        return "–"
    return f"{x / 1e6:.1f}M" if x >= 1e6 else f"{x:,.0f}"


class _Doc:
    def __init__(self, out: Path):
        self.out = out
        self.figures: list[tuple[str, str, str]] = []            # (section, file, caption)
        self.tables: list[tuple[str, list[str], list[list], str, str]] = []   # (title, header, md rows, csv, note)
        self.missing: list[str] = []

    def figure(self, section: str, path: Path, caption: str) -> None:
        self.figures.append((section, path.name, caption))

    def table(self, title: str, name: str, header: Sequence[str], rows: Sequence[Sequence], md_header=None,
              md_rows=None, note: str = "") -> None:
        with (self.out / f"{name}.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            for r in rows:
                w.writerow([_csv_value(v) for v in r])
        self.tables.append((title, list(md_header or header),
                            [list(r) for r in (md_rows if md_rows is not None else rows)], f"{name}.csv", note))


def _md_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    def cell(v):
        if isinstance(v, float):
            v = _fmt(v, 3)
        return str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(map(cell, header)) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def _order_archs(archs: Iterable[str]) -> list[str]:
    try:
        from ..nets import ARCHS
    except Exception:  # noqa: BLE001
        ARCHS = ()
    archs = set(archs)
    return [a for a in ARCHS if a in archs] + sorted(a for a in archs if a not in ARCHS)


def _order_tasks(tasks: Iterable[str]) -> list[str]:
    tasks = set(tasks)
    return [t for t in TASK_ORDER if t in tasks] + sorted(t for t in tasks if t not in TASK_ORDER)


def _display(p: Path) -> str:
    try:
        rel = os.path.relpath(p)
        return rel if not rel.startswith("..") else str(p)
    except ValueError:
        return str(p)


def build_report(run_dirs: Sequence[str | Path], out: str | Path,
                 compare: Sequence[str] = DEFAULT_COMPARE, title: str = "mjx_morph report") -> Path:
    """Read the runs, write figures, tables and `out/report.md`; returns the path of report.md. `run_dirs` may
    name directories holding run directories (see find_run_dirs)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = _Doc(out)
    runs: list[Run] = []
    for d in find_run_dirs(run_dirs):
        try:
            runs.append(load_run(d))
        except (OSError, ValueError, yaml.YAMLError) as e:
            doc.missing.append(f"`{_display(d)}`: left out ({e})")
    classify(runs)
    for r in runs:
        for n in r.notes:
            doc.missing.append(f"`{_display(r.path)}`: {n}")
        if not r.evals:
            doc.missing.append(f"`{_display(r.path)}`: no eval/*.json: in no return figure or table (evaluate it with "
                               f"`python -m experiments.evaluate run_dir={_display(r.path)}`)")
        elif "test" not in r.evals:
            doc.missing.append(f"`{_display(r.path)}`: no eval/test.json: left out of the test-return figures")
        if r.kind == "other":
            doc.missing.append(f"`{_display(r.path)}`: context_features set and num_robots {r.num_robots} differs from "
                               "the task's main runs: in no figure")
    compare = tuple(compare) if compare else DEFAULT_COMPARE
    tasks = _order_tasks(r.task for r in runs)
    main = {t: {a: [r for r in runs if r.task == t and r.arch == a and r.kind == "main"]
                for a in _order_archs(r.arch for r in runs if r.task == t and r.kind == "main")} for t in tasks}

    _runs_table(doc, runs)
    _learning_curves(doc, tasks, main)
    _returns(doc, tasks, main)
    _robot_differences(doc, tasks, main, compare)
    _reward_per_step(doc, tasks, main)
    _train_size(doc, tasks, runs)
    _context_features(doc, tasks, runs, main)
    _params_table(doc, runs)
    _compute_table(doc, tasks, main)
    return _write_markdown(doc, runs, title)


def _runs_table(doc: _Doc, runs: Sequence[Run]) -> None:
    header = ["run", "task", "arch", "seed", "kind", "num_robots", "context_features", "iterations", "env_steps",
              "wall_h", "h_per_100M", "mean_sps", "final_train_return", "evals"]
    rows, md = [], []
    for r in runs:
        ctx = r.context_label
        evals = ", ".join(sorted(r.evals)) or "none"
        rows.append([_display(r.path), r.task, r.arch, r.seed, r.kind, r.num_robots if r.num_robots else "all", ctx,
                     r.iterations, r.final_steps, r.wall_hours(), r.hours_per_100m(), r.mean_sps(),
                     r.final_train_return(), evals])
        md.append([f"`{_display(r.path)}`", r.task, r.arch, r.seed, r.kind, r.num_robots or "all", ctx, r.iterations,
                   _steps(r.final_steps), _fmt(r.wall_hours(), 2), _fmt(r.hours_per_100m(), 2), _fmt(r.mean_sps(), 0),
                   _fmt(r.final_train_return()), evals])
    doc.table("Runs", "runs", header, rows,
              ["run", "task", "arch", "seed", "kind", "robots", "context", "iterations", "env steps", "wall h",
               "wall h / 100 M steps", "mean steps/s", "final train return", "evals"], md,
              note="final train return: mean episode return of the last ~5% of iterations; wall h / 100 M steps: "
                   "sum(wall_s) / final env steps x 1e8; mean steps/s excludes the first iteration (compilation).")


def _learning_curves(doc: _Doc, tasks, main) -> None:
    for t in tasks:
        curves, labels = {}, {}
        for a, rs in main[t].items():
            cs = [(r.metrics["env_steps"], r.metrics["episode_return"]) for r in rs
                  if "env_steps" in r.metrics and "episode_return" in r.metrics]
            grid, m, lo, hi, _ = mean_curve(cs)
            if grid.size:
                curves[a] = (grid, m, lo, hi)
                labels[a] = f"{a} ({len(cs)} seed{'s' if len(cs) != 1 else ''})"
        if not curves:
            doc.missing.append(f"{t}: learning curves — no main run has episode returns in metrics.csv")
            continue
        p = plots.mean_curves(curves, doc.out / f"learning_curve_{t}.png", title=f"{t}: training return",
                              labels=labels)
        doc.figure("Learning curves", p, f"{t}: mean training episode return against env steps, mean over seeds "
                                         f"(band: 95% CI where at least two seeds cover a point; main runs: all "
                                         f"train robots and context features).")


def _returns(doc: _Doc, tasks, main) -> None:
    header = ["task", "arch", "seeds"]
    for s in SETS:
        header += [f"{s}_return", f"{s}_ci95", f"{s}_normalised", f"{s}_normalised_ci95", f"{s}_robots"]
    rows, md, present = [], [], set()
    change_rows = []
    for t in tasks:
        set_series: dict[str, tuple[list, list]] = {}
        change_series: dict[str, tuple[list, list]] = {}
        sets_here = [s for s in SETS if any(s in r.evals for rs in main[t].values() for r in rs)]
        changes_here: list[str] = []
        stats = {a: {s: set_stat(rs, s, t) for s in SETS} for a, rs in main[t].items()}
        cstats = {a: change_stats(rs, t) for a, rs in main[t].items()}
        for a in main[t]:
            for c in cstats[a]:
                if c not in changes_here:
                    changes_here.append(c)
        changes_here = [c for c in CHANGE_TYPES if c in changes_here]
        for a, rs in main[t].items():
            st = stats[a]
            if not any(st.values()):
                continue
            seeds = len(rs)
            row, mrow = [t, a, seeds], [t, a, seeds]
            for s in SETS:
                x = st[s]
                row += [x.mean, x.ci, x.norm, x.norm_ci, x.robots] if x else [float("nan")] * 4 + [0]
                if x:
                    present.add(s)
            rows.append(row)
            md.append(mrow + [(f"{_pm(st[s].mean, st[s].ci)} ({_pm(st[s].norm, st[s].norm_ci, 3)})" if st[s] else "–")
                              for s in SETS])
            set_series[a] = ([st[s].mean if st[s] else np.nan for s in sets_here],
                             [st[s].ci if st[s] else np.nan for s in sets_here])
            if cstats[a]:
                change_series[a] = ([cstats[a][c].mean if c in cstats[a] else np.nan for c in changes_here],
                                    [cstats[a][c].ci if c in cstats[a] else np.nan for c in changes_here])
                for c, x in cstats[a].items():
                    change_rows.append([t, a, c, x.seeds, x.robots, x.mean, x.ci, x.norm, x.norm_ci])
        if not set_series:
            doc.missing.append(f"{t}: return bars — no main run has eval/*.json")
            continue
        panels = [{"groups": sets_here, "series": set_series, "ylabel": "mean return",
                   "title": "by robot set (95% CI over robots)"}]
        if change_series:
            panels.append({"groups": changes_here, "series": change_series, "ylabel": "mean return",
                           "title": "variants by change type"})
        else:
            doc.missing.append(f"{t}: variant returns by change type — no main run has eval/variants.json")
        if "test" not in sets_here:
            doc.missing.append(f"{t}: test returns — no main run has eval/test.json")
        p = plots.bar_panels(panels, doc.out / f"returns_{t}.png", title=f"{t}: evaluation returns")
        per_change = " and per variant change type" if change_series else ""
        doc.figure("Returns", p, f"{t}: mean return per robot set{per_change}"
                                 f", seed-averaged per robot, 95% CI over robots.")
    if rows:
        keep = [s for s in SETS if s in present]
        cols = [0, 1, 2] + [3 + SETS.index(s) for s in keep]          # markdown: only the sets some run has
        md_header = ["task", "arch", "seeds"] + [f"{s} return (normalised)" for s in SETS]
        doc.table("Returns (main runs)", "returns", header, rows,
                  [md_header[i] for i in cols],
                  [[r[i] for i in cols] for r in md],
                  note="mean ± 95% CI over robots of seed-averaged per-robot returns; sets present: "
                       f"{', '.join(keep)}.")
    if change_rows:
        doc.table("Variant returns by change type", "variants_by_change",
                  ["task", "arch", "change", "seeds", "robots", "return", "ci95", "normalised", "normalised_ci95"],
                  change_rows,
                  ["task", "arch", "change", "seeds", "robots", "return", "normalised"],
                  [[t, a, c, s, n, _pm(m, ci), _pm(nm, nci, 3)] for t, a, c, s, n, m, ci, nm, nci in change_rows])
    # normalised returns pooled across tasks
    archs = _order_archs(a for t in tasks for a in main[t])
    pooled: dict[str, dict[str, Stat]] = {}
    pooled_tasks: dict[str, list[str]] = {}
    for a in archs:
        for s in SETS:
            vals = []
            ts_ = []
            for t in tasks:
                rs = main[t].get(a, [])
                pr = seed_average(rs, s)
                if pr and t in TASK_RANGES:
                    vals.extend(_norm(list(pr.values()), t).tolist())
                    ts_.append(t)
            if vals:
                pooled.setdefault(a, {})[s] = stat_of(vals, None, 0, norm_values=vals)
                pooled_tasks.setdefault(a, [])
                pooled_tasks[a] = sorted(set(pooled_tasks[a]) | set(ts_), key=_order_tasks(tasks).index)
    if not pooled:
        doc.missing.append("pooled normalised returns — no main run has per-robot eval results on a known task")
        return
    sets_here = [s for s in SETS if any(s in v for v in pooled.values())]
    series = {a: ([pooled[a][s].norm if s in pooled[a] else np.nan for s in sets_here],
                  [pooled[a][s].norm_ci if s in pooled[a] else np.nan for s in sets_here]) for a in pooled}
    p = plots.bar_panels([{"groups": sets_here, "series": series, "ylabel": "mean normalised return",
                           "title": "pooled over tasks and robots (95% CI)"}],
                         doc.out / "returns_pooled_normalised.png",
                         title="normalised returns, all tasks")
    tasks_note = "; ".join(f"{a}: {', '.join(pooled_tasks[a])}" for a in pooled)
    doc.figure("Returns", p, f"Normalised return pooled across tasks ((task, robot) pairs, seed-averaged), 95% CI; "
                             f"tasks: {tasks_note}.")
    prow, pmd = [], []
    for a in pooled:
        row, mrow = [a, " ".join(pooled_tasks[a])], [a, ", ".join(pooled_tasks[a])]
        for s in SETS:
            x = pooled[a].get(s)
            row += [x.norm, x.norm_ci, x.robots] if x else [float("nan"), float("nan"), 0]
            mrow.append(_pm(x.norm, x.norm_ci, 3) if x else "–")
        prow.append(row)
        pmd.append(mrow)
    doc.table("Normalised returns pooled across tasks", "returns_pooled",
              ["arch", "tasks"] + [f"{s}_{k}" for s in SETS for k in ("normalised", "normalised_ci95", "robots")],
              prow, ["arch", "tasks"] + [f"{s} normalised" for s in SETS], pmd,
              note="95% CI over (task, robot) pairs of seed-averaged normalised returns.")


def _pair(archs_with_test: list[str], compare: tuple[str, ...]) -> tuple[str, str] | None:
    if len(compare) >= 2 and compare[0] in archs_with_test and compare[1] in archs_with_test:
        return compare[0], compare[1]
    return (archs_with_test[0], archs_with_test[1]) if len(archs_with_test) >= 2 else None


def _robot_differences(doc: _Doc, tasks, main, compare) -> None:
    summary, pairs = [], {}
    for t in tasks:
        with_test = [a for a, rs in main[t].items() if seed_average(rs, "test")]
        pair = _pair(with_test, compare)
        if pair is None:
            doc.missing.append(f"{t}: per-robot difference — needs per-robot test returns of two architectures "
                               f"(have: {', '.join(with_test) or 'none'})")
            continue
        if pair != tuple(compare[:2]):
            doc.missing.append(f"{t}: compare pair {compare[0]} vs {compare[1]} not both present; "
                               f"showed {pair[0]} vs {pair[1]} instead")
        pairs[t] = pair
        a, b = pair
        rows = robot_difference(main[t][a], main[t][b], "test")
        if not rows:
            doc.missing.append(f"{t}: per-robot difference — {a} and {b} have no test robot in common")
            continue
        _write_csv(doc.out / f"robot_diff_{t}.csv", ["robot", f"{a}_return", f"{b}_return", "difference"], rows)
        d = np.array([r[3] for r in rows])
        p = plots.robot_difference([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], a, b,
                                   doc.out / f"robot_diff_{t}.png", title=f"{t}: per-robot test return, {a} vs {b}")
        doc.figure("Per-robot differences", p, f"{t}: per-robot test return of {a} minus {b} (seed-averaged), sorted; "
                                               f"right: both returns in the same order (data: robot_diff_{t}.csv).")
        summary.append([t, a, b, len(rows), float(d.mean()), ci95(d), int((d > 0).sum()), f"robot_diff_{t}.csv"])
    # pooled across tasks on normalised returns
    counts: dict[tuple[str, str], int] = defaultdict(int)
    for pr in pairs.values():
        counts[pr] += 1
    wanted = tuple(compare[:2])
    pair = wanted if counts.get(wanted, 0) >= 2 else max(counts, key=counts.get, default=None)
    if pair is None or counts[pair] < 2:
        doc.missing.append("pooled per-robot difference — needs the same pair of architectures with test results on "
                           f"at least two tasks (have {len(pairs)} task(s) with a pair)")
    else:
        a, b = pair
        rows = []
        for t in tasks:
            if pairs.get(t) == pair and t in TASK_RANGES:
                rows += [(f"{t}:{n}", va, vb, d)
                         for n, va, vb, d in robot_difference(main[t][a], main[t][b], "test", t)]
        rows.sort(key=lambda r: (-r[3], r[0]))
        _write_csv(doc.out / "robot_diff_pooled.csv", ["task:robot", f"{a}_normalised", f"{b}_normalised",
                                                        "difference"], rows)
        d = np.array([r[3] for r in rows])
        p = plots.robot_difference([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], a, b,
                                   doc.out / "robot_diff_pooled.png", unit="normalised test return",
                                   title=f"all tasks: per-robot normalised test return, {a} vs {b}")
        doc.figure("Per-robot differences", p, f"All tasks: per-(task, robot) normalised test return of {a} minus {b}, "
                                               "sorted; right: both in the same order (data: robot_diff_pooled.csv).")
        summary.append(["pooled (normalised)", a, b, len(rows), float(d.mean()), ci95(d), int((d > 0).sum()),
                        "robot_diff_pooled.csv"])
    if summary:
        doc.table("Per-robot test differences", "robot_diff",
                  ["task", "a", "b", "robots", "mean_difference", "ci95", "robots_a_better", "data"], summary,
                  ["task", "a", "b", "robots", "mean a − b", "a better on", "per-robot data"],
                  [[t, a, b, n, _pm(m, ci, 3 if t.startswith("pooled") else 1), f"{k}/{n}", f"[{f}]({f})"]
                   for t, a, b, n, m, ci, k, f in summary])


def _write_csv(path: Path, header, rows) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            w.writerow([_csv_value(v) for v in r])


def _mean_trace(traces: list[list]) -> np.ndarray | None:
    traces = [np.asarray(x, float) for x in traces if x]
    if not traces:
        return None
    n = min(x.size for x in traces)
    return np.mean([x[:n] for x in traces], axis=0)


def _reward_per_step(doc: _Doc, tasks, main) -> None:
    for t in tasks:
        series, alive, zero_steps = {}, {}, set()
        for a, rs in main[t].items():
            tests = [r.evals["test"] for r in rs if "test" in r.evals]
            tr = _mean_trace([e.get("reward_trace") for e in tests])
            if tr is None:
                continue
            zero = _mean_trace([e.get("reward_trace_zero_state") for e in tests])
            series[a] = (tr, zero)
            al = _mean_trace([e.get("alive_trace") for e in tests])
            if al is not None:
                alive[a] = al
            zero_steps |= {int(e["zero_state_steps"]) for e in tests if e.get("zero_state_steps")}
        if not series:
            doc.missing.append(f"{t}: reward per timestep — no main run has a reward_trace in eval/test.json")
            continue
        zs = min(zero_steps) if zero_steps else None
        p = plots.reward_per_step(series, doc.out / f"reward_per_step_{t}.png", zero_steps=zs, alive=alive or None,
                                  title=f"{t}: reward per timestep, test robots")
        rec = [a for a, (_, z) in series.items() if z is not None]
        doc.figure("Reward per timestep", p,
                   f"{t}: mean reward at each of the first {len(next(iter(series.values()))[0])} steps over all test "
                   f"episodes (0 after an episode ended)"
                   + (f"; dashed: recurrent state held at 0 for the first {zs} steps"
                      + (" (dotted marker)" if zs and zs < len(next(iter(series.values()))[0]) else "") if rec else "")
                   + "; lower panel: fraction of episodes still running.")


def _train_size(doc: _Doc, tasks, runs) -> None:
    rows, md = [], []
    for t in tasks:
        cand = [r for r in runs if r.task == t and r.context is None and "test" in r.evals]
        if not any(r.kind == "size" for r in cand):
            doc.missing.append(f"{t}: training-set-size figure — no runs with all context features, eval/test.json "
                               "and a num_robots other than the main runs'")
            continue
        series = {}
        for a in _order_archs(r.arch for r in cand):
            mine = [r for r in cand if r.arch == a]
            explicit = {r.num_robots for r in mine if r.num_robots}
            by: dict[int, list[Run]] = defaultdict(list)
            for r in mine:       # a full-set run stands at its robot count where no run names that count
                if r.num_robots or r.train_size not in explicit:
                    by[r.train_size].append(r)
            if len(by) < 2:
                continue
            xs = sorted(by)
            st = [set_stat(by[x], "test", t) for x in xs]
            series[a] = (xs, [s.mean for s in st], [s.ci for s in st])
            for x, s in zip(xs, st):
                rows.append([t, a, x, s.seeds, s.robots, s.mean, s.ci, s.norm, s.norm_ci])
                md.append([t, a, x, s.seeds, s.robots, _pm(s.mean, s.ci), _pm(s.norm, s.norm_ci, 3)])
        if not series:
            doc.missing.append(f"{t}: training-set-size figure — no architecture has test results at two robot "
                               "counts")
            continue
        p = plots.errorbar_lines(series, doc.out / f"train_size_{t}.png", title=f"{t}: training-set size",
                                 xlabel="train robots", ylabel="mean test return")
        doc.figure("Training-set size", p, f"{t}: test return (mean ± 95% CI over robots, seed-averaged) against the "
                                           "number of train robots.")
    if rows:
        doc.table("Training-set size", "train_size",
                  ["task", "arch", "num_robots", "seeds", "test_robots", "test_return", "ci95", "normalised",
                   "normalised_ci95"], rows,
                  ["task", "arch", "train robots", "seeds", "test robots", "test return", "normalised"], md)


def _context_features(doc: _Doc, tasks, runs, main) -> None:
    rows, md = [], []
    for t in tasks:
        ctx_runs = [r for r in runs if r.task == t and r.kind == "context" and "test" in r.evals]
        if not ctx_runs:
            doc.missing.append(f"{t}: single-context-feature figure — no run with context_features set and "
                               "eval/test.json")
            continue
        labels = sorted({r.context_label for r in ctx_runs},
                        key=lambda s: ([CONTEXT_GROUPS.index(g) if g in CONTEXT_GROUPS else 99
                                        for g in s.split("+")], s))
        archs = _order_archs(r.arch for r in ctx_runs)
        series, refs = {}, {}
        for a in archs:
            ms, cs = [], []
            for lab in labels:
                sel = [r for r in ctx_runs if r.arch == a and r.context_label == lab]
                s = set_stat(sel, "test", t) if sel else None
                ms.append(s.mean if s else np.nan)
                cs.append(s.ci if s else np.nan)
                if s:
                    rows.append([t, a, lab, s.seeds, s.robots, s.mean, s.ci, s.norm, s.norm_ci])
                    md.append([t, a, lab, s.seeds, _pm(s.mean, s.ci), _pm(s.norm, s.norm_ci, 3)])
            series[a] = (ms, cs)
            ref = set_stat(main[t].get(a, []), "test", t)
            if ref:
                refs[a] = ref.mean
                rows.append([t, a, "all", ref.seeds, ref.robots, ref.mean, ref.ci, ref.norm, ref.norm_ci])
                md.append([t, a, "all", ref.seeds, _pm(ref.mean, ref.ci), _pm(ref.norm, ref.norm_ci, 3)])
            else:
                doc.missing.append(f"{t}: single-context-feature figure — no all-features reference for {a} "
                                   "(no main run with eval/test.json)")
        p = plots.bar_panels([{"groups": labels, "series": series, "refs": refs, "ylabel": "mean test return",
                               "ref_label": "all features ({})", "title": "only this context feature group kept"}],
                             doc.out / f"context_features_{t}.png", title=f"{t}: single context feature")
        doc.figure("Single context feature", p, f"{t}: test return with only one context feature group kept (others "
                                                "zeroed), 95% CI over robots; dashed: all features.")
    if rows:
        doc.table("Single context feature", "context_features",
                  ["task", "arch", "context_features", "seeds", "test_robots", "test_return", "ci95", "normalised",
                   "normalised_ci95"], rows,
                  ["task", "arch", "kept features", "seeds", "test return", "normalised"], md)


def _params_table(doc: _Doc, runs) -> None:
    rows, seen = [], set()
    for r in runs:
        if (r.task, r.arch) in seen:
            continue
        seen.add((r.task, r.arch))
        try:
            n = param_count(r.cfg)
        except Exception as e:  # noqa: BLE001 - a table cell, not a reason to fail the report
            doc.missing.append(f"parameter count of {r.arch} on {r.task}: {type(e).__name__}: {str(e)[:200]}")
            continue
        rows.append([r.task, r.arch, n])
    order_t, order_a = _order_tasks(x[0] for x in rows), _order_archs(x[1] for x in rows)
    rows.sort(key=lambda x: (order_t.index(x[0]), order_a.index(x[1])))
    if rows:
        doc.table("Parameters", "params", ["task", "arch", "parameters"], rows,
                  md_rows=[[t, a, f"{n:,}"] for t, a, n in rows],
                  note="trainable parameters of the run's model (actor and critic).")


def _compute_table(doc: _Doc, tasks, main) -> None:
    rows, md = [], []
    for t in tasks:
        for a, rs in main[t].items():
            rs = [r for r in rs if r.metrics]
            if not rs:
                continue
            h = np.array([r.hours_per_100m() for r in rs])
            sps = np.array([r.mean_sps() for r in rs])
            fin = np.array([r.final_train_return() for r in rs])
            steps = np.array([r.final_steps for r in rs])
            row = [t, a, len(rs), float(np.nanmean(steps)), float(np.nanmean(h)), ci95(h[np.isfinite(h)]),
                   float(np.nanmean(sps)), float(np.nanmean(fin)), ci95(fin[np.isfinite(fin)])]
            rows.append(row)
            md.append([t, a, len(rs), _steps(row[3]), _pm(row[4], row[5], 2), _fmt(row[6], 0), _pm(row[7], row[8])])
    if rows:
        doc.table("Compute and final training return (main runs)", "compute",
                  ["task", "arch", "seeds", "env_steps", "h_per_100M", "h_per_100M_ci95", "mean_sps",
                   "final_train_return", "final_train_return_ci95"], rows,
                  ["task", "arch", "seeds", "env steps", "wall h / 100 M steps", "mean steps/s", "final train return"],
                  md, note="mean ± 95% CI over seeds; final train return: mean episode return of the last ~5% of "
                           "iterations.")


SECTIONS = ("Learning curves", "Returns", "Per-robot differences", "Reward per timestep", "Training-set size",
            "Single context feature")


def _write_markdown(doc: _Doc, runs: Sequence[Run], title: str) -> Path:
    lines = [f"# {title}", "", f"Generated {datetime.datetime.now():%Y-%m-%d %H:%M} from {len(runs)} run(s).", ""]
    lines += ["## Runs", ""]
    runs_table = next((tb for tb in doc.tables if tb[3] == "runs.csv"), None)
    if runs_table:
        lines += [_md_table(runs_table[1], runs_table[2]), "", f"*{runs_table[4]}* ([runs.csv](runs.csv))", ""]
    for sec in SECTIONS:
        figs = [f for f in doc.figures if f[0] == sec]
        if not figs:
            continue
        lines += [f"## {sec}", ""]
        for _, name, cap in figs:
            lines += [f"![{cap}]({name})", "", f"*{cap}*", ""]
    lines += ["## Tables", ""]
    for tt, header, rows, csv_name, note in doc.tables:
        if csv_name == "runs.csv":
            continue
        lines += [f"### {tt}", "", _md_table(header, rows), ""]
        lines += [(f"*{note}* " if note else "") + f"([{csv_name}]({csv_name}))", ""]
    lines += ["## Missing", ""]
    lines += [f"- {m}" for m in doc.missing] or ["Nothing: every figure could be drawn."]
    lines.append("")
    path = doc.out / "report.md"
    path.write_text("\n".join(lines))
    return path
