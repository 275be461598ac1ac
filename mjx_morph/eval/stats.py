"""Statistics of evaluation results and learning curves.

    ci95(x)                          # half-width of the 95% CI of the mean (Student t)
    normalised(returns, "ft")        # the paper's per-task range: (R - min) / (max - min)
    set_stat(runs, "test", "ft")     # Stat: mean and CI over robots of the seed-averaged per-robot returns
    grid, mean, lo, hi, n = mean_curve([(steps, returns), ...])
    claim_test(seed_set_means(model_runs, "test"), seed_set_means(baseline_runs, "test"), "better")
    claim_test(..., "better", looks=2)   # the second look at data that grew by seeds: Bonferroni, p < 0.025 / 2

Per-robot mean returns (the `per_robot` of eval/<tag>.json) are averaged over the seeds (runs) of a group that
evaluated the robot (`seed_average`); means and 95% CIs are then taken over robots. Normalised returns use the
per-task ranges of `TASK_RANGES` (nan for a task without one). Learning curves are lightly smoothed, interpolated
onto a common grid and averaged where all the curves reach (the mean ends with the shortest).

Claims (`claim_test`) take seeds as the samples: each seed's mean return over the set's robots (`seed_set_means`;
runs that share a seed are one sample), the difference of the means over seeds model - baseline with a 95% CI from
Welch's t, and a verdict against a margin of `CLAIM_MARGIN` of the baseline's mean. Where the same comparison was
looked at k times as seeds came in (`looks=k`), the CI is widened to 1 - 0.05 / k and a claim holds at p < 0.025 / k
(Bonferroni), so that k looks together keep the 2.5% error rate of one.
"""
from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy import stats

from ..sim.tasks import TASKS, get_task
from ..unimal.variants import CHANGE_TYPES, variant_change
from .runs import Run

#: the paper's per-task return range over robots, (min, max): the task records' `return_range`
TASK_RANGES = {name: task.return_range for name, task in TASKS.items()}
CURVE_POINTS = 200
#: the margin m of `claim_test`, a fraction of the baseline's mean return: the smallest difference that counts. A gain
#: below m is no gain ("better" not reproduced); a loss below m is "at least as well" (non-inferiority, "level")
CLAIM_MARGIN = 0.05
#: power the report plans seeds for: a claim test at the observed effect and seed spreads succeeds this often
CLAIM_POWER = 0.8
#: the verdicts of `claim_test`
REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE, TOO_FEW_SEEDS = ("reproduced", "not reproduced", "inconclusive",
                                                          "inconclusive (n < 2)")


def normalised(ret, task: str):
    """(R - min) / (max - min) with the task's return range (`Task.normalised`)."""
    return get_task(task).normalised(ret)


def normalised_or_nan(x, task: str | None) -> np.ndarray:
    """`normalised`, or nan (of the shape of `x`) for a task without a range."""
    if task not in TASK_RANGES:
        return np.full(np.shape(x), np.nan)
    return normalised(x, task)


def ci95(x: Sequence[float]) -> float:
    """Half-width of the 95% confidence interval of the mean (Student t); nan for fewer than 2 values."""
    x = np.asarray(x, np.float64)
    if x.size < 2:
        return float("nan")
    return float(stats.t.ppf(0.975, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))


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
    n = normalised_or_nan(v, task) if norm_values is None else np.asarray(norm_values, float)
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
        return stat_of(list(pr.values()), task, seed_count(have))
    st = stat_of(seed_set_means(have, tag), task, seed_count(have))
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
        return {c: stat_of(by[c], task, seed_count(have)) for c in CHANGE_TYPES if c in by}
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
                va, vb = float(normalised_or_nan(va, task)), float(normalised_or_nan(vb, task))
            rows.append((k, va, vb, va - vb))
    return sorted(rows, key=lambda r: (-r[3], r[0]))


def seed_set_means(runs: Sequence[Run], tag: str) -> list[float]:
    """Each seed's mean return over the robots of `tag`, from its runs' per-robot numbers (those `seed_average`
    reads; without any, the file's mean_return), for the runs that evaluated `tag`. Runs of one seed (the same
    config run again, e.g. on another GPU model, which gives another run) are one sample, their mean: they share
    their initial parameters and episodes, so they are not independent seeds."""
    def mean_return(r: Run) -> float:
        if tag not in r.evals:
            return float("nan")
        pr = r.per_robot(tag)
        try:
            return float(np.mean(list(pr.values()))) if pr else float(r.evals[tag].get("mean_return"))
        except (TypeError, ValueError):
            return float("nan")
    return _per_seed(runs, mean_return)


def seed_train_means(runs: Sequence[Run], steps: float) -> list[float]:
    """Each seed's training return at `steps` env steps (`Run.train_return`: the last ~5% of the iterations up to
    there in metrics.csv), for the runs that reached `steps` (one cut short is at another point of its schedule); runs
    of one seed are one sample, their mean, as in `seed_set_means`."""
    return _per_seed(runs, lambda r: r.train_return(steps) if r.final_steps >= steps else float("nan"))


def eval_steps_of(runs: Sequence[Run], tag: str) -> dict[float | None, list[Run]]:
    """{env steps of the checkpoint evaluated: [runs]} over the runs that evaluated `tag` (key None: a file that does
    not say), in order of env steps."""
    by: dict[float | None, list[Run]] = {}
    for r in runs:
        if tag in r.evals:
            by.setdefault(r.eval_steps(tag), []).append(r)
    return dict(sorted(by.items(), key=lambda kv: (kv[0] is not None, kv[0] or 0.0)))


def common_eval_steps(runs_a: Sequence[Run], runs_b: Sequence[Run], tag: str
                      ) -> tuple[float | None, list[Run], list[Run]] | None:
    """Where two groups' evaluations on `tag` are compared (a policy at 18 M steps is not one at 20 M): of the env
    steps both groups evaluated at, the one with the most seeds on the smaller side, then the most seeds in all, then
    the latest; returns (those steps, the runs of each group evaluated there), the steps None where the files do not
    say (they count as one step of their own). None where the groups share no step."""
    a, b = eval_steps_of(runs_a, tag), eval_steps_of(runs_b, tag)
    both = [s for s in a if s in b]
    if not both:
        return None
    at = max(both, key=lambda s: (min(seed_count(a[s]), seed_count(b[s])), seed_count(a[s]) + seed_count(b[s]),
                                  s is not None, s or 0.0))
    return at, a[at], b[at]


def _per_seed(runs: Sequence[Run], value: Callable[[Run], float]) -> list[float]:
    """The mean of `value` over each seed's runs (a run without a seed alone), runs whose value is not finite left
    out."""
    by_seed: dict = {}
    for i, r in enumerate(runs):
        v = value(r)
        if math.isfinite(v):
            by_seed.setdefault(("seed", r.seed) if r.seed is not None else ("run", i), []).append(v)
    return [float(np.mean(v)) for v in by_seed.values()]


def seed_count(runs: Sequence[Run]) -> int:
    """How many seeds `runs` have (runs of one seed count once; a run without a seed counts alone)."""
    return len({r.seed for r in runs if r.seed is not None}) + sum(r.seed is None for r in runs)


def repeated_seeds(runs: Sequence[Run]) -> dict:
    """{seed: [run paths]} for the seeds that more than one of `runs` has."""
    paths: dict = {}
    for r in runs:
        if r.seed is not None:
            paths.setdefault(r.seed, []).append(str(r.path))
    return {seed: p for seed, p in paths.items() if len(p) > 1}


def welch_ci(a: Sequence[float], b: Sequence[float], level: float = 0.95) -> tuple[float, float]:
    """CI (low, high) at `level` of mean(a) - mean(b) from Welch's t (scipy's `ttest_ind(equal_var=False)`); (nan,
    nan) with fewer than 2 values on a side, the difference itself when neither side has any spread (scipy gives nan)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.size < 2 or b.size < 2:
        return float("nan"), float("nan")
    if a.var() + b.var() == 0:
        d = float(a.mean() - b.mean())
        return d, d
    ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(level)
    return float(ci.low), float(ci.high)


@dataclass(frozen=True)
class ClaimTest:
    """What `claim_test` found: seeds per side, means over seeds, the difference model - baseline with its 95% CI
    (nan with fewer than 2 seeds on a side), the margin m (in return), the verdict, and the seeds per side that would
    reproduce the claim with probability CLAIM_POWER if the observed difference and seed spreads are the truth (nan
    where the difference does not clear the claim's bound, or with fewer than 2 seeds on a side), and `p_value`: the
    one-sided Welch p of "the difference is at most the claim's bound" (reproduced exactly when p < 0.025 / looks:
    the data looked at `looks` times as seeds came in, Bonferroni's correction; the CI is then at 1 - 0.05 / looks)."""
    model_seeds: int
    baseline_seeds: int
    model_mean: float
    baseline_mean: float
    difference: float
    ci_low: float
    ci_high: float
    margin: float
    verdict: str
    seeds_for_power: float
    p_value: float = float("nan")
    looks: int = 1

    @property
    def level(self) -> float:
        """The CI's confidence level: 0.95 at one look."""
        return ci_level(self.looks)

    @property
    def relative(self) -> float:
        """The difference in percent of the baseline's mean."""
        return 100 * self.difference / abs(self.baseline_mean) if self.baseline_mean else float("nan")


def ci_level(looks: int) -> float:
    """The confidence level of a claim's CI after `looks` looks at the data (Bonferroni): 1 - 0.05 / looks."""
    if not (isinstance(looks, (int, np.integer)) and looks >= 1):
        raise ValueError(f"looks={looks!r}: expected a whole number >= 1 (how many times the comparison was looked at)")
    return 1 - 0.05 / int(looks)


def claim_test(model: Sequence[float], baseline: Sequence[float], kind: str,
               margin: float = CLAIM_MARGIN, looks: int = 1) -> ClaimTest:
    """Whether the seeds' returns `model` support a claim against `baseline` (one number per seed, e.g.
    `seed_set_means`). kind "better": the model is better (delta = 0); "level": it does at least as well (delta = -m),
    with m = margin x |mean(baseline)|. With the 95% Welch CI [lo, hi] of mean(model) - mean(baseline): reproduced if
    lo > delta, else not reproduced if hi < delta + m (a gain surely below m; a loss surely there), else inconclusive;
    "inconclusive (n < 2)" with fewer than 2 seeds on a side. `looks` > 1: the CI at 1 - 0.05 / looks (the
    comparison looked at that many times as seeds came in; Bonferroni), so reproduced exactly when p < 0.025 / looks."""
    if kind not in ("better", "level"):
        raise ValueError(f"claim kind {kind!r}: not 'better' or 'level'")
    a, b = np.asarray(model, np.float64), np.asarray(baseline, np.float64)
    ma, mb = (float(x.mean()) if x.size else float("nan") for x in (a, b))
    m = margin * abs(mb)
    level = ci_level(looks)
    lo, hi = welch_ci(a, b, level)
    delta = 0.0 if kind == "better" else -m
    if a.size < 2 or b.size < 2:
        verdict = TOO_FEW_SEEDS
    elif lo > delta:
        verdict = REPRODUCED
    elif hi < delta + m:
        verdict = NOT_REPRODUCED
    else:
        verdict = INCONCLUSIVE
    return ClaimTest(int(a.size), int(b.size), ma, mb, ma - mb, lo, hi, m, verdict,
                     seeds_for_power(a, b, ma - mb - delta, level=level), welch_p_above(a, b, delta), int(looks))


def welch_p_above(a: np.ndarray, b: np.ndarray, delta: float) -> float:
    """One-sided p-value of Welch's t for H0: mean(a) - mean(b) <= delta against mean(a) - mean(b) > delta (scipy's
    `ttest_ind(equal_var=False, alternative="greater")` with b shifted by delta): below 0.025 exactly when the 95%
    Welch CI of the difference lies above delta. nan with fewer than 2 values on a side; 0 or 1 when neither side has
    any spread (the difference is then known)."""
    if a.size < 2 or b.size < 2:
        return float("nan")
    if a.var() + b.var() == 0:
        return 0.0 if a.mean() - b.mean() > delta else 1.0
    return float(stats.ttest_ind(a, b + delta, equal_var=False, alternative="greater").pvalue)


def welch_p_two_sided(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sided p-value of Welch's t for mean(a) = mean(b), from `welch_p_above` (so nan with fewer than 2 values on
    a side, 0 or 1 when neither side has any spread)."""
    above = welch_p_above(a, b, 0.0)
    return min(1.0, 2 * min(above, 1 - above)) if math.isfinite(above) else float("nan")


def seeds_for_power(a: np.ndarray, b: np.ndarray, effect: float, power: float = CLAIM_POWER,
                    level: float = 0.95) -> float:
    """Seeds per side for which a two-sided test at `level` of a difference `effect` (its distance from the bound the
    CI must clear) succeeds with probability `power`, at the sides' seed standard deviations:
    n = (z_((1 + level) / 2) + z_power)^2 (s_a^2 + s_b^2) / effect^2, the normal approximation (Welch's t needs ~1-2
    seeds more at n < 10), rounded up. nan with fewer than 2 seeds on a side or an effect <= 0 (no number of seeds
    reproduces a claim the data point against)."""
    if a.size < 2 or b.size < 2 or not effect > 0:
        return float("nan")
    z = stats.norm.ppf((1 + level) / 2) + stats.norm.ppf(power)
    return float(math.ceil(z ** 2 * (a.var(ddof=1) + b.var(ddof=1)) / effect ** 2))


def _smooth(y: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average over k points (shorter at the ends)."""
    if k <= 1 or y.size < 3:
        return y
    c = np.concatenate([[0.0], np.cumsum(y)])
    i = np.arange(y.size)
    lo, hi = np.maximum(0, i - k // 2), np.minimum(y.size, i + k // 2 + 1)
    return (c[hi] - c[lo]) / (hi - lo)


def mean_curve(curves: Sequence[tuple[np.ndarray, np.ndarray]], points: int = CURVE_POINTS, smooth: bool = True):
    """(grid, mean, lo, hi, count) of curves (x, y) interpolated onto a common grid; count = how many curves cover a
    grid point. The mean and its band (mean -/+ ci95, from two curves) only where all of them do, else nan: a mean
    over whichever seeds reach a point would jump where one ends."""
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
    mean = ys.mean(0)                              # nan where a curve is missing
    half = np.array([ci95(c) if len(curves) >= 2 and np.isfinite(c).all() else np.nan for c in ys.T])
    return grid, mean, mean - half, mean + half, count


def furthest_mean_curve(curves: Sequence[tuple[np.ndarray, np.ndarray]], points: int = CURVE_POINTS,
                        smooth: bool = True):
    """Where some curves end early: (grid, mean, lo, hi, n) of the n >= 2 curves that reach furthest, on the stretch
    past the point where all curves end (from that point on), the part of the picture that `mean_curve` leaves out;
    None where all curves end together or fewer than 2 reach furthest. The same seeds as the report's claim set
    'training' (the runs at the furthest env steps)."""
    curves = [(np.asarray(x, float), np.asarray(y, float)) for x, y in curves]
    curves = [(x, y) for x, y in curves if np.isfinite(x).any()]
    ends = [np.nanmax(x) for x, _ in curves]
    far = [c for c, e in zip(curves, ends) if e == max(ends)]
    if not 2 <= len(far) < len(curves):
        return None
    grid, mean, lo, hi, _ = mean_curve(far, points, smooth)
    past = grid >= min(ends)
    return grid[past], mean[past], lo[past], hi[past], len(far)
