"""Figures, tables and a markdown report from finished runs.

    build_report(["runs/ft-rmomo-s0", "runs/ft-modumorph-s0"], "reports/ft")    # -> reports/ft/report.md
    python -m experiments.report runs=[runs/ft-rmomo-s0,runs/ft-modumorph-s0] out=reports/ft

Inputs, per run directory (read only, see `mjx_morph.eval.runs`): `config.yaml`, `metrics.csv` and `eval/<tag>.json`
of `mjx_morph.eval.evaluate` (any of them but config.yaml may be missing: what needs it is left out and listed in the
report's "Missing" section).

Runs are grouped by task (`env.task`), name (the architecture, plus the training settings that differ among the
runs of one task and architecture, e.g. "rmomo, scale_after_cell=true": `runs.name_variants`) and kind
(`runs.classify`):
- main: all train robots (`num_robots` null; if no run of the task has that, the task's largest num_robots) and
  all context features (`context_features` absent, null or every group); seeds of a task and architecture pool;
- size: all context features and another `num_robots` (training-set-size runs); in the size figure a full-set
  run stands at its robot count (the `robots` of its eval/train.json, else 100) unless a run names that count;
- context: `context_features` a list of kept groups (single-context-feature runs) at the main robot count,
  compared with the main runs.

Statistics (`mjx_morph.eval.stats`): the per-robot mean returns of eval/<tag>.json are averaged over the seeds of a
group (over the seeds that evaluated the robot), and mean and 95% CI (`ci95`, Student t) are taken over robots;
normalised returns use `normalised` (the paper's per-task range) and are pooled across tasks as (task, robot)
pairs, per set over the tasks that every architecture evaluated on that set has. Learning curves: each seed's
episode return against env steps, lightly smoothed, interpolated onto a common grid; mean and 95% CI over the seeds
covering each grid point (no band with one seed).

Claims (`CLAIMS`, the paper's claims as data): per task, each model against its baseline on one eval set, on the
main runs of the groups named exactly by the architecture (so not the arms of an A/B study, e.g. "rmomo,
precision=bf16"), with seeds as the samples and the verdict rule of `stats.claim_test`; a claim that a side has no
eval/<set>.json for is listed under "Missing" (unless neither model ran the task). Policies are compared at one
point of training: where a model's seeds were evaluated at different env steps (the checkpoint of eval/<set>.json),
the claim takes the evaluations at the steps both models have most seeds at (`stats.common_eval_steps`) and names
the others under "Missing"; the per-robot differences take the same evaluations (the returns table and its bars
pool every step, and say so). The training claims are also tested on the learning curves (set "training",
`TRAINING_CLAIMS`: each seed's last ~5% of iterations in metrics.csv, runs at the furthest env steps; where some
runs stopped short, also set "training_all": every run, at the env steps all of them reached). A comparison looked
at k times as seeds came in takes Bonferroni's bar (`stats.claim_test`'s looks); `Looks` gives each claim model, or
task and model, its own k, so one report over every run on file gives every claim its verdict; `claims.png` draws
them all (difference in % of the baseline, CI, verdict).

A setting the paper chooses per model on the val robots (the KL threshold) is read off the arms of a study: "Chosen
on val" gives, per task and architecture with two or more arms evaluated on val, the arm with the higher mean val
return and whether the seeds separate it from the runner-up (Welch). "A/B arms" sets every pair of a study's arms
side by side, on training and each eval set: the difference over seeds with its Welch CI and p, and how many of one
arm's seeds lie within the other's range (a description, no verdict). "Rates per phase" gives each run's env steps/s
(rollout, update, end to end) over the iterations that ran all epochs, over those the KL stop cut short and over
the whole run without its calls' compiling iterations (`Run.phase_rates`), the figures docs/benchmarks.md records of
each lease's runs. "Health" gives each run's bookkeeping checks (`Run.health`: the first minibatch's ratio and KL
after each rollout, unstable episodes, non-finite metrics, the physics of each call), each with a flag where a
reader should look before trusting its returns.

The report is the sections of `SECTIONS`, in order: each is a function (document, context) that adds figures
(under its heading), tables and missing items to the `document.Document`; `build_report` reads the runs, makes the
context and walks the list.

Outputs in `out/`: PNG figures, CSV tables and `report.md` (runs, figures with captions, tables, missing).
"""
from __future__ import annotations

import math
import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np
import yaml

from ..nets import ARCHS
from ..run import unhealthy_reason
from ..unimal.variants import CHANGE_TYPES
from . import plots
from .document import Document, fmt, fmt_steps, pm, write_csv
from .params import param_count
from .runs import CONTEXT_GROUPS, Run, classify, find_run_dirs, name_variants, read_run
from .stats import (CLAIM_MARGIN, CLAIM_POWER, TASK_RANGES, Stat, change_stats, ci95, ci_level, claim_test,
                    common_eval_steps, eval_steps_of, furthest_mean_curve, mean_curve, normalised_or_nan,
                    repeated_seeds, robot_difference, seed_average, seed_count, seed_set_means, seed_train_means,
                    set_stat, stat_of, welch_ci, welch_p_two_sided)

SETS = ("train", "test", "val", "variants")
TASK_ORDER = tuple(TASK_RANGES)
DEFAULT_COMPARE = ("rmomo", "modumorph")


@dataclass(frozen=True)
class Claim:
    """A claim of the paper: `model` against `baseline` on the eval set `set`; kind "better" (a gain) or "level" (at
    least as well: non-inferiority within the margin), as `stats.claim_test` reads them."""
    model: str
    baseline: str
    set: str
    kind: str
    text: str

    @property
    def short(self) -> str:
        """The claim in a few words, for a figure's labels: "R-MoMo > ModuMorph" ("≥": at least as well)."""
        return f"{PAPER_NAMES[self.model]} {'>' if self.kind == 'better' else '≥'} {PAPER_NAMES[self.baseline]}"


#: The paper's names of the architectures the claims compare.
PAPER_NAMES = {"metamorph": "MetaMorph", "modumorph": "ModuMorph", "rmemo": "R-MeMo", "rmomo": "R-MoMo"}

CLAIMS: tuple[Claim, ...] = (
    Claim("rmomo", "modumorph", "train", "level", "R-MoMo trains at least as well as ModuMorph"),
    Claim("rmemo", "metamorph", "train", "level", "R-MeMo trains at least as well as MetaMorph"),
    Claim("rmomo", "modumorph", "test", "better", "R-MoMo beats ModuMorph zero-shot on unseen topologies"),
    Claim("rmemo", "metamorph", "test", "better", "R-MeMo beats MetaMorph zero-shot on unseen topologies"),
    Claim("rmomo", "modumorph", "variants", "better", "R-MoMo beats ModuMorph zero-shot on dynamics/kinematics "
                                                      "variants"),
    Claim("rmemo", "metamorph", "variants", "better", "R-MeMo beats MetaMorph zero-shot on dynamics/kinematics "
                                                      "variants"),
)

#: The models the claims are about; `Looks` keys name them.
CLAIM_MODELS: tuple[str, ...] = tuple(dict.fromkeys(c.model for c in CLAIMS))


@dataclass(frozen=True)
class Looks:
    """How many times each claim's comparison has been looked at as seeds came in (`stats.claim_test`'s `looks`):
    `per["<task>/<model>"]` for one task's claims of a model, else `per["<model>"]` for its claims on every task,
    else `default`. A report over several tasks and models, each looked at its own number of times, then gives every
    claim its own Bonferroni bar: `Looks.parse({"ft/rmomo": 5, "rmemo": 3})`."""
    default: int = 1
    per: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def parse(cls, looks) -> "Looks":
        """From a whole number (every claim) or a mapping of "<model>" / "<task>/<model>" keys to whole numbers
        (unlisted claims: one look); ValueError naming the key and what was expected."""
        if isinstance(looks, Looks):
            return looks
        if not isinstance(looks, Mapping):
            ci_level(looks)
            return cls(int(looks))
        per = {}
        for key, k in looks.items():
            parts = str(key).split("/")
            task, model = (None, parts[0]) if len(parts) == 1 else (parts[0], parts[-1])
            if len(parts) > 2 or model not in CLAIM_MODELS or (task is not None and task not in TASK_ORDER):
                raise ValueError(f"looks: key {key!r}: expected a claim's model ({', '.join(CLAIM_MODELS)}) or "
                                 f"<task>/<model> with a task of {', '.join(TASK_ORDER)}, e.g. ft/rmomo")
            try:
                ci_level(k)
            except ValueError as e:
                raise ValueError(f"looks: key {key!r}: {e}") from None
            per[str(key)] = int(k)
        return cls(1, per)

    def of(self, task: str, model: str) -> int:
        """The looks of `model`'s claims on `task`."""
        return self.per.get(f"{task}/{model}", self.per.get(model, self.default))


#: The training claims read off the learning curves too (set "training"): each seed's final training return, the mean
#: episode return of its last ~5% of iterations (metrics.csv), for the runs of both models that reached the furthest
#: env steps any of them reached (a run cut short is at another point of the schedule).
TRAINING = "training"
#: ... and, where some runs stopped short of the others (a lost call), once more at the env steps that every run of
#: both models reached (set "training_all"): each run's last ~5% of the iterations up to there, so no seed drops out.
TRAINING_ALL = "training_all"
TRAINING_CLAIMS: tuple[Claim, ...] = tuple(c for c in CLAIMS if c.set == "train")


@dataclass
class ReportContext:
    """What the sections draw from."""
    runs: list[Run]                                   # every run read, in the order found
    tasks: list[str]                                  # the runs' tasks, in report order
    main: dict[str, dict[str, list[Run]]]             # task -> arch (in report order) -> its main runs (seeds)
    compare: tuple[str, ...]                          # the architectures to compare robot by robot
    looks: Looks = field(default_factory=Looks)       # how many times each claim's comparison was looked at
    param_counts: dict[str, int] = field(default_factory=dict)   # param_count's memo, for this report only


def _order_archs(names: Iterable[str]) -> list[str]:
    """Run names in report order: by architecture (the zoo's order), then by variant."""
    base = lambda n: n.split(",", 1)[0]
    return sorted(set(names), key=lambda n: (ARCHS.index(base(n)) if base(n) in ARCHS else len(ARCHS), base(n), n))


def _order_tasks(tasks: Iterable[str]) -> list[str]:
    tasks = set(tasks)
    return [t for t in TASK_ORDER if t in tasks] + sorted(t for t in tasks if t not in TASK_ORDER)


def _display(p: Path) -> str:
    try:
        rel = os.path.relpath(p)
        return rel if not rel.startswith("..") else str(p)
    except ValueError:
        return str(p)


# ---- the sections ----------------------------------------------------------------------------------------------
def _runs_table(doc: Document, ctx: ReportContext) -> None:
    runs = ctx.runs
    header = ["run", "task", "arch", "seed", "kind", "num_robots", "context_features", "iterations", "env_steps",
              "device", "physics", "physics_computed", "wall_h", "h_per_100M", "mean_sps", "final_train_return",
              "evals"]
    rows, md = [], []
    for r in runs:
        label = r.context_label
        evals = ", ".join(sorted(r.evals)) or "none"
        device = " + ".join(r.devices) or "?"
        rows.append([_display(r.path), r.task, r.name, r.seed, r.kind, r.num_robots if r.num_robots else "all", label,
                     r.iterations, r.final_steps, device, " ".join(r.physics), r.physics_computed or "",
                     r.wall_hours(), r.hours_per_100m(),
                     r.mean_sps(), r.final_train_return(), evals])
        md.append([f"`{_display(r.path)}`", r.task, r.name, r.seed, r.kind, r.num_robots or "all", label, r.iterations,
                   fmt_steps(r.final_steps), device, _physics_label(r), fmt(r.wall_hours(), 2),
                   fmt(r.hours_per_100m(), 2), fmt(r.mean_sps(), 0), fmt(r.final_train_return()), evals])
    doc.table("Runs", "runs", header, rows,
              ["run", "task", "arch", "seed", "kind", "robots", "context", "iterations", "env steps", "device",
               "physics", "wall h", "wall h / 100 M steps", "mean steps/s", "final train return", "evals"], md,
              note="final train return: mean episode return of the last ~5% of iterations; wall h / 100 M steps: "
                   "sum(wall_s) / final env steps x 1e8, on the run's device (devices.yaml; ?: not recorded), so "
                   "compare it only between runs of one device; mean steps/s excludes the first iteration "
                   "(compilation); physics: the first 8 digits of the model digest the run trained on (devices.yaml: "
                   "the stacked MJX model and the robots' constants, `UnimalEnv.digest`; –: not recorded, runs "
                   "before session 45; a → b: resumed onto other physics; a*: not recorded, computed afterwards "
                   "from the run's config by a checkout with the run's physics code, physics.yaml).",
              lead=True)


def _physics_label(r: Run, none: str = "–", mark: str = "*") -> str:
    """The physics a run trained on, as its model digests' first 8 digits; for a run that recorded none, the digest
    computed afterwards (physics.yaml) followed by `mark`; `none` where there is neither."""
    if r.physics:
        return " → ".join(d[:8] for d in r.physics)
    return r.physics_computed[:8] + mark if r.physics_computed else none


def _physics_mix(runs_of: dict[str, list[Run]]) -> str:
    """'' when every run of the groups trained on one recorded physics; else how the groups' runs spread over the
    physics (first 8 digits of the model digest; 'not recorded' for runs before session 45)."""
    label = {a: [_physics_label(r, "not recorded", mark="") for r in rs] for a, rs in runs_of.items()}
    if len({x for xs in label.values() for x in xs}) <= 1:
        return ""
    return "; ".join(f"{a}: " + ", ".join(f"{xs.count(x)} {x}" for x in dict.fromkeys(xs)) for a, xs in label.items())


#: below this many seeds a learning curve shows each seed (thin) instead of a 95% CI band (t = 12.7 with 2 seeds)
BAND_MIN_SEEDS = 3


def _learning_curves(doc: Document, ctx: ReportContext) -> None:
    tasks, main = ctx.tasks, ctx.main
    for t in tasks:
        curves, labels, members, tails = {}, {}, {}, {}
        for a, rs in main[t].items():
            cs = [(r.metrics["env_steps"], r.metrics["episode_return"]) for r in rs
                  if "env_steps" in r.metrics and "episode_return" in r.metrics]
            grid, m, lo, hi, n = mean_curve(cs)
            if grid.size:
                banded = len(cs) >= BAND_MIN_SEEDS
                curves[a] = (grid, m, lo if banded else None, hi if banded else None)
                # each seed thin below BAND_MIN_SEEDS, and wherever some seed ends early (the mean ends with it)
                thin = len(cs) >= 2 and (not banded or n.min() < len(cs))
                members[a] = [mean_curve([c])[:2] for c in cs] if thin else []
                labels[a] = f"{a} ({len(cs)} seed{'s' if len(cs) != 1 else ''})"
                far = furthest_mean_curve(cs)   # past the common end: the seeds that reach furthest, dashed
                if far is not None:
                    g, fm, flo, fhi, k = far
                    band = k >= BAND_MIN_SEEDS
                    tails[a] = (g, fm, flo if band else None, fhi if band else None,
                                f"{a}: the {k} seeds that reach {fmt_steps(g[-1])}")
        if not curves:
            doc.missing.append(f"{t}: learning curves — no main run has episode returns in metrics.csv")
            continue
        p = plots.mean_curves(curves, doc.out / f"learning_curve_{t}.png", title=f"{t}: training return",
                              labels=labels, members=members, tails=tails)
        doc.figure(p, f"{t}: mean training episode return against env steps, mean over seeds where all of them "
                      f"reach (band: 95% CI from {BAND_MIN_SEEDS} seeds; with 2 seeds, or seeds of unequal length, "
                      f"each seed as a thin line; dashed, where some seeds end early: the mean of those that reach "
                      f"furthest, the claims' set 'training'; main runs: all train robots and context features).")


def _set_cell(x: Stat | None, seeds: int) -> str:
    """A returns-table cell: mean ± CI (normalised), and how many of the row's seeds evaluated the set when not all."""
    if x is None:
        return "–"
    part = f" [{x.seeds} of {seeds} seeds]" if x.seeds != seeds else ""
    return f"{pm(x.mean, x.ci)} ({pm(x.norm, x.norm_ci, 3)}){part}"


def _returns(doc: Document, ctx: ReportContext) -> None:
    tasks, main = ctx.tasks, ctx.main
    header = ["task", "arch", "seeds"]
    for s in SETS:
        header += [f"{s}_return", f"{s}_ci95", f"{s}_normalised", f"{s}_normalised_ci95", f"{s}_robots", f"{s}_seeds"]
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
            for s in SETS:
                by_steps = eval_steps_of(rs, s)
                if len(by_steps) > 1:
                    doc.missing.append(
                        f"{t}, {a}: {s} evaluated at different env steps ("
                        + ", ".join(f"{fmt_steps(x) if x is not None else 'unknown'}: {len(v)} run(s)"
                                    for x, v in by_steps.items())
                        + "); the returns and their bars pool them, the per-robot differences and the claims "
                          "compare the steps both models have most seeds at")
            seeds = seed_count(rs)
            row, mrow = [t, a, seeds], [t, a, seeds]
            for s in SETS:
                x = st[s]
                row += [x.mean, x.ci, x.norm, x.norm_ci, x.robots, x.seeds] if x else [float("nan")] * 4 + [0, 0]
                if x:
                    present.add(s)
            rows.append(row)
            md.append(mrow + [_set_cell(st[s], seeds) for s in SETS])
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
        doc.figure(p, f"{t}: mean return per robot set{per_change}"
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
                  [[t, a, c, s, n, pm(m, ci), pm(nm, nci, 3)] for t, a, c, s, n, m, ci, nm, nci in change_rows])
    # normalised returns pooled across tasks: per set, over the tasks on which every architecture evaluated on that
    # set has results, so that no architecture's mean takes in a task the others lack (a harder task would sink it)
    archs = _order_archs(a for t in tasks for a in main[t])
    per_task: dict[tuple[str, str, str], list[float]] = {}
    for a in archs:
        for s in SETS:
            for t in tasks:
                pr = seed_average(main[t].get(a, []), s)
                if pr and t in TASK_RANGES:
                    per_task[a, s, t] = normalised_or_nan(list(pr.values()), t).tolist()
    pooled: dict[str, dict[str, Stat]] = {}
    set_tasks: dict[str, list[str]] = {}        # per set, the tasks pooled
    left_out: list[str] = []
    for s in SETS:
        with_s = [a for a in archs if any((a, s, t) in per_task for t in tasks)]
        common = [t for t in tasks if with_s and all((a, s, t) in per_task for a in with_s)]
        left_out += [f"{t} on {s} (results of {', '.join(a for a in with_s if (a, s, t) in per_task)} only)"
                     for t in tasks if t not in common and any((a, s, t) in per_task for a in with_s)]
        if not common:
            continue
        set_tasks[s] = common
        for a in with_s:
            vals = [v for t in common for v in per_task[a, s, t]]
            pooled.setdefault(a, {})[s] = stat_of(vals, None, 0, norm_values=vals)
    pooled_tasks = {a: [t for t in tasks if any(t in set_tasks[s] for s in pooled[a])] for a in pooled}
    if left_out:
        doc.missing.append("pooled normalised returns — tasks left out of the pool because not every architecture "
                           "has them: " + "; ".join(left_out))
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
    tasks_note = "; ".join(f"{s}: {', '.join(ts_)}" for s, ts_ in set_tasks.items())
    doc.figure(p, f"Normalised return pooled across tasks ((task, robot) pairs, seed-averaged), 95% CI; per set, the "
                  f"tasks every architecture evaluated on it has: {tasks_note}.")
    prow, pmd = [], []
    for a in pooled:
        row, mrow = [a, " ".join(pooled_tasks[a])], [a, ", ".join(pooled_tasks[a])]
        for s in SETS:
            x = pooled[a].get(s)
            row += [x.norm, x.norm_ci, x.robots] if x else [float("nan"), float("nan"), 0]
            mrow.append(pm(x.norm, x.norm_ci, 3) if x else "–")
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


def _robot_differences(doc: Document, ctx: ReportContext) -> None:
    tasks, main, compare = ctx.tasks, ctx.main, ctx.compare
    summary, pairs, at_common_steps = [], {}, {}
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
        runs_a, runs_b = at_common_steps[t] = _at_common_steps(main[t][a], main[t][b], "test")
        rows = robot_difference(runs_a, runs_b, "test")
        if not rows:
            doc.missing.append(f"{t}: per-robot difference — {a} and {b} have no test robot in common")
            continue
        write_csv(doc.out / f"robot_diff_{t}.csv", ["robot", f"{a}_return", f"{b}_return", "difference"], rows)
        d = np.array([r[3] for r in rows])
        p = plots.robot_difference([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], a, b,
                                   doc.out / f"robot_diff_{t}.png", title=f"{t}: per-robot test return, {a} vs {b}")
        doc.figure(p, f"{t}: per-robot test return of {a} minus {b} (seed-averaged), sorted; "
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
                         for n, va, vb, d in robot_difference(*at_common_steps[t], "test", t)]
        rows.sort(key=lambda r: (-r[3], r[0]))
        write_csv(doc.out / "robot_diff_pooled.csv", ["task:robot", f"{a}_normalised", f"{b}_normalised",
                                                        "difference"], rows)
        d = np.array([r[3] for r in rows])
        p = plots.robot_difference([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], a, b,
                                   doc.out / "robot_diff_pooled.png", unit="normalised test return",
                                   title=f"all tasks: per-robot normalised test return, {a} vs {b}")
        doc.figure(p, f"All tasks: per-(task, robot) normalised test return of {a} minus {b}, "
                      "sorted; right: both in the same order (data: robot_diff_pooled.csv).")
        summary.append(["pooled (normalised)", a, b, len(rows), float(d.mean()), ci95(d), int((d > 0).sum()),
                        "robot_diff_pooled.csv"])
    if summary:
        doc.table("Per-robot test differences", "robot_diff",
                  ["task", "a", "b", "robots", "mean_difference", "ci95", "robots_a_better", "data"], summary,
                  ["task", "a", "b", "robots", "mean a − b", "a better on", "per-robot data"],
                  [[t, a, b, n, pm(m, ci, 3 if t.startswith("pooled") else 1), f"{k}/{n}", f"[{f}]({f})"]
                   for t, a, b, n, m, ci, k, f in summary])


def _at_common_steps(runs_a: list[Run], runs_b: list[Run], tag: str) -> tuple[list[Run], list[Run]]:
    """The runs of two groups evaluated on `tag` at the env steps `common_eval_steps` picks, as the claims compare
    them (all of them where the groups share no step)."""
    at = common_eval_steps(runs_a, runs_b, tag)
    return (runs_a, runs_b) if at is None else (at[1], at[2])


def _interval(d: float, lo: float, hi: float) -> str:
    """"+d [+lo, +hi]" with one decimal ("+d" without a CI)."""
    if not math.isfinite(d):
        return "–"
    return f"{d:+.1f} [{lo:+.1f}, {hi:+.1f}]" if math.isfinite(lo) else f"{d:+.1f}"


def _claims(doc: Document, ctx: ReportContext) -> None:
    """The CLAIMS table: each claim per task with both sides' main runs evaluated on its set; the rest missing."""
    rows, md, tested = [], [], []
    claim_archs = {a for c in CLAIMS for a in (c.model, c.baseline)}
    for t in ctx.tasks:
        main, untested = ctx.main[t], []
        # the claims of a model (or an A/B arm of one) that ran this task; the others are for another report
        ran = {group.split(",", 1)[0] for group in main}
        eval_claims, training_claims = ([c for c in claims if {c.model, c.baseline} & ran]
                                        for claims in (CLAIMS, TRAINING_CLAIMS))
        # (claim, set, model's seed means, baseline's, env steps: of the evaluations compared, or a training row's
        # point; nan where the eval files do not say)
        sides = [_eval_claim_sides(doc, t, main, c) for c in eval_claims]
        for c in training_claims:
            both = [r for a in (c.model, c.baseline) for r in main.get(a, []) if math.isfinite(r.final_train_return())]
            reached = sorted({r.final_steps for r in both}) or [math.nan]     # nan: no runs, listed as untested
            points = {TRAINING: reached[-1], **({TRAINING_ALL: reached[0]} if len(reached) > 1 else {})}
            sides += [(c, set_name, seed_train_means(main.get(c.model, []), at),
                       seed_train_means(main.get(c.baseline, []), at), at, None) for set_name, at in points.items()]
        for c, set_name, a, b, at, why in sides:
            if why or not a or not b:
                untested.append(f"{c.text} ({set_name}: "
                                + (why or f"{c.model} {len(a)}, {c.baseline} {len(b)} seeds") + ")")
                continue
            r = claim_test(a, b, c.kind, looks=ctx.looks.of(t, c.model))
            rows.append([t, c.model, c.baseline, c.text, c.kind, set_name, at, r.model_seeds, r.baseline_seeds,
                         r.model_mean, r.baseline_mean, r.difference, r.ci_low, r.ci_high, r.margin, r.relative,
                         r.verdict, r.p_value, r.seeds_for_power, r.level, r.looks])
            point = "to" if set_name in (TRAINING, TRAINING_ALL) else "at"
            label = f"{set_name} {point} {at / 1e6:.1f} M steps" if math.isfinite(at) else set_name
            md.append([t, c.text, label, f"{r.model_seeds}/{r.baseline_seeds}", fmt(r.model_mean),
                       fmt(r.baseline_mean), _interval(r.difference, r.ci_low, r.ci_high),
                       f"{r.relative:+.1f}%" if math.isfinite(r.relative) else "–", r.verdict,
                       _p(r.p_value), f"{r.seeds_for_power:.0f}" if math.isfinite(r.seeds_for_power) else "–",
                       r.looks])
            tested.append((t, c, label, r))
        mix = _physics_mix({a: main[a] for a in sorted(claim_archs & set(main))})
        if mix and sides:
            doc.missing.append(f"{t}: the claims compare runs of more than one physics (model digest; runs per "
                               f"physics): {mix}")
        for arch in sorted(claim_archs & set(main)):
            for seed, paths in repeated_seeds(main[arch]).items():
                doc.missing.append(f"{t}, {arch}: {len(paths)} runs of seed {seed} ({', '.join(paths)}) count as one "
                                   f"seed in the claims, their mean")
        if untested:
            arms = [a for a in main if a.split(",", 1)[0] in claim_archs and a not in claim_archs]
            doc.missing.append(f"{t}: claims untested — each needs eval/<set>.json (set training: metrics.csv) of "
                               f"main runs of both architectures: {'; '.join(untested)}"
                               + (f" (A/B arms are not compared: {'; '.join(arms)})" if arms else ""))
    if rows:
        m = f"{100 * CLAIM_MARGIN:g}%"
        ks = sorted({r.looks for *_, r in tested})
        if len(ks) == 1:                         # one number of looks: named once, in the header and the note
            k = ks[0]
            level, bar = f"{100 * ci_level(k):.4g}% CI", f"{0.025 / k:.4g}"
            looked = ("" if k == 1 else
                      f" The comparisons were looked at {k} times as seeds came in (looks={k}): the CIs are at "
                      f"{100 * ci_level(k):.4g}% and a claim is reproduced at p < 0.025 / {k} = {bar} (Bonferroni), so "
                      "that the looks together keep one look's 2.5% error rate.")
            md = [r[:-1] for r in md]
            looks_header = []
        else:                                    # each claim its own (the column looks)
            level, bar = "CI at 1 − 0.05 / looks", "0.025 / looks"
            looked = (" Each comparison was looked at as many times as seeds came in as its column looks says: its CI "
                      "is at 1 − 0.05 / looks and it is reproduced at p < 0.025 / looks (Bonferroni), so that the "
                      "looks together keep one look's 2.5% error rate.")
            looks_header = ["looks"]
        doc.table("Claims", "claims",
                  ["task", "model", "baseline", "claim", "kind", "set", "env_steps", "model_seeds", "baseline_seeds",
                   "model_mean", "baseline_mean", "difference", "ci95_low", "ci95_high", "margin",
                   "relative_difference_pct", "verdict", "p_one_sided", "seeds_for_power", "ci_level", "looks"], rows,
                  ["task", "claim", "set", "seeds (model/baseline)", "model mean", "baseline mean",
                   f"difference [{level}]", "relative difference", "verdict", "p (one-sided)",
                   f"seeds per side for {100 * CLAIM_POWER:g}% power", *looks_header], md,
                  note="per seed, the set's mean return over robots, of the evaluations at the env steps named (where "
                       "a model's seeds were evaluated at different steps, those at the steps both models have most "
                       "seeds at; the others are named under Missing) (set 'training': the mean episode return of "
                       "the last ~5% of iterations in metrics.csv, of the runs that reached the furthest env steps; "
                       "'training_all': of every run, up to the env steps that all of them reached); "
                       f"difference of the means over seeds, model − baseline, {level} from Welch's t; "
                       f"margin m = {m} of the baseline's mean. 'beats': reproduced if the CI lies above 0, not "
                       "reproduced if below m; 'at least as well': reproduced if above −m, not reproduced if below "
                       "0; otherwise inconclusive. p: Welch's one-sided p-value against the claim's bound (0 or −m): "
                       f"reproduced exactly when p < {bar}; where the data were looked at k times as seeds came in, "
                       "p < 0.025 / k keeps the claim (Bonferroni: the report's looks=k). Main runs of the groups "
                       "named by the architecture alone (A/B arms are not compared). Seeds per side for "
                       f"{100 * CLAIM_POWER:g}% power: how many seeds of each would reproduce the claim that often if "
                       "the observed difference and seed spreads held (normal approximation; – where the difference "
                       "does not clear the claim's bound)." + looked)
        _claims_figure(doc, tested, level)


def _claims_figure(doc: Document, tested: list, level: str) -> None:
    """Every tested claim's difference in percent of its baseline's mean, with its CI, coloured by verdict."""
    items = []
    for t, c, label, r in tested:
        scale = 100 / abs(r.baseline_mean) if r.baseline_mean else math.nan
        seeds = f"{r.model_seeds}/{r.baseline_seeds} seeds"
        items.append(dict(label=f"{t}: {c.short} ({label})", value=r.relative, lo=r.ci_low * scale,
                          hi=r.ci_high * scale, verdict=r.verdict,
                          note=f"{seeds}, p {_p(r.p_value)}" + (f", {r.looks} looks" if r.looks > 1 else "")))
    if not any(math.isfinite(i["value"]) for i in items):
        return
    bound = f"−{100 * CLAIM_MARGIN:g}%: the 'at least as well' bound"
    p = plots.intervals(items, doc.out / "claims.png", title="The paper's claims: model − baseline",
                        xlabel="difference in % of the baseline's mean", refs={0.0: "", -100 * CLAIM_MARGIN: bound})
    doc.figure(p, f"Each claim's difference of the seed means, model − baseline, in % of the baseline's mean, with "
                  f"its {level} (Welch, over seeds), coloured by verdict: 'beats' is reproduced where the CI lies "
                  f"above 0, 'at least as well' where it lies above −{100 * CLAIM_MARGIN:g}% (claims.csv).")


#: Where the seed-spread table reads the learning curves: these fractions of the env steps every main run of a task
#: reached.
SPREAD_POINTS = (0.25, 0.5, 0.75, 1.0)


def _seed_spread(doc: Document, ctx: ReportContext) -> None:
    """How widely the seeds of each main group spread in training, and whether that narrows as they learn: the
    standard deviation over seeds of the training return (`Run.train_return`, as the training claims read it) over
    its mean, at SPREAD_POINTS of the env steps every main run of the task reached. The power a claim has at a point
    of the schedule goes with this spread."""
    rows, md = [], []
    for t in ctx.tasks:
        reached = [r.final_steps for runs in ctx.main[t].values() for r in runs
                   if math.isfinite(r.final_train_return())]
        if not reached:
            continue
        shared = min(reached)
        for arch, runs in ctx.main[t].items():
            cells = []
            for f in SPREAD_POINTS:
                vals = np.asarray([v for v in seed_train_means(runs, f * shared) if math.isfinite(v)])
                if vals.size < 2:
                    break
                mean, sd = float(vals.mean()), float(vals.std(ddof=1))
                rel = sd / abs(mean) if mean else math.nan
                rows.append([t, arch, f * shared, vals.size, mean, sd, rel])
                cells.append(fmt(rel, 2))
            if len(cells) == len(SPREAD_POINTS):
                md.append([t, arch, rows[-1][3], fmt_steps(shared), *cells])
    if rows:
        doc.table("Seed spread in training", "seed_spread",
                  ["task", "arch", "env_steps", "seeds", "mean_train_return", "sd_over_seeds", "sd_over_mean"], rows,
                  ["task", "arch", "seeds", "steps every run reached", *(f"sd / mean at {100 * f:g}%"
                                                                         for f in SPREAD_POINTS)], md,
                  note="each seed's training return (the mean episode return of the last ~5% of the iterations up to "
                       "the point, as the training claims read it), its standard deviation over seeds divided by "
                       "the mean, at fractions of the env steps every main run of the task reached; main runs with "
                       "2 or more seeds. A spread that narrows as training goes on makes later comparisons need fewer "
                       "seeds.")


def _seeds_by_physics(doc: Document, ctx: ReportContext) -> None:
    """Where a task's main runs trained on more than one physics (model digests; runs before session 45 recorded
    none), each group's seeds split by physics: their mean training return and test and variants returns. A
    description beside the claims, which pool the physics; no test."""
    rows, md = [], []
    for t in ctx.tasks:
        if len({_physics_label(r, mark="") for runs in ctx.main[t].values() for r in runs}) < 2:
            continue
        for arch, runs in ctx.main[t].items():
            for label in dict.fromkeys(_physics_label(r, mark="") for r in runs):
                mine = [r for r in runs if _physics_label(r, mark="") == label]
                cells = [[v for v in vals if math.isfinite(v)] for vals in (
                    [r.final_train_return() for r in mine],
                    *([float(r.evals.get(tag, {}).get("mean_return", math.nan)) for r in mine]
                      for tag in ("test", "variants")))]
                means = [float(np.mean(c)) if c else math.nan for c in cells]
                seeds = ", ".join(f"{r.seed}{'*' if r.physics_computed else ''}" for r in mine)
                rows.append([t, arch, " ".join(mine[0].physics) or (mine[0].physics_computed or ""), seeds, *means,
                             *(len(c) for c in cells)])
                md.append([t, arch, _physics_label(mine[0], "not recorded", mark=""), seeds,
                           *(f"{fmt(m)} ({len(c)})" if c else "–" for m, c in zip(means, cells))])
    if rows:
        doc.table("Seeds by physics", "seeds_by_physics",
                  ["task", "arch", "physics", "seeds", "train_return", "test_return", "variants_return", "n_train",
                   "n_test", "n_variants"], rows,
                  ["task", "arch", "physics", "seeds", "train return (runs)", "test return (runs)",
                   "variants return (runs)"], md,
                  note="only where a task's main runs trained on more than one physics (the first 8 digits of the "
                       "model digest in devices.yaml; not recorded: runs before session 45; seed*: a run that "
                       "recorded none, its digest computed afterwards, physics.yaml): each group's runs per "
                       "physics, the mean over runs of the final train return and of the test and variants mean "
                       "returns. A description beside the claims, which pool the physics: no test.")


def _choice_on_val(doc: Document, ctx: ReportContext) -> None:
    """The paper's rule for a training setting chosen per model (the KL threshold, issue 15 part 3): the arm with the
    higher mean val return. For each task and architecture with two or more main groups that evaluated val (the
    arms of a study, e.g. "modumorph, kl_threshold=0.03" and "modumorph, kl_threshold=0.05"): each arm's mean over
    seeds of the seed's mean val return and the spread of those seeds; the arm the rule picks, its margin over the
    runner-up and the two-sided Welch p of that margin, so that a pick the seeds cannot tell apart reads as one."""
    rows, md = [], []
    for t in ctx.tasks:
        arms_of: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
        for name, runs in ctx.main[t].items():
            vals = np.asarray([v for v in seed_set_means(runs, "val") if math.isfinite(v)])
            if vals.size:
                arms_of[runs[0].arch][name] = vals
        for base, arms in arms_of.items():
            if len(arms) < 2:
                continue
            order = sorted(arms, key=lambda n: -float(arms[n].mean()))
            best, second = arms[order[0]], arms[order[1]]
            p = welch_p_two_sided(best, second)
            margin = float(best.mean() - second.mean())
            for n in order:
                v, chosen = arms[n], n == order[0]
                sd = float(v.std(ddof=1)) if v.size > 1 else math.nan
                rows.append([t, base, n, v.size, float(v.mean()), sd, chosen, margin if chosen else math.nan,
                             p if chosen else math.nan])
                md.append([t, base, n, v.size, fmt(float(v.mean())), fmt(sd), "**chosen**" if chosen else "",
                           f"{fmt(margin)} ({100 * margin / abs(float(second.mean())):+.1f}%)" if chosen else "",
                           _p(p) if chosen else ""])
    if rows:
        doc.table("Chosen on val", "choice_on_val",
                  ["task", "arch", "arm", "seeds", "val_return", "sd_over_seeds", "chosen", "margin", "p_two_sided"],
                  rows, ["task", "arch", "arm", "seeds", "val return (mean over seeds)", "sd over seeds", "rule",
                         "margin over the runner-up", "p (two-sided)"], md,
                  note="per architecture, the arm with the higher mean val return (the paper's rule for the KL "
                       "threshold); each seed's val return is its mean over the val robots; p: Welch's t over "
                       "seeds of the chosen arm against the runner-up. A large p says the seeds do not separate "
                       "the arms: the rule's pick is then a tie broken by noise.")


def _arm_sides(runs_a: list[Run], runs_b: list[Run]) -> list[tuple[str, float | None, list[float], list[float]]]:
    """(set, env steps, seed values of a, of b) for two arms: "training" at the env steps every run of both with a
    learning curve reached (`seed_train_means`), and each eval set both evaluated, at the steps `common_eval_steps`
    picks."""
    sides = []
    reached = [r.final_steps for r in runs_a + runs_b if math.isfinite(r.final_train_return())]
    if reached:
        steps = min(reached)
        sides.append(("training", steps, seed_train_means(runs_a, steps), seed_train_means(runs_b, steps)))
    for tag in SETS:
        at = common_eval_steps(runs_a, runs_b, tag)
        if at is not None:
            sides.append((tag, at[0], seed_set_means(at[1], tag), seed_set_means(at[2], tag)))
    return sides


def _arms(doc: Document, ctx: ReportContext) -> None:
    """The arms of an A/B study side by side: for each task and architecture with two or more main groups (e.g.
    "metamorph, iterations=16" and "metamorph, iterations=5"), every pair of arms, first minus second in the report's
    order, on training and on each eval set both evaluated (`_arm_sides`): seeds, means over seeds, the difference
    with its 95% Welch CI over seeds and the two-sided p, and how many of the first arm's seeds lie below, within and
    above the second arm's seed range (issue 13's test of a fast mode, "within the seed spread", read as "no seed
    below it": docs/leases.md, plan item 4); then the non-inferiority test the claims' training claims use (the
    first arm at least the second's mean less CLAIM_MARGIN of it: one-sided Welch p) and the seeds a side it would
    need for CLAIM_POWER at the observed difference and spreads, which a seed-range rule cannot show at any seed
    count. A description with no verdict: the claims section tests the paper's claims, which compare architectures,
    not arms."""
    rows, md = [], []
    for t in ctx.tasks:
        names_of: dict[str, list[str]] = defaultdict(list)
        for name, runs in ctx.main[t].items():
            names_of[runs[0].arch].append(name)
        for names in names_of.values():
            for i, a in enumerate(names):
                for b in names[i + 1:]:
                    for tag, steps, va, vb in _arm_sides(ctx.main[t][a], ctx.main[t][b]):
                        va = np.asarray([v for v in va if math.isfinite(v)])
                        vb = np.asarray([v for v in vb if math.isfinite(v)])
                        if not (va.size and vb.size):
                            continue
                        d = float(va.mean() - vb.mean())
                        lo, hi = welch_ci(va, vb)
                        p = welch_p_two_sided(va, vb)
                        rel = 100 * d / abs(float(vb.mean())) if vb.mean() else math.nan
                        below, above = int((va < vb.min()).sum()), int((va > vb.max()).sum())
                        inside = va.size - below - above
                        level = claim_test(va, vb, "level")          # a no worse than b less CLAIM_MARGIN of it
                        p_level, n_level = level.p_value, level.seeds_for_power
                        rows.append([t, a, b, tag, steps if steps is not None else math.nan, va.size, vb.size,
                                     float(va.mean()), float(vb.mean()), d, lo, hi, rel, p, below, inside, above,
                                     p_level, n_level])
                        md.append([t, f"{a} − {b}", tag, f"{va.size} / {vb.size}", fmt(float(va.mean())),
                                   fmt(float(vb.mean())), _interval(d, lo, hi),
                                   f"{rel:+.1f}%" if math.isfinite(rel) else "–", _p(p),
                                   f"{below} / {inside} / {above} of {va.size} ({fmt(float(vb.min()))} to "
                                   f"{fmt(float(vb.max()))})", _p(p_level),
                                   f"{n_level:.0f}" if math.isfinite(n_level) else "–"])
    if rows:
        doc.table("A/B arms", "arms",
                  ["task", "arm_a", "arm_b", "set", "env_steps", "seeds_a", "seeds_b", "mean_a", "mean_b",
                   "difference", "ci95_low", "ci95_high", "relative_pct", "p_two_sided", "a_seeds_below_b_range",
                   "a_seeds_in_b_range", "a_seeds_above_b_range", "p_a_not_worse", "seeds_for_not_worse"], rows,
                  ["task", "arms (a − b)", "set", "seeds a / b", "a", "b", "difference [95% CI]", "relative", "p",
                   "a's seeds below / in / above b's range", f"p, a ≥ b − {CLAIM_MARGIN:.0%}",
                   f"seeds a side for it ({CLAIM_POWER:.0%})"], md,
                  note="per task and architecture with two or more arms (main groups told apart by a setting), each "
                       "pair: each seed's training return (the mean episode return of the last ~5% of the "
                       "iterations up to the env steps every run of the pair reached) or mean return over a set's "
                       "robots (at the env steps both evaluated, as the claims take them); means over seeds, the "
                       "difference with its 95% Welch CI over seeds (none with fewer than 2 seeds a side), the "
                       "two-sided Welch p, and how many of a's seeds fall below, within and above b's seed range "
                       "(a fast mode passes where none of its training seeds is below: docs/leases.md, plan item "
                       f"4); then the one-sided Welch p that a's mean is at least b's less {CLAIM_MARGIN:.0%} of it "
                       "(the training claims' test: a match shown where p < 0.025) and the seeds a side that test "
                       f"would need for {CLAIM_POWER:.0%} power at the observed difference and spreads (– where the "
                       "data point the other way). A description: no verdict.")


def _eval_claim_sides(doc: Document, task: str, main: dict[str, list[Run]], c: Claim) -> tuple:
    """(claim, set, model's seed means, baseline's, env steps evaluated (nan: the files do not say), why untested or
    None) of an eval-set claim: the evaluations at the env steps `common_eval_steps` picks; those at other steps are
    named under Missing. Untested where both models evaluated the set but at no env steps in common."""
    runs = {a: main.get(a, []) for a in (c.model, c.baseline)}
    at = common_eval_steps(runs[c.model], runs[c.baseline], c.set)
    if at is None:
        have = {a: [fmt_steps(x) for x in eval_steps_of(rs, c.set) if x is not None] for a, rs in runs.items()}
        why = (f"evaluated at different env steps, {c.model} {', '.join(have[c.model])}, {c.baseline} "
               f"{', '.join(have[c.baseline])}" if all(have.values()) else None)
        return (c, c.set, seed_set_means(runs[c.model], c.set), seed_set_means(runs[c.baseline], c.set), math.nan,
                why)
    steps, ra, rb = at
    left = [r for rs in runs.values() for r in rs if c.set in r.evals and r.eval_steps(c.set) != steps]
    if left:
        doc.missing.append(f"{task}: {c.text} compares the {c.set} evaluations at {fmt_steps(steps or math.nan)} env "
                           "steps; left out, evaluated at other steps: "
                           + ", ".join(f"{_display(r.path)} ({fmt_steps(r.eval_steps(c.set) or math.nan)})"
                                       for r in left))
    return (c, c.set, seed_set_means(ra, c.set), seed_set_means(rb, c.set), math.nan if steps is None else steps,
            None)


def _p(p: float) -> str:
    """A p-value for the tables: two significant digits, '<0.0001' below that, '–' for nan."""
    if not math.isfinite(p):
        return "–"
    return "<0.0001" if p < 1e-4 else f"{p:.2g}"


def _mean_trace(traces: list[list]) -> np.ndarray | None:
    traces = [np.asarray(x, float) for x in traces if x]
    if not traces:
        return None
    n = min(x.size for x in traces)
    return np.mean([x[:n] for x in traces], axis=0)


def _reward_per_step(doc: Document, ctx: ReportContext) -> None:
    tasks, main = ctx.tasks, ctx.main
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
        doc.figure(p,
                   f"{t}: mean reward at each of the first {len(next(iter(series.values()))[0])} steps over all test "
                   f"episodes (0 after an episode ended)"
                   + (f"; dashed: recurrent state held at 0 for the first {zs} steps"
                      + (" (dotted marker)" if zs and zs < len(next(iter(series.values()))[0]) else "") if rec else "")
                   + "; lower panel: fraction of episodes still running.")


def _train_size(doc: Document, ctx: ReportContext) -> None:
    tasks, runs = ctx.tasks, ctx.runs
    rows, md = [], []
    for t in tasks:
        cand = [r for r in runs if r.task == t and r.context is None and "test" in r.evals]
        if not any(r.kind == "size" for r in cand):
            doc.missing.append(f"{t}: training-set-size figure — no runs with all context features, eval/test.json "
                               "and a num_robots other than the main runs'")
            continue
        series = {}
        for a in _order_archs(r.name for r in cand):
            mine = [r for r in cand if r.name == a]
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
                md.append([t, a, x, s.seeds, s.robots, pm(s.mean, s.ci), pm(s.norm, s.norm_ci, 3)])
        if not series:
            doc.missing.append(f"{t}: training-set-size figure — no architecture has test results at two robot "
                               "counts")
            continue
        p = plots.errorbar_lines(series, doc.out / f"train_size_{t}.png", title=f"{t}: training-set size",
                                 xlabel="train robots", ylabel="mean test return")
        doc.figure(p, f"{t}: test return (mean ± 95% CI over robots, seed-averaged) against the "
                      "number of train robots.")
    if rows:
        doc.table("Training-set size", "train_size",
                  ["task", "arch", "num_robots", "seeds", "test_robots", "test_return", "ci95", "normalised",
                   "normalised_ci95"], rows,
                  ["task", "arch", "train robots", "seeds", "test robots", "test return", "normalised"], md)


def _context_features(doc: Document, ctx: ReportContext) -> None:
    tasks, runs, main = ctx.tasks, ctx.runs, ctx.main
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
        archs = _order_archs(r.name for r in ctx_runs)
        series, refs = {}, {}
        for a in archs:
            ms, cs = [], []
            for lab in labels:
                sel = [r for r in ctx_runs if r.name == a and r.context_label == lab]
                s = set_stat(sel, "test", t) if sel else None
                ms.append(s.mean if s else np.nan)
                cs.append(s.ci if s else np.nan)
                if s:
                    rows.append([t, a, lab, s.seeds, s.robots, s.mean, s.ci, s.norm, s.norm_ci])
                    md.append([t, a, lab, s.seeds, pm(s.mean, s.ci), pm(s.norm, s.norm_ci, 3)])
            series[a] = (ms, cs)
            ref = set_stat(main[t].get(a, []), "test", t)
            if ref:
                refs[a] = ref.mean
                rows.append([t, a, "all", ref.seeds, ref.robots, ref.mean, ref.ci, ref.norm, ref.norm_ci])
                md.append([t, a, "all", ref.seeds, pm(ref.mean, ref.ci), pm(ref.norm, ref.norm_ci, 3)])
            else:
                doc.missing.append(f"{t}: single-context-feature figure — no all-features reference for {a} "
                                   "(no main run with eval/test.json)")
        p = plots.bar_panels([{"groups": labels, "series": series, "refs": refs, "ylabel": "mean test return",
                               "ref_label": "all features ({})", "title": "only this context feature group kept"}],
                             doc.out / f"context_features_{t}.png", title=f"{t}: single context feature")
        doc.figure(p, f"{t}: test return with only one context feature group kept (others "
                      "zeroed), 95% CI over robots; dashed: all features.")
    if rows:
        doc.table("Single context feature", "context_features",
                  ["task", "arch", "context_features", "seeds", "test_robots", "test_return", "ci95", "normalised",
                   "normalised_ci95"], rows,
                  ["task", "arch", "kept features", "seeds", "test return", "normalised"], md)


def _params_table(doc: Document, ctx: ReportContext) -> None:
    runs = ctx.runs
    rows, seen = [], set()
    for r in runs:
        if (r.task, r.name) in seen:
            continue
        seen.add((r.task, r.name))
        try:
            n = param_count(r.cfg, ctx.param_counts)
        except Exception as e:  # noqa: BLE001 - a table cell, not a reason to fail the report
            doc.missing.append(f"parameter count of {r.name} on {r.task}: {type(e).__name__}: {str(e)[:200]}")
            continue
        rows.append([r.task, r.name, n])
    order_t, order_a = _order_tasks(x[0] for x in rows), _order_archs(x[1] for x in rows)
    rows.sort(key=lambda x: (order_t.index(x[0]), order_a.index(x[1])))
    if rows:
        doc.table("Parameters", "params", ["task", "arch", "parameters"], rows,
                  md_rows=[[t, a, f"{n:,}"] for t, a, n in rows],
                  note="trainable parameters of the run's model (actor and critic).")


def _compute_table(doc: Document, ctx: ReportContext) -> None:
    tasks, main = ctx.tasks, ctx.main
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
            md.append([t, a, len(rs), fmt_steps(row[3]), pm(row[4], row[5], 2), fmt(row[6], 0), pm(row[7], row[8])])
    if rows:
        doc.table("Compute and final training return (main runs)", "compute",
                  ["task", "arch", "runs", "env_steps", "h_per_100M", "h_per_100M_ci95", "mean_sps",
                   "final_train_return", "final_train_return_ci95"], rows,
                  ["task", "arch", "runs", "env steps", "wall h / 100 M steps", "mean steps/s", "final train return"],
                  md, note="mean ± 95% CI over runs (a seed run twice counts twice here); final train return: mean "
                           "episode return of the last ~5% of iterations.")


def _rates_table(doc: Document, ctx: ReportContext) -> None:
    """Each run's env steps/s per phase (`Run.phase_rates`): what docs/benchmarks.md records of a lease's runs."""
    rows, md = [], []
    for r in ctx.runs:
        for ph in r.phase_rates():
            rows.append([_display(r.path), r.task, r.name, r.seed, " + ".join(r.devices) or "?", ph["phase"],
                         ph["iterations"], ph["left_out"], ph["rollout_sps"], ph["update_sps"], ph["sps"],
                         ph["epochs"]])
            md.append([f"`{_display(r.path)}`", r.seed, ph["phase"], ph["iterations"],
                       f"{ph['rollout_sps'] / 1e3:.1f} k", f"{ph['update_sps'] / 1e3:.1f} k",
                       f"**{ph['sps'] / 1e3:.1f} k**", f"{ph['epochs']:.2f}"])
    if rows:
        doc.table("Rates per phase", "rates",
                  ["run", "task", "arch", "seed", "device", "phase", "iterations", "left_out", "rollout_sps",
                   "update_sps", "sps", "mean_epochs"], rows,
                  ["run", "seed", "phase", "iterations", "rollout", "update", "end to end", "mean epochs run"], md,
                  note=f"env steps/s, medians over the iterations that ran all epochs and over those the KL stop cut "
                       f"short, leaving out iterations slower than {Run.SLOW_ITERATION:g}x the run's median wall time "
                       f"(a call's first iteration, with its compilation; left_out in rates.csv); whole run: its env "
                       f"steps over the summed time of its iterations but each call's first (devices.yaml's starts), "
                       f"the rollout's and the update's time from their rates; on the run's device (runs table), so "
                       f"compare rates only between runs of one device.")


def _health_table(doc: Document, ctx: ReportContext) -> None:
    """Each run's bookkeeping checks (`Run.health`): what a lease's runs are read for before their returns."""
    rows, md = [], []
    for r in ctx.runs:
        h = r.health()
        if h is None:
            continue
        physics = _physics_label(r)
        rows.append([_display(r.path), r.task, r.name, r.seed, r.iterations, h["ratio_off"], h["kl"], h["unstable"],
                     h["first_kl_stop"], h["value_max"], h["nonfinite"], physics, "; ".join(h["flags"])])
        md.append([f"`{_display(r.path)}`", r.seed, r.iterations, f"{h['ratio_off']:.1e}", f"{h['kl']:.1e}",
                   "–" if h["unstable"] is None else h["unstable"], h["first_kl_stop"] or "never",
                   fmt(h["value_max"], 2), physics, "; ".join(h["flags"]) or "ok"])
    if rows:
        doc.table("Health", "health",
                  ["run", "task", "arch", "seed", "iterations", "first_ratio_off", "first_kl", "unstable_episodes",
                   "first_kl_stop", "value_max", "nonfinite_iterations", "physics", "flags"], rows,
                  ["run", "seed", "iterations", "first minibatch: max abs(ratio - 1)", "max abs(KL)",
                   "unstable episodes", "first KL stop", "max abs(value)", "physics", "flags"], md,
                  note=f"over every iteration of metrics.csv: the first minibatch after each rollout, where acting and "
                       f"training see the same states (ratio 1 and KL 0: fp32 to ~1e-7, bf16 to ~1e-4; flagged "
                       f"beyond {Run.RATIO_TOLERANCE:g}), the simulator's unstable episodes (reset and counted), the "
                       f"first iteration the KL stop cut short, the largest mean value estimate, and the model "
                       f"digests its calls recorded (devices.yaml; more than one is flagged).")


# (heading, section) in report order; a section's figures go under "## <heading>" (the runs table under "## Runs")
SECTIONS: tuple[tuple[str, Callable[[Document, ReportContext], None]], ...] = (
    ("Runs", _runs_table),
    ("Learning curves", _learning_curves),
    ("Returns", _returns),
    ("Per-robot differences", _robot_differences),
    ("Claims", _claims),
    ("Seed spread", _seed_spread),
    ("Seeds by physics", _seeds_by_physics),
    ("Chosen on val", _choice_on_val),
    ("A/B arms", _arms),
    ("Reward per timestep", _reward_per_step),
    ("Training-set size", _train_size),
    ("Single context feature", _context_features),
    ("Parameters", _params_table),
    ("Compute", _compute_table),
    ("Rates", _rates_table),
    ("Health", _health_table),
)


def build_report(run_dirs: Sequence[str | Path], out: str | Path,
                 compare: Sequence[str] = DEFAULT_COMPARE, title: str = "mjx_morph report",
                 looks: int | Mapping[str, int] = 1) -> Path:
    """Read the runs, write figures, tables and `out/report.md`; returns the path of report.md. `run_dirs` may
    name directories holding run directories (see runs.find_run_dirs). `looks`: how many times the claims'
    comparisons were looked at as seeds came in (their CIs and verdicts corrected for it, `stats.claim_test`): one
    number for every claim, or per model / task and model (`Looks.parse`)."""
    looks = Looks.parse(looks)          # a bad value fails before anything is read or written
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = Document(out)
    runs: list[Run] = []
    for d in find_run_dirs(run_dirs):
        why = unhealthy_reason(d)                   # the train loop stopped it: it starts broken (stop_unhealthy)
        if why:
            doc.missing.append(f"`{_display(d)}`: left out: it stopped because it starts broken ({why})")
            continue
        try:
            runs.append(read_run(d))
        except (OSError, ValueError, yaml.YAMLError) as e:
            doc.missing.append(f"`{_display(d)}`: left out ({e})")
    classify(runs)
    name_variants(runs)
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
    tasks = _order_tasks(r.task for r in runs)
    main = {t: {a: [r for r in runs if r.task == t and r.name == a and r.kind == "main"]
                for a in _order_archs(r.name for r in runs if r.task == t and r.kind == "main")} for t in tasks}
    ctx = ReportContext(runs, tasks, main, tuple(compare) if compare else DEFAULT_COMPARE, looks=looks)
    for heading, section in SECTIONS:
        doc.section(heading)
        section(doc, ctx)
    return doc.write(title, len(runs))
