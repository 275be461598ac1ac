"""experiments.report / mjx_morph.eval.report on synthetic run directories (config.yaml, metrics.csv, eval/*.json in
the formats of mjx_morph.ppo.loop and mjx_morph.eval.evaluate, filled with fixed random numbers)."""
from __future__ import annotations

import csv
import json
import math
import re
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from experiments.report import ReportConfig, report as report_cli
from mjx_morph.eval import plots
from mjx_morph.eval.report import CLAIMS, Looks, build_report
from mjx_morph.eval.runs import NotARunDir, Run, classify, find_run_dirs, name_variants, read_manifest, read_run
from mjx_morph.eval.stats import TASK_RANGES, claim_test, furthest_mean_curve, mean_curve
from mjx_morph.unimal.variants import CHANGE_TYPES

ROOT = Path(__file__).resolve().parents[1]
TRAIN = [f"train-{i:03d}" for i in range(100)]
TEST = [f"test-{i:02d}" for i in range(12)]
VAL = [f"val-{i:02d}" for i in range(8)]
VARIANTS = [f"{b}_{c}_{k}" for b in TRAIN[:3] for c in CHANGE_TYPES for k in range(2)]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def ci_ref(x) -> float:
    """95% CI half-width (Student t), computed here independently of mjx_morph.eval.stats.ci95."""
    x = np.asarray(x, float)
    return float(stats.t.ppf(0.975, x.size - 1) * np.std(x, ddof=1) / np.sqrt(x.size))


def _summary(task, arch, tag, per_robot, recurrent, rng, env_steps=40_000):
    v = np.array(list(per_robot.values()))
    lo, hi = TASK_RANGES[task]
    n = (v - lo) / (hi - lo)
    d = {"run_dir": "x", "arch": arch, "task": task, "set": tag, "tag": tag, "checkpoint": env_steps // 1000,
         "env_steps": env_steps,
         "episodes": 2, "seed": 0, "episode_length": 1000, "robots": len(v), "episodes_total": 2 * len(v),
         "mean_return": float(v.mean()), "ci95_return": ci_ref(v), "mean_normalised": float(n.mean()),
         "ci95_normalised": ci_ref(n), "mean_length": 500.0, "fall_fraction": 0.5, "out_of_bounds_fraction": 0.0,
         "timeout_fraction": 0.5, "instabilities": 0, "per_robot": per_robot,
         "reward_trace": rng.uniform(0, 1, 500).tolist(), "alive_trace": np.linspace(1, 0.4, 500).tolist()}
    if tag == "variants":
        d["per_change"] = {c: {"robots": 6, "mean_return": float(np.mean([per_robot[k] for k in per_robot
                                                                         if f"_{c}_" in k]))} for c in CHANGE_TYPES}
    elif recurrent:
        d["zero_state_steps"] = 100
        d["reward_trace_zero_state"] = rng.uniform(0, 1, 500).tolist()
        d["mean_return_zero_state"] = float(v.mean()) - 10
    return d


def make_run(root: Path, name: str, task="ft", arch="rmomo", seed=0, num_robots=None, context=None,
             evals=("train", "test", "variants"), metrics=True, iters=40, returns=(50, 3000),
             eval_steps=40_000) -> tuple[Path, dict]:
    """A synthetic run directory, per-robot returns uniform in `returns`, its evaluations of the checkpoint at
    `eval_steps` env steps; returns (path, {tag: per_robot})."""
    rng = np.random.default_rng(zlib.crc32(f"{name}|{task}|{arch}|{seed}".encode()))
    d = root / name
    (d / "eval").mkdir(parents=True)
    cfg = {"env": {"task": task}, "arch": arch, "seed": seed, "num_robots": num_robots,
           "robots": "unimal100/train", "total_steps": iters * 1000}
    if context is not None:
        cfg["env"]["context_features"] = context
    (d / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    if metrics:
        with (d / "metrics.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["iteration", "env_steps", "episode_return", "episode_length", "wall_s", "sps", "rollout_sps",
                        "update_sps", "epochs_run"])
            for it in range(1, iters + 1):
                wall = 30.0 if it == 1 else float(rng.uniform(1, 3))
                w.writerow([it, it * 1000, 10 * it + rng.normal(0, 5), 100 + it, wall, 1000 / wall, 2000, 2000, 8])
    names = {"train": TRAIN[: num_robots or 100], "test": TEST, "val": VAL, "variants": VARIANTS}
    per = {}
    for tag in evals:
        pr = {k: float(rng.uniform(*returns)) for k in names[tag]}
        per[tag] = pr
        (d / "eval" / f"{tag}.json").write_text(json.dumps(
            _summary(task, arch, tag, pr, arch == "rmomo", rng, eval_steps), indent=1))
    return d, per


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    data = {}
    for arch in ("rmomo", "modumorph"):
        for seed in (0, 1):
            data[("ft", arch, seed)] = make_run(root / "main", f"ft-{arch}-s{seed}", "ft", arch, seed)[1]
        data[("incline", arch, 0)] = make_run(root / "main", f"incline-{arch}-s0", "incline", arch, 0,
                                              evals=("train", "test"))[1]
    for n in (25, 50):
        data[("size", n)] = make_run(root / "size", f"ft-rmomo-size{n}", num_robots=n, evals=("train", "test"))[1]
    for feat in ("gear", "body_mass"):
        data[("ctx", feat)] = make_run(root / "ctx", f"ft-rmomo-{feat}", context=[feat], evals=("test",))[1]
    no_eval, _ = make_run(root / "bare", "ft-metamorph-s0", arch="metamorph", evals=())
    nothing, _ = make_run(root / "bare", "ft-metamorph-s1", arch="metamorph", seed=1, evals=(), metrics=False)
    out = root / "report"
    md = build_report([root / "main", root / "size", root / "ctx", no_eval, nothing], out)
    return {"root": root, "out": out, "md": md, "text": md.read_text(), "data": data, "no_eval": no_eval,
            "nothing": nothing}


def _csv(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


EXPECTED_PNGS = ["learning_curve_ft", "learning_curve_incline", "returns_ft", "returns_incline",
                 "returns_pooled_normalised", "robot_diff_ft", "robot_diff_incline", "robot_diff_pooled",
                 "reward_per_step_ft", "reward_per_step_incline", "train_size_ft", "context_features_ft", "claims"]


def test_figures_exist_are_pngs_and_linked(report):
    import matplotlib.image as mpimg
    for name in EXPECTED_PNGS:
        p = report["out"] / f"{name}.png"
        assert p.exists(), name
        assert p.read_bytes()[:8] == PNG_MAGIC
        assert p.stat().st_size > 10_000, name
        img = mpimg.imread(p)
        assert img.shape[0] > 200 and img.shape[1] > 200 and img[..., :3].std() > 0.05, name
        assert f"]({name}.png)" in report["text"], name


def test_markdown_has_runs_tables_and_csvs(report):
    text = report["text"]
    for heading in ("## Runs", "## Tables", "### Returns (main runs)", "### Parameters", "### Compute",
                    "### Per-robot test differences", "### Training-set size", "### Single context feature",
                    "### Variant returns by change type", "### Normalised returns pooled across tasks", "## Missing"):
        assert heading in text, heading
    for name in ("runs", "returns", "params", "compute", "robot_diff", "train_size", "context_features",
                 "variants_by_change", "returns_pooled", "robot_diff_ft", "robot_diff_pooled"):
        assert (report["out"] / f"{name}.csv").exists(), name
    runs = _csv(report["out"] / "runs.csv")
    assert len(runs) == 2 * 2 + 2 + 2 + 2 + 2          # ft main, incline main, size, context, bare
    params = {(r["task"], r["arch"]): int(r["parameters"]) for r in _csv(report["out"] / "params.csv")}
    assert params[("ft", "rmomo")] > params[("ft", "modumorph")] > 1_000_000


def test_returns_table_is_mean_and_ci_over_robots_of_seed_means(report):
    rows = {(r["task"], r["arch"]): r for r in _csv(report["out"] / "returns.csv")}
    d = report["data"]
    for arch in ("rmomo", "modumorph"):
        for tag in ("train", "test", "variants"):
            a, b = d[("ft", arch, 0)][tag], d[("ft", arch, 1)][tag]
            v = np.array([(a[k] + b[k]) / 2 for k in a])
            r = rows[("ft", arch)]
            assert float(r[f"{tag}_return"]) == pytest.approx(v.mean(), rel=1e-9)
            assert float(r[f"{tag}_ci95"]) == pytest.approx(ci_ref(v), rel=1e-9)
            lo, hi = TASK_RANGES["ft"]
            assert float(r[f"{tag}_normalised"]) == pytest.approx(((v - lo) / (hi - lo)).mean(), rel=1e-9)
            assert int(r[f"{tag}_robots"]) == len(v)
        assert r["seeds"] == r["test_seeds"] == r["variants_seeds"] == "2"
    # one seed on incline: the CI equals the file's ci95 over robots
    r = rows[("incline", "rmomo")]
    v = np.array(list(d[("incline", "rmomo", 0)]["test"].values()))
    assert float(r["test_ci95"]) == pytest.approx(ci_ref(v), rel=1e-9)
    assert r["variants_return"] == ""
    # per change type
    ch = {(r["arch"], r["change"]): r for r in _csv(report["out"] / "variants_by_change.csv")}
    a, b = d[("ft", "rmomo", 0)]["variants"], d[("ft", "rmomo", 1)]["variants"]
    v = np.array([(a[k] + b[k]) / 2 for k in a if "_gear_" in k])
    assert float(ch[("rmomo", "gear")]["return"]) == pytest.approx(v.mean())
    assert float(ch[("rmomo", "gear")]["ci95"]) == pytest.approx(ci_ref(v))


def test_per_robot_difference(report):
    d = report["data"]
    rows = _csv(report["out"] / "robot_diff_ft.csv")
    assert list(rows[0]) == ["robot", "rmomo_return", "modumorph_return", "difference"]
    assert {r["robot"] for r in rows} == set(TEST)
    for r in rows:
        a = (d[("ft", "rmomo", 0)]["test"][r["robot"]] + d[("ft", "rmomo", 1)]["test"][r["robot"]]) / 2
        b = (d[("ft", "modumorph", 0)]["test"][r["robot"]] + d[("ft", "modumorph", 1)]["test"][r["robot"]]) / 2
        assert float(r["rmomo_return"]) == pytest.approx(a)
        assert float(r["modumorph_return"]) == pytest.approx(b)
        assert float(r["difference"]) == pytest.approx(a - b)
    diffs = [float(r["difference"]) for r in rows]
    assert diffs == sorted(diffs, reverse=True)
    pooled = _csv(report["out"] / "robot_diff_pooled.csv")
    assert len(pooled) == 2 * len(TEST)
    lo, hi = TASK_RANGES["incline"]
    r = next(r for r in pooled if r["task:robot"] == f"incline:{TEST[3]}")
    want = ((d[("incline", "rmomo", 0)]["test"][TEST[3]] - d[("incline", "modumorph", 0)]["test"][TEST[3]])
            / (hi - lo))
    assert float(r["difference"]) == pytest.approx(want)
    summary = {r["task"]: r for r in _csv(report["out"] / "robot_diff.csv")}
    assert float(summary["ft"]["mean_difference"]) == pytest.approx(np.mean(diffs))
    assert float(summary["ft"]["ci95"]) == pytest.approx(ci_ref(diffs))


def test_size_context_and_compute_tables(report):
    d = report["data"]
    size = {(r["arch"], int(r["num_robots"])): r for r in _csv(report["out"] / "train_size.csv")}
    assert sorted(size) == [("rmomo", 25), ("rmomo", 50), ("rmomo", 100)]      # the full set stands at 100
    v = np.array(list(d[("size", 25)]["test"].values()))
    assert float(size[("rmomo", 25)]["test_return"]) == pytest.approx(v.mean())
    assert float(size[("rmomo", 25)]["ci95"]) == pytest.approx(ci_ref(v))
    assert size[("rmomo", 100)]["seeds"] == "2"
    ctx = {r["context_features"]: r for r in _csv(report["out"] / "context_features.csv") if r["arch"] == "rmomo"}
    assert set(ctx) == {"gear", "body_mass", "all"}
    assert float(ctx["gear"]["test_return"]) == pytest.approx(np.mean(list(d[("ctx", "gear")]["test"].values())))
    runs = {Path(r["run"]).name: r for r in _csv(report["out"] / "runs.csv")}
    r = runs["ft-rmomo-s0"]
    with (report["root"] / "main" / "ft-rmomo-s0" / "metrics.csv").open() as fh:
        m = list(csv.DictReader(fh))
    wall = sum(float(x["wall_s"]) for x in m)
    assert float(r["h_per_100M"]) == pytest.approx(wall / 40_000 * 1e8 / 3600)
    assert float(r["mean_sps"]) == pytest.approx(np.mean([float(x["sps"]) for x in m[1:]]))
    assert float(r["final_train_return"]) == pytest.approx(np.mean([float(x["episode_return"]) for x in m[-2:]]))
    assert runs["ft-rmomo-gear"]["kind"] == "context" and runs["ft-rmomo-size25"]["kind"] == "size"


def test_runs_without_eval_are_reported_missing(report):
    missing = report["text"].split("## Missing", 1)[1]
    assert f"{report['no_eval'].name}`: no eval/*.json" in missing
    assert f"{report['nothing'].name}`: no metrics.csv rows" in missing
    # a report of runs that have no eval at all still builds, listing what it could not draw
    out = report["root"] / "report_bare"
    text = build_report([report["no_eval"], report["nothing"]], out).read_text()
    assert (out / "learning_curve_ft.png").exists()
    assert "ft: return bars — no main run has eval/*.json" in text
    assert "reward per timestep" in text.split("## Missing", 1)[1]


def _verdict_ref(model, baseline, kind):
    """The claims' verdict, computed here independently of mjx_morph.eval.stats (scipy's Welch CI)."""
    if len(model) < 2 or len(baseline) < 2:
        return "inconclusive (n < 2)", None
    ci = stats.ttest_ind(model, baseline, equal_var=False).confidence_interval(0.95)
    m = 0.05 * abs(np.mean(baseline))
    delta = 0.0 if kind == "better" else -m
    verdict = ("reproduced" if ci.low > delta else "not reproduced" if ci.high < delta + m else "inconclusive")
    return verdict, ci


def _seed_means(per_robot_of_seeds, tag):
    return [np.mean(list(pr[tag].values())) for pr in per_robot_of_seeds]


def test_claim_test_verdicts():
    base = [100.0, 101.0, 99.0]
    cases = [([110.0, 112.0, 111.0], "better", "reproduced"),            # a clear gain
             ([80.0, 81.0, 79.0], "better", "not reproduced"),           # a clear loss
             ([80.0, 81.0, 79.0], "level", "not reproduced"),
             ([40.0, 160.0, 100.0], "better", "inconclusive"),           # wide overlap
             ([40.0, 160.0, 100.0], "level", "inconclusive"),
             ([98.0, 98.5, 97.5], "level", "reproduced"),                # a small loss, inside the 5% margin
             ([98.0, 98.5, 97.5], "better", "not reproduced"),
             ([102.0, 102.5, 101.5], "better", "not reproduced"),        # a sure gain, but below the margin
             ([130.0], "better", "inconclusive (n < 2)")]
    for model, kind, want in cases:
        r = claim_test(model, base, kind)
        ref, ci = _verdict_ref(model, base, kind)
        assert r.verdict == want == ref, (model, kind)
        assert r.difference == pytest.approx(np.mean(model) - 100.0)
        assert r.relative == pytest.approx(r.difference)                 # the baseline's mean is 100
        assert r.margin == pytest.approx(5.0)
        assert (r.model_seeds, r.baseline_seeds) == (len(model), 3)
        if ci is not None:
            assert (r.ci_low, r.ci_high) == pytest.approx((ci.low, ci.high), rel=1e-9)
        else:
            assert np.isnan(r.ci_low) and np.isnan(r.ci_high)
    with pytest.raises(ValueError, match="claim kind"):
        claim_test(base, base, "worse")


def test_seeds_for_power():
    """The seeds per side the claims table plans with: the normal-approximation formula at the observed difference
    (its distance from the bound: 0 for 'better', -m for 'level') and seed spreads, and what it promises: about 80%
    of simulated experiments of that size reproduce the claim."""
    base = [100.0, 101.0, 99.0]
    z2 = (stats.norm.ppf(0.975) + stats.norm.ppf(0.8)) ** 2
    wide = [40.0, 160.0, 100.0]
    assert claim_test(wide, base, "level").seeds_for_power == math.ceil(z2 * (3600 + 1) / 5.0 ** 2)   # 0 + m
    assert np.isnan(claim_test(wide, base, "better").seeds_for_power)         # no difference: no number of seeds
    assert np.isnan(claim_test([80.0, 81.0, 79.0], base, "better").seeds_for_power)   # the data point against it
    assert claim_test([110.0, 112.0, 111.0], base, "better").seeds_for_power == 1
    assert np.isnan(claim_test([130.0], base, "better").seeds_for_power)
    # 80% power, simulated: seeds ~ N(1100, 100) against N(1000, 100); the planned n reproduces "better" ~80% of the
    # time (Welch's t at n = 16 a little less than the normal approximation's 80%)
    rng = np.random.default_rng(0)
    n = int(claim_test(1100 + 100 * np.array([-1.0, 0, 1]), 1000 + 100 * np.array([-1.0, 0, 1]),
                       "better").seeds_for_power)
    assert n == math.ceil(z2 * 2 * 100 ** 2 / 100 ** 2) == 16
    hits = np.mean([claim_test(rng.normal(1100, 100, n), rng.normal(1000, 100, n), "better").verdict == "reproduced"
                    for _ in range(2000)])
    assert 0.72 < hits < 0.84, hits


def test_claim_p_value_is_welchs_one_sided_and_agrees_with_the_verdict():
    """p: Welch's one-sided p-value of "difference <= the claim's bound" (0 for 'better', -m for 'level'), computed
    here by hand (Welch-Satterthwaite degrees of freedom, Student t); reproduced exactly when p < 0.025."""
    def p_ref(a, b, delta):
        a, b = np.asarray(a, float), np.asarray(b, float)
        va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
        df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
        return float(stats.t.sf((a.mean() - b.mean() - delta) / np.sqrt(va + vb), df))

    rng = np.random.default_rng(1)
    seen = set()
    for _ in range(300):
        a, b = rng.normal(1100, 150, rng.integers(2, 9)), rng.normal(1000, 150, rng.integers(2, 9))
        for kind in ("better", "level"):
            r = claim_test(a, b, kind)
            delta = 0.0 if kind == "better" else -r.margin
            assert r.p_value == pytest.approx(p_ref(a, b, delta), rel=1e-7, abs=1e-12)
            assert (r.p_value < 0.025) == (r.verdict == "reproduced"), (a, b, kind)
            seen.add(r.verdict)
    assert {"reproduced", "inconclusive"} <= seen
    assert np.isnan(claim_test([130.0], [100.0, 101.0], "better").p_value)
    assert claim_test([110.0, 110.0], [100.0, 100.0], "better").p_value == 0.0       # no spread: the difference known


def test_claims_after_several_looks_use_bonferronis_bar():
    """looks=k (the comparison looked at k times as seeds came in): the CI at 1 - 0.05 / k, reproduced exactly when
    p < 0.025 / k; p itself does not change, the seeds planned for power grow; a bad k is refused."""
    rng = np.random.default_rng(2)
    seen = set()
    for _ in range(300):
        a, b = rng.normal(1150, 150, rng.integers(2, 9)), rng.normal(1000, 150, rng.integers(2, 9))
        one, three = claim_test(a, b, "better"), claim_test(a, b, "better", looks=3)
        assert three.p_value == one.p_value and three.level == pytest.approx(1 - 0.05 / 3) and one.level == 0.95
        assert three.ci_low <= one.ci_low and three.ci_high >= one.ci_high
        assert (three.p_value < 0.025 / 3) == (three.verdict == "reproduced"), (a, b)
        if math.isfinite(one.seeds_for_power):
            assert three.seeds_for_power >= one.seeds_for_power
        seen.add((one.verdict, three.verdict))
    assert ("reproduced", "inconclusive") in seen        # some claims hold at one look and not after three
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="looks="):
            claim_test([1.0, 2.0], [1.0, 2.0], "better", looks=bad)


def _claim_rows(out: Path) -> dict:
    return {(r["task"], r["model"], r["set"]): r for r in _csv(out / "claims.csv")}


def test_claims_table(report):
    """Each claim per task against numbers computed here; one seed a side: n < 2; no eval: missing, no row."""
    d, rows = report["data"], _claim_rows(report["out"])
    assert "### Claims" in report["text"]
    for c in CLAIMS:
        if c.model != "rmomo":
            assert ("ft", c.model, c.set) not in rows and ("incline", c.model, c.set) not in rows
            continue
        a = _seed_means([d[("ft", "rmomo", s)] for s in (0, 1)], c.set)
        b = _seed_means([d[("ft", "modumorph", s)] for s in (0, 1)], c.set)
        r = rows[("ft", "rmomo", c.set)]
        verdict, ci = _verdict_ref(a, b, c.kind)
        assert (r["claim"], r["kind"], r["baseline"], r["verdict"]) == (c.text, c.kind, "modumorph", verdict)
        assert (r["model_seeds"], r["baseline_seeds"]) == ("2", "2")
        assert float(r["model_mean"]) == pytest.approx(np.mean(a)) and float(r["baseline_mean"]) == pytest.approx(
            np.mean(b))
        assert float(r["ci95_low"]) == pytest.approx(ci.low) and float(r["ci95_high"]) == pytest.approx(ci.high)
        assert float(r["relative_difference_pct"]) == pytest.approx(100 * (np.mean(a) / np.mean(b) - 1))
        row = f"| ft | {c.text} | {c.set} at 0.0 M steps | 2/2 | {np.mean(a):.1f} | {np.mean(b):.1f} |"
        assert row in report["text"]
        assert float(r["env_steps"]) == 40_000
        if c.set == "variants":                                          # incline: not evaluated
            assert ("incline", "rmomo", "variants") not in rows
        else:
            r = rows[("incline", "rmomo", c.set)]
            assert r["verdict"] == "inconclusive (n < 2)" and r["ci95_low"] == ""
            assert (r["model_seeds"], r["baseline_seeds"]) == ("1", "1")
    missing = report["text"].split("## Missing", 1)[1]
    untested = {line.split(":", 1)[0][2:]: line for line in missing.splitlines() if "claims untested" in line}
    # ft's MetaMorph runs have no evaluations; incline's R-MoMo and ModuMorph runs no variants; incline's R-MeMo
    # claims, with neither model run there, are not listed
    assert set(untested) == {"ft", "incline"}
    assert "R-MeMo beats MetaMorph zero-shot on unseen topologies (test: rmemo 0, metamorph 0 seeds)" in untested["ft"]
    assert "R-MoMo" not in untested["ft"] and "(variants: rmomo 0, modumorph 0 seeds)" in untested["incline"]
    assert "R-MeMo" not in untested["incline"]


def test_claims_verdicts_on_clear_runs(tmp_path):
    """Runs built to settle every claim: R-MeMo well above MetaMorph (reproduced), R-MoMo well below ModuMorph (not
    reproduced); the verdicts and numbers match those computed here."""
    levels = {"rmemo": (1500, 1600), "metamorph": (1000, 1100), "rmomo": (500, 600), "modumorph": (1000, 1100)}
    data = {a: [make_run(tmp_path / "runs", f"ft-{a}-s{s}", arch=a, seed=s, returns=lv, metrics=False)[1]
                for s in range(3 if a in ("rmemo", "metamorph") else 2)] for a, lv in levels.items()}
    build_report([tmp_path / "runs"], tmp_path / "out")
    rows = _claim_rows(tmp_path / "out")
    assert len(rows) == len(CLAIMS)
    for c in CLAIMS:
        a, b = _seed_means(data[c.model], c.set), _seed_means(data[c.baseline], c.set)
        r = rows[("ft", c.model, c.set)]
        assert r["verdict"] == _verdict_ref(a, b, c.kind)[0]
        assert r["verdict"] == ("reproduced" if c.model == "rmemo" else "not reproduced")
        assert float(r["difference"]) == pytest.approx(np.mean(a) - np.mean(b))
        assert float(r["margin"]) == pytest.approx(0.05 * np.mean(b))
    # the fourth look at the same comparison: Bonferroni's CIs (wider, named in the table), p unchanged
    md = build_report([tmp_path / "runs"], tmp_path / "out4", looks=4).read_text()
    for key, r4 in _claim_rows(tmp_path / "out4").items():
        assert float(r4["ci_level"]) == pytest.approx(0.9875) and float(rows[key]["ci_level"]) == 0.95
        assert float(r4["ci95_low"]) < float(rows[key]["ci95_low"]) and r4["p_one_sided"] == rows[key]["p_one_sided"]
    assert "difference [98.75% CI]" in md and "looked at 4 times" in md and "p < 0.025 / 4 = 0.00625" in md
    assert "98.75% CI from Welch's t" in md and "95% CI from Welch's t" not in md
    with pytest.raises(ValueError, match="looks=0"):
        build_report([tmp_path / "runs"], tmp_path / "out0", looks=0)


def test_looks_per_claim_model_and_task():
    """looks as a mapping: "<task>/<model>" before "<model>" before one look; keys that name no claim's model or no
    task, and counts that are not whole numbers >= 1, are refused naming the key."""
    lk = Looks.parse({"rmomo": 5, "incline/rmomo": 3, "ft/rmemo": 2})
    assert (lk.of("ft", "rmomo"), lk.of("incline", "rmomo"), lk.of("ft", "rmemo"), lk.of("incline", "rmemo")) == (
        5, 3, 2, 1)
    assert Looks.parse(4).of("csr", "rmemo") == 4 and Looks.parse(lk) is lk
    for bad, match in (({"modumorph": 2}, re.escape("key 'modumorph': expected a claim's model (rmomo, rmemo)")),
                       ({"mars/rmomo": 2}, "key 'mars/rmomo'.*with a task of ft, incline"),
                       ({"ft/rmomo/x": 2}, "key 'ft/rmomo/x'"), ({"rmomo": 0}, "key 'rmomo': looks=0"),
                       ({"rmemo": 2.5}, "key 'rmemo': looks=2.5"), (0, "looks=0")):
        with pytest.raises(ValueError, match=match):
            Looks.parse(bad)


def test_claims_looked_at_a_different_number_of_times_per_model(tmp_path):
    """looks={rmemo: 3} through the command line: R-MeMo's claims at Bonferroni's 3-look CI, R-MoMo's at one look's,
    each row naming its looks, the same numbers as one report per model; the claims figure drawn; a bad key refused
    before anything is written."""
    levels = {"rmemo": (1500, 1600), "metamorph": (1000, 1100), "rmomo": (1000, 1150), "modumorph": (1000, 1100)}
    for a, lv in levels.items():
        for s in range(3):
            make_run(tmp_path / "runs", f"ft-{a}-s{s}", arch=a, seed=s, returns=lv, metrics=False)
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "experiments.report", f"runs=[{tmp_path / 'runs'}]", f"out={out}",
                        "looks={rmemo:3}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    build_report([tmp_path / "runs"], tmp_path / "one")
    build_report([tmp_path / "runs"], tmp_path / "three", looks=3)
    rows, one, three = (_claim_rows(d) for d in (out, tmp_path / "one", tmp_path / "three"))
    assert len(rows) == len(CLAIMS)
    for key, r in rows.items():
        ref = three[key] if key[1] == "rmemo" else one[key]
        assert r["looks"] == ("3" if key[1] == "rmemo" else "1")
        for col in ("ci_level", "ci95_low", "ci95_high", "verdict", "p_one_sided", "seeds_for_power"):
            assert r[col] == ref[col], (key, col)
    md = (out / "report.md").read_text()
    assert "difference [CI at 1 − 0.05 / looks]" in md and "| looks |" in md and "](claims.png)" in md
    assert (out / "claims.png").read_bytes()[:8] == PNG_MAGIC
    assert "| looks |" not in (tmp_path / "three" / "report.md").read_text()      # one number: in the header
    bad = subprocess.run([sys.executable, "-m", "experiments.report", f"runs=[{tmp_path / 'runs'}]",
                          f"out={tmp_path / 'bad'}", "looks={modumorph:2}"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert bad.returncode != 0 and "key 'modumorph'" in bad.stderr and not (tmp_path / "bad").exists()


def test_mean_curve_band():
    x = np.arange(0, 1000, 10.0)
    grid, m, lo, hi, n = mean_curve([(x, x), (x, x + 2)], points=50, smooth=False)
    assert np.allclose(m, grid + 1)
    half = stats.t.ppf(0.975, 1) * np.sqrt(2) / np.sqrt(2)
    assert np.allclose(hi - m, half) and np.allclose(m - lo, half)
    _, m1, lo1, _, _ = mean_curve([(x, x)], points=20, smooth=False)
    assert np.isnan(lo1).all() and np.isfinite(m1).all()
    # a shorter seed: the mean and its band end with it (no jump to the longer seed alone)
    grid, m, lo, _, n = mean_curve([(x, x), (x[:50], x[:50] + 2)], points=100, smooth=False)
    assert n[0] == 2 and n[-1] == 1 and np.isnan(lo[-1]) and np.isnan(m[-1])
    inside = grid <= x[49]
    assert np.allclose(m[inside], grid[inside] + 1) and np.isnan(m[~inside]).all()
    # what mean_curve leaves out there: the seeds that reach furthest, from where the first one ends
    assert furthest_mean_curve([(x, x), (x[:50], x[:50] + 2)]) is None       # one seed reaches furthest: no mean
    assert furthest_mean_curve([(x, x), (x, x + 4)]) is None                  # all end together
    g, fm, flo, fhi, k = furthest_mean_curve([(x, x), (x, x + 4), (x[:50], x[:50] + 2)], points=100, smooth=False)
    assert k == 2 and g[0] >= x[49] and g[-1] == x[-1] and np.allclose(fm, g + 2)
    assert np.isfinite(flo).all() and np.all(flo < fm) and np.all(fhi > fm)


def test_learning_curves_show_seeds_below_three_and_a_band_from_three(tmp_path, monkeypatch):
    """2 seeds: each seed drawn thin and no band (t = 12.7 makes it meaningless); 3 seeds: a band, no seed lines."""
    for seed in (0, 1):
        make_run(tmp_path / "runs", f"ft-rmomo-s{seed}", arch="rmomo", seed=seed, evals=())
    for seed in (0, 1, 2):
        make_run(tmp_path / "runs", f"ft-modumorph-s{seed}", arch="modumorph", seed=seed, evals=())
    seen = {}

    def capture(curves, out, **kw):
        seen.update(curves=curves, members=kw["members"], tails=kw["tails"])
        return real(curves, out, **kw)
    real = plots.mean_curves
    monkeypatch.setattr(plots, "mean_curves", capture)
    build_report([tmp_path / "runs"], tmp_path / "report")
    _, _, lo2, hi2 = seen["curves"]["rmomo"]
    _, _, lo3, hi3 = seen["curves"]["modumorph"]
    assert lo2 is None and hi2 is None and len(seen["members"]["rmomo"]) == 2
    assert np.isfinite(lo3).any() and np.all(lo3[np.isfinite(lo3)] <= hi3[np.isfinite(lo3)])
    assert seen["members"]["modumorph"] == [] and seen["tails"] == {}     # all seeds of a model end together
    # each thin line is that seed's own curve (40 iterations: a smoothing window of 1), ending at its last return
    for (x, y), seed in zip(seen["members"]["rmomo"], (0, 1)):
        rows = _csv(tmp_path / "runs" / f"ft-rmomo-s{seed}" / "metrics.csv")
        assert x[-1] == float(rows[-1]["env_steps"])
        assert y[-1] == pytest.approx(float(rows[-1]["episode_return"]), abs=1e-6)
    # 3 seeds, one stopped early: the mean and band end with it, and each seed is drawn thin to its own end
    make_run(tmp_path / "runs2", "ft-modumorph-s0", arch="modumorph", seed=0, evals=(), iters=25)
    for seed in (1, 2):
        make_run(tmp_path / "runs2", f"ft-modumorph-s{seed}", arch="modumorph", seed=seed, evals=())
    build_report([tmp_path / "runs2"], tmp_path / "report2")
    grid, m, lo, _ = seen["curves"]["modumorph"]
    assert np.isnan(m[-1]) and np.isnan(lo[-1]) and np.isfinite(m[0]) and np.isfinite(lo[0])
    assert grid[np.isfinite(m)].max() <= 25 * 1000
    assert [x[-1] for x, _ in seen["members"]["modumorph"]] == [25 * 1000, 40 * 1000, 40 * 1000]
    # past 25 k steps, dashed: the mean of the two seeds that reach 40 k (2 seeds: no band), labelled so
    tx, tm, tlo, thi, label = seen["tails"]["modumorph"]
    assert tx[0] >= 25 * 1000 and tx[-1] == 40 * 1000 and tlo is None and thi is None
    last = [float(_csv(tmp_path / "runs2" / f"ft-modumorph-s{s}" / "metrics.csv")[-1]["episode_return"])
            for s in (1, 2)]
    assert tm[-1] == pytest.approx(np.mean(last), abs=1e-6)     # a smoothing window of one
    assert label == "modumorph: the 2 seeds that reach 40,000"


def test_find_run_dirs(tmp_path):
    a, _ = make_run(tmp_path / "study", "a", evals=(), metrics=False)
    b, _ = make_run(tmp_path / "study" / "nested", "b", evals=(), metrics=False)
    assert find_run_dirs([tmp_path / "study"]) == [a, b]
    assert find_run_dirs([a, tmp_path / "study"]) == [a, b]
    (tmp_path / "empty").mkdir()
    with pytest.raises(NotARunDir, match="not a run directory"):
        find_run_dirs([tmp_path / "empty"])


def test_cli_rejects_a_non_run_path(tmp_path):
    p = subprocess.run([sys.executable, "-m", "experiments.report", "runs=[/nonexistent]", f"out={tmp_path / 'o'}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "error: /nonexistent: not a run directory (no config.yaml)" in p.stderr
    assert not (tmp_path / "o").exists()


def _check_manifest(name: str, runs_glob: str):
    """Every run directory of results/<runs_glob>/ stands in exactly one list of results/<name>, so a run brought
    home without a decision fails; no model's seed is pooled twice, pending included (e.g. a rerun of a seed beside
    its first run); a pending run is not yet pooled; some run is pooled. Returns the manifest."""
    m = read_manifest(ROOT / "results" / name)
    listed = [p.resolve() for p in m.runs + m.pending + list(m.excluded)]
    assert len(listed) == len(set(listed))
    on_file = {p.resolve() for d in sorted((ROOT / "results").glob(runs_glob)) for p in find_run_dirs([d])}
    assert not on_file - set(listed), f"runs of results/{runs_glob}/ in no list of results/{name}: " \
                                      f"{sorted(str(p) for p in on_file - set(listed))}"
    seeds = [(r.task, r.arch, r.seed) for r in map(read_run, m.runs + m.pending)]
    assert len(seeds) == len(set(seeds)), sorted(s for s in seeds if seeds.count(s) > 1)
    assert m.runs and all(why.strip() for why in m.excluded.values())
    Looks.parse(m.looks)
    return m


def test_the_claims_manifest_holds_every_paper_run_once_and_each_seed_once():
    """results/claims.yaml (the 18-20 M-step claims table of docs/results.md) holds every run of results/paper_s*/."""
    assert _check_manifest("claims.yaml", "paper_s*").excluded


def converged_violations(runs: list[Run], physics: str, task: str) -> dict[str, list[str]]:
    """What keeps each run out of a converged-physics comparison: another physics digest, task, rollout geometry than
    1,024 envs x 80 steps, or precision than fp32; {run: the rules it breaks} for the runs that break any."""
    def off(r):
        ppo = r.cfg.get("ppo") or {}
        return [k for k, bad in [("physics", [d[:8] for d in r.physics] != [physics]),
                                 ("task", r.task != task),
                                 ("geometry", (ppo.get("num_envs"), ppo.get("rollout_len")) != (1024, 80)),
                                 ("precision", r.cfg.get("precision") != "fp32")] if bad]
    return {str(r.path): off(r) for r in runs if off(r)}


def test_the_converged_physics_manifest_pools_one_physics_geometry_and_precision():
    """results/claims_converged.yaml (R-MoMo against ModuMorph at 20 M steps on today's physics) pools only runs of
    physics a3c4a671 at 1,024 envs x 80 steps in fp32, each seed once, at least three seeds of each model; the physics
    rule is seen to fail on a run of the capped solver."""
    m = read_manifest(ROOT / "results" / "claims_converged.yaml")
    runs = [read_run(p) for p in m.runs + m.pending]
    seeds = [(r.task, r.arch, r.seed) for r in runs]
    assert len(seeds) == len(set(seeds)), sorted(s for s in seeds if seeds.count(s) > 1)
    assert not converged_violations(runs, "a3c4a671", "ft")
    counts = {a: sum(r.arch == a for r in runs) for a in ("rmomo", "modumorph")}
    assert min(counts.values()) >= 3, counts
    Looks.parse(m.looks)
    capped = read_run(read_manifest(ROOT / "results" / "claims.yaml").runs[0])
    assert "physics" in converged_violations([capped], "a3c4a671", "ft")[str(capped.path)]


INCLINE_SETS = {"val", "test", "train", "variants"}


def incline_design_violations(pooled: list[tuple[str, int, set]], pending: list[tuple[str, int]],
                              looks: int) -> list[str]:
    """What breaks incline's converged-physics design (docs/leases.md, fixed in session 70, its continuation in
    session 81): R-MoMo and ModuMorph, seeds 0-2 for the one look (looks 1), seeds 3-4 pending after it for the
    second, at five a side (looks 2). `pooled`: (arch, seed, the sets it was evaluated on) of each pooled run;
    `pending`: (arch, seed). A look pools exactly its seeds of both models, each evaluated on val, test70, the train
    robots and the variants; before the first look nothing is pooled and only seeds 0-2 wait; after the last, nothing."""
    out = []
    models = {"rmomo", "modumorph"}
    named = [(a, s) for a, s, _ in pooled]
    for arch, seed in named + list(pending):
        if arch not in models or seed not in range(5):
            out.append(f"{arch} seed {seed}: not R-MoMo or ModuMorph with a seed of 0-4")
    if looks not in (1, 2):
        out.append(f"looks {looks}: the design has two looks, at three and at five seeds a side")
        return out
    n = 3 if looks == 1 else 5
    have = set(named)
    if (pooled or looks == 2) and have != {(a, s) for a in models for s in range(n)}:      # look 1 may not have come
        out.append(f"look {looks} pools {sorted(have)}, not seeds 0-{n - 1} of both models")
    for a, s, sets in pooled:
        if not INCLINE_SETS <= set(sets):
            out.append(f"{a} seed {s} pooled without {sorted(INCLINE_SETS - set(sets))}")
    waiting = range(3) if not pooled else range(3, 5) if looks == 1 else range(0)
    out += [f"{a} seed {s} pending at look {looks} ({'nothing pooled' if not pooled else 'pooled'})"
            for a, s in pending if s not in waiting]
    return out


def test_the_incline_design_rule_fails_where_the_design_is_broken():
    full = lambda n: [(a, s, INCLINE_SETS) for a in ("rmomo", "modumorph") for s in range(n)]
    assert not incline_design_violations([], [("rmomo", 0), ("modumorph", 2)], 1)         # before the first look
    assert not incline_design_violations(full(3), [("rmomo", 3)], 1)                     # after it, seed 3 waits
    assert not incline_design_violations(full(5), [], 2)                                 # the second look
    assert incline_design_violations(full(3)[:5], [], 1)                                 # a look one run short
    assert incline_design_violations(full(3)[:5] + [("modumorph", 2, {"val", "test", "train"})], [], 1)  # no variants
    assert incline_design_violations([], [("rmomo", 3)], 1)                              # seed 3 before the look
    assert incline_design_violations(full(3), [("rmomo", 1)], 1)                         # a seed left behind
    assert incline_design_violations(full(5), [("rmomo", 5)], 2)                         # seed 5, and pending after
    assert incline_design_violations(full(3), [], 2)                                     # look 2 at three a side
    assert incline_design_violations([("metamorph", 0, INCLINE_SETS)], [], 1)


def test_the_converged_incline_manifest_follows_its_design():
    """results/claims_converged_incline.yaml (incline on the converged physics, design fixed in session 70) holds
    every incline run of results/ab_geometry_s*/ once, each of physics 8e90ddac at 1,024 envs x 80 steps in fp32, and
    follows the design's looks (`incline_design_violations`; the first taken in session 82). The task rule is seen
    to fail on an ft run of that study."""
    m = _check_manifest("claims_converged_incline.yaml", "ab_geometry_s*/incline-*")
    pooled, pending = [read_run(p) for p in m.runs], [read_run(p) for p in m.pending]
    assert not converged_violations(pooled + pending, "8e90ddac", "incline")
    assert set(m.looks) == {"incline/rmomo"}, m.looks
    assert not incline_design_violations([(r.arch, r.seed, set(r.evals)) for r in pooled],
                                         [(r.arch, r.seed) for r in pending], m.looks["incline/rmomo"])
    ft = read_run(read_manifest(ROOT / "results" / "claims_converged.yaml").runs[0])
    assert "task" in converged_violations([ft], "8e90ddac", "incline")[str(ft.path)]


def design_100m_violations(runs: list[Run]) -> list[str]:
    """What breaks the 100 M-step claims' design (docs/leases.md, plan item 6, fixed in session 50 before any of
    its runs): the paper's schedule run to its end (total_steps 1e8, no stop_at), the converged solver (16
    iterations), one precision for every run. One line per run and rule broken."""
    bad = [f"{r.path}: {why}" for r in runs for why, broken in [
        (f"total_steps {r.cfg.get('total_steps')}, expected 100000000", r.cfg.get("total_steps") != 100_000_000),
        (f"stop_at {r.cfg.get('stop_at')}, expected none", r.cfg.get("stop_at") is not None),
        (f"env.iterations {(r.cfg.get('env') or {}).get('iterations')}, expected 16",
         (r.cfg.get("env") or {}).get("iterations") != 16)] if broken]
    precisions = sorted({str(r.cfg.get("precision")) for r in runs})
    return bad + ([f"precisions {precisions}: expected one for every run"] if len(precisions) > 1 else [])


def test_the_100m_claims_manifest_holds_every_100m_run_and_only_the_design():
    """results/claims100.yaml (the 100 M-step claims, created with the first finished run) holds every run of
    results/paper100_s*/, and its pooled and pending runs follow the design fixed before them; the rule is seen
    to fail on the 18-20 M runs (stopped early, the capped solver, two precisions)."""
    capped = [read_run(p) for p in read_manifest(ROOT / "results" / "claims.yaml").runs]
    broken = design_100m_violations(capped)
    assert any("stop_at 2" in b for b in broken) and any("env.iterations 5," in b for b in broken)
    assert design_100m_violations(capped[:1] + [read_run(ROOT / "results" / "ab_precision_s51" /
                                                         "ft-modumorph-bf16-s0")])[-1].startswith("precisions")
    if not (ROOT / "results" / "claims100.yaml").exists() and not list((ROOT / "results").glob("paper100_s*")):
        pytest.skip("no 100 M-step run on file yet (docs/leases.md, plan item 6)")
    m = _check_manifest("claims100.yaml", "paper100_s*")
    assert not design_100m_violations([read_run(p) for p in m.runs + m.pending])


def test_a_manifest_names_the_file_and_entry_of_each_mistake(tmp_path):
    """read_manifest: globs relative to the manifest's folder, folders of runs allowed; an unknown key, an entry
    that matches nothing, a run reached twice (two entries, or pooled and excluded), an exclusion without its reason
    and an empty `runs` are errors naming the file and the entry; the CLI takes a manifest or runs=, not both."""
    a, _ = make_run(tmp_path / "s1", "ft-rmomo-s0", evals=(), metrics=False)
    b, _ = make_run(tmp_path / "s1", "ft-rmomo-s1", seed=1, evals=(), metrics=False)
    c, _ = make_run(tmp_path / "s2" / "nested", "ft-modumorph-s0", arch="modumorph", evals=(), metrics=False)
    f = tmp_path / "m.yaml"

    def manifest(**kw):
        f.write_text(yaml.safe_dump(kw))
        return read_manifest(f)

    m = manifest(runs=["s1/ft-*"], pending=["s2"], excluded={}, looks={"ft/rmomo": 2})
    assert m.runs == [a, b] and m.pending == [c] and m.looks == {"ft/rmomo": 2}
    assert manifest(runs=["s1/ft-rmomo-s[0]"], excluded={"s1/ft-rmomo-s1": "a bad seed"}).excluded == {b: "a bad seed"}
    for kw, message in [
            (dict(runs=["s1/*"], seeds=[0]), r"m.yaml: unknown key\(s\) seeds"),
            (dict(runs=["s1/*", "s3/*"]), r"m.yaml: runs\[1\] 's3/\*': matches no run directory"),
            (dict(runs=["s1/*", "s1/ft-rmomo-s1"]), r"runs\[1\] 's1/ft-rmomo-s1': .*ft-rmomo-s1 is already reached by "
                                                      r"runs\[0\] 's1/\*'"),
            (dict(runs=["s1/*"], excluded={"s1/ft-rmomo-s0": "why"}), r"runs\[0\] 's1/\*': .*ft-rmomo-s0 is already "
                                                                       r"reached by excluded 's1/ft-rmomo-s0'"),
            (dict(runs=["s1/*"], excluded={"s2": " "}), r"excluded 's2': say why it is left out"),
            (dict(excluded={"s1/*": "why"}), r"m.yaml: runs: expected at least one run, pooled \(runs\) or"),
            (dict(runs="s1/*"), r"runs: expected a list of globs")]:
        with pytest.raises(ValueError, match=message):
            manifest(**kw)
    assert manifest(pending=["s1/*"]).runs == []          # trained before a design's first look
    with pytest.raises(ValueError, match=r"m.yaml: runs: nothing pooled yet \(2 pending for the first look\)"):
        report_cli(ReportConfig(manifest=str(f), out=str(tmp_path / "o")))
    f.write_text(yaml.safe_dump(dict(runs=["s1/*"])))
    p = subprocess.run([sys.executable, "-m", "experiments.report", f"manifest={f}", f"runs=[{a}]",
                        f"out={tmp_path / 'o'}"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "it gives the runs and the looks; drop runs= and looks=" in p.stderr, p.stderr
    assert not (tmp_path / "o").exists()


def test_classify_main_size_context():
    def run(n=None, ctx=None, task="ft"):
        return Run(Path("x"), {"env": {"task": task, "context_features": ctx}, "arch": "rmomo", "num_robots": n})
    smoke = [run(2), run(2), run(2, ["gear"])]                 # tiny runs: all on 2 robots
    classify(smoke)
    assert [r.kind for r in smoke] == ["main", "main", "context"]
    study = [run(25), run(50), run(100), run(None, task="incline"), run(10, task="incline")]
    classify(study)
    assert [r.kind for r in study] == ["size", "size", "main", "main", "size"]
    mixed = [run(None), run(25), run(None, ["gear"]), run(25, ["gear"]), run(None, list(
        ["body_pos", "body_ipos", "body_iquat", "geom_quat", "body_mass", "body_shape", "jnt_pos", "joint_range",
         "joint_axis", "gear"]))]
    classify(mixed)
    assert [r.kind for r in mixed] == ["main", "size", "context", "other", "main"]


def test_variants_of_an_architecture_are_reported_apart(tmp_path):
    """The arms of an A/B study (same task and arch, different training keys) are separate groups named by the keys
    that differ; seeds of one arm pool and do not make variants; a key a run's config lacks (an older run) counts at
    today's default (an old run without `precision` ran fp32, so a bf16 run stands apart from it)."""
    def run(seed, model=None, precision=None, extra=None):
        cfg = {"env": {"task": "ft"}, "arch": "rmomo", "seed": seed, "model": {"scale_after_cell": model,
                                                                               "d_model": 128}}
        if precision:
            cfg["precision"] = precision
        cfg.update(extra or {})
        return Run(Path(f"r{seed}"), cfg)
    runs = [run(0), run(1), run(0, True), run(1, True), run(0, True, "bf16"), run(0, extra={"arch": "modumorph"})]
    name_variants(runs)
    assert [r.name for r in runs] == ["rmomo, scale_after_cell=null, precision=fp32"] * 2 \
        + ["rmomo, scale_after_cell=true, precision=fp32"] * 2 + ["rmomo, scale_after_cell=true, precision=bf16"] \
        + ["modumorph"]
    same = [run(0, True, "bf16"), run(1, True, "tf32")]
    name_variants(same)
    assert [r.name for r in same] == ["rmomo, precision=bf16", "rmomo, precision=tf32"]
    solver = [run(0), run(1, extra={"env": {"task": "ft", "linalg": "pallas"}})]    # the same physics: seeds pool
    name_variants(solver)
    assert [r.name for r in solver] == ["rmomo", "rmomo"]

    root = tmp_path / "runs"
    for name, flag in (("a-s0", None), ("a-s1", None), ("b-s0", True)):
        d, _ = make_run(root, name, seed=int(name[-1]), evals=("train",))
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        cfg["model"] = {"scale_after_cell": flag}
        (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    md = build_report([root], tmp_path / "out").read_text()
    assert "| ft | rmomo, scale_after_cell=null | 2 |" in md and "| ft | rmomo, scale_after_cell=true | 1 |" in md
    # claims compare only the groups named by the architecture alone
    assert "(A/B arms are not compared: rmomo, scale_after_cell=null; rmomo, scale_after_cell=true)" in md
    assert not (tmp_path / "out" / "claims.csv").exists()


def test_the_arm_chosen_on_val_and_whether_the_seeds_separate_it(tmp_path):
    """"Chosen on val" (the paper's rule for the KL threshold): per task and architecture with two or more arms
    that evaluated val, the arm with the higher mean over seeds of the seeds' mean val return, its margin over the
    runner-up and Welch's two-sided p over seeds; an architecture with one arm, or arms without val, gets no row."""
    root = tmp_path / "runs"
    seeds = {}
    for arm, kl, returns in (("kl003", 0.03, (400, 900)), ("kl005", 0.05, (500, 1200))):
        for seed in (0, 1, 2):
            d, per = make_run(root, f"ft-modumorph-{arm}-s{seed}", arch="modumorph", seed=seed, evals=("val", "test"),
                              metrics=False, returns=returns)
            cfg = yaml.safe_load((d / "config.yaml").read_text())
            cfg["ppo"] = {"kl_threshold": kl}
            (d / "config.yaml").write_text(yaml.safe_dump(cfg))
            seeds.setdefault(f"modumorph, kl_threshold={kl}", []).append(np.mean(list(per["val"].values())))
    make_run(root, "ft-rmomo-s0", arch="rmomo", evals=("val", "test"), metrics=False)      # one arm: no choice
    md = build_report([root], tmp_path / "out").read_text()
    rows = _csv(tmp_path / "out" / "choice_on_val.csv")
    assert {r["arch"] for r in rows} == {"modumorph"} and len(rows) == 2
    means = {k: float(np.mean(v)) for k, v in seeds.items()}
    best = max(means, key=means.get)
    other = min(means, key=means.get)
    by_arm = {r["arm"]: r for r in rows}
    for arm, v in seeds.items():
        assert float(by_arm[arm]["val_return"]) == pytest.approx(np.mean(v))
        assert float(by_arm[arm]["sd_over_seeds"]) == pytest.approx(np.std(v, ddof=1))
        assert int(by_arm[arm]["seeds"]) == 3
    assert by_arm[best]["chosen"] == "True" and by_arm[other]["chosen"] == "False"
    assert float(by_arm[best]["margin"]) == pytest.approx(means[best] - means[other])
    p = stats.ttest_ind(seeds[best], seeds[other], equal_var=False).pvalue
    assert float(by_arm[best]["p_two_sided"]) == pytest.approx(p)
    assert f"| ft | modumorph | {best} | 3 | {means[best]:.1f} |" in md and "**chosen**" in md


def test_ab_arms_side_by_side_with_welch_ci_over_seeds(tmp_path):
    """"A/B arms" (arms.csv): per architecture with two or more arms, each pair on training and on every eval set
    both evaluated: means over seeds, the difference first - second with its 95% Welch CI and two-sided p over seeds,
    and how many of the first arm's seeds lie below, inside and above the second's seed range; an architecture with
    one arm gets no row, and an arm with one seed gets no CI."""
    root = tmp_path / "runs"
    vals: dict = {}
    for arm, iters, returns, seeds in (("capped", 5, (400, 900), (0, 1, 2)), ("converged", 16, (700, 1500), (0, 1))):
        for seed in seeds:
            d, per = make_run(root, f"ft-metamorph-{arm}-s{seed}", arch="metamorph", seed=seed,
                              evals=("test",), returns=returns)
            cfg = yaml.safe_load((d / "config.yaml").read_text())
            cfg["env"]["iterations"] = iters
            (d / "config.yaml").write_text(yaml.safe_dump(cfg))
            vals.setdefault(iters, []).append(np.mean(list(per["test"].values())))
    make_run(root, "ft-metamorph-capped-s3", arch="metamorph", seed=3, evals=("test",), metrics=False,
             eval_steps=10_000)         # no learning curve: it sets no point of training (nor joins test at 40 k)
    cfg = yaml.safe_load((root / "ft-metamorph-capped-s3" / "config.yaml").read_text())
    cfg["env"]["iterations"] = 5
    (root / "ft-metamorph-capped-s3" / "config.yaml").write_text(yaml.safe_dump(cfg))
    make_run(root, "ft-rmemo-s0", arch="rmemo", evals=("test",))                     # one arm: no pair
    make_run(root, "ft-rmemo-s1", arch="rmemo", seed=1, evals=("test",))
    md = build_report([root], tmp_path / "out").read_text()
    rows = _csv(tmp_path / "out" / "arms.csv")
    assert {r["set"] for r in rows} == {"training", "test"}
    assert {(r["arm_a"], r["arm_b"]) for r in rows} == {("metamorph, iterations=16", "metamorph, iterations=5")}
    test = next(r for r in rows if r["set"] == "test")
    a, b = np.asarray(vals[16]), np.asarray(vals[5])
    assert (int(test["seeds_a"]), int(test["seeds_b"])) == (2, 3)
    assert float(test["difference"]) == pytest.approx(a.mean() - b.mean())
    ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    assert float(test["ci95_low"]) == pytest.approx(ci.low) and float(test["ci95_high"]) == pytest.approx(ci.high)
    assert float(test["p_two_sided"]) == pytest.approx(stats.ttest_ind(a, b, equal_var=False).pvalue)
    assert int(test["a_seeds_in_b_range"]) == int(((a >= b.min()) & (a <= b.max())).sum())
    assert int(test["a_seeds_below_b_range"]) == int((a < b.min()).sum())
    assert int(test["a_seeds_above_b_range"]) == int((a > b.max()).sum())
    assert sum(int(test[f"a_seeds_{k}_b_range"]) for k in ("below", "in", "above")) == 2
    # non-inferiority, the training claims' test: H0 mean(a) - mean(b) <= -5% of |mean(b)|, and the seeds a side
    # that a two-sided 95% test of the distance from that bound would need for 80% power (normal approximation)
    m = 0.05 * abs(b.mean())
    want = stats.ttest_ind(a, b - m, equal_var=False, alternative="greater").pvalue
    assert float(test["p_a_not_worse"]) == pytest.approx(want)
    z = stats.norm.ppf(0.975) + stats.norm.ppf(0.8)
    n = np.ceil(z ** 2 * (a.var(ddof=1) + b.var(ddof=1)) / (a.mean() - b.mean() + m) ** 2)
    assert float(test["seeds_for_not_worse"]) == n
    assert "| ft | metamorph, iterations=16 − metamorph, iterations=5 | test | 2 / 3 |" in md
    training = next(r for r in rows if r["set"] == "training")
    assert (int(training["seeds_a"]), int(training["seeds_b"])) == (2, 3) and float(training["env_steps"]) == 40_000
    # one seed on a side: the difference without a CI or p
    shutil.rmtree(root / "ft-metamorph-converged-s1")
    build_report([root], tmp_path / "out1")
    one = next(r for r in _csv(tmp_path / "out1" / "arms.csv") if r["set"] == "test")
    assert int(one["seeds_a"]) == 1 and float(one["difference"]) == pytest.approx(vals[16][0] - b.mean())
    assert one["ci95_low"] == one["ci95_high"] == one["p_two_sided"] == ""          # nan, written empty
    assert one["p_a_not_worse"] == one["seeds_for_not_worse"] == ""


def test_rates_per_phase_are_medians_without_the_slow_iterations(tmp_path):
    """"Rates per phase" (rates.csv): per run, the iterations that ran all `ppo.epochs` and those the KL stop cut
    short, each the median of rollout_sps / update_sps / sps and the mean epochs run, leaving out the iterations
    slower than 3x the run's median wall time (the calls' first iterations, with their compilation); and the whole
    run: env steps over the summed time of every iteration but each call's first, as devices.yaml's starts say."""
    d, _ = make_run(tmp_path / "runs", "ft-rmomo-s0", evals=(), metrics=False)
    cfg = yaml.safe_load((d / "config.yaml").read_text())
    cfg["ppo"] = {"epochs": 4}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    rng = np.random.default_rng(0)
    rows = []
    for it in range(1, 31):
        epochs = 4 if it <= 10 else float(rng.choice([0.5, 1.25, 2.0]))
        wall = 60.0 if it in (1, 17) else float(rng.uniform(1, 2))            # 1 and 17: the calls' first iterations
        rows.append({"iteration": it, "env_steps": 1000 * it, "episode_return": it, "wall_s": wall,
                     "rollout_sps": rng.uniform(30, 40), "update_sps": rng.uniform(10, 90), "sps": 1000 / wall,
                     "epochs_run": epochs})
    with (d / "metrics.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (d / "devices.yaml").write_text(yaml.safe_dump([dict(start_iteration=0), dict(start_iteration=16)]))
    build_report([tmp_path / "runs"], tmp_path / "out")
    got = {r["phase"]: r for r in _csv(tmp_path / "out" / "rates.csv")}
    assert set(got) == {"all epochs", "KL stop active", "whole run"}
    for phase, full in (("all epochs", True), ("KL stop active", False)):
        sel = [r for r in rows if (r["epochs_run"] == 4) == full and r["wall_s"] < 60]
        assert int(got[phase]["iterations"]) == len(sel) and int(got[phase]["left_out"]) == 2
        for k in ("rollout_sps", "update_sps", "sps"):
            assert float(got[phase][k]) == pytest.approx(np.median([r[k] for r in sel]))
        assert float(got[phase]["mean_epochs"]) == pytest.approx(np.mean([r["epochs_run"] for r in sel]))
    whole, kept = got["whole run"], [r for r in rows if r["iteration"] not in (1, 17)]
    assert int(whole["iterations"]) == 28 and int(whole["left_out"]) == 2
    assert float(whole["sps"]) == pytest.approx(1000 * 28 / sum(r["wall_s"] for r in kept))
    for k in ("rollout_sps", "update_sps"):
        assert float(whole[k]) == pytest.approx(28 / sum(1 / r[k] for r in kept))


def test_health_flags_what_a_run_should_be_read_for(tmp_path):
    """"Health" (health.csv): per run over every iteration, the first minibatch's largest |ratio - 1| and |KL|, the
    unstable episodes, the first KL stop, the largest |value_mean|, the non-finite iterations and the physics of its
    calls; flagged: a ratio off 1 beyond Run.RATIO_TOLERANCE, non-finite metrics, unstable episodes, two physics, a
    run short of the iteration its config ends it at."""
    rng = np.random.default_rng(1)
    for name, sick in (("ft-rmomo-s0", False), ("ft-rmomo-s1", True)):
        d, _ = make_run(tmp_path / "runs", name, seed=int(sick), evals=(), metrics=False)
        rows = []
        for it in range(1, 21):
            rows.append({"iteration": it, "env_steps": 1000 * it, "episode_return": it, "epochs_run": 8 if it < 6
                         else 2, "first_ratio": 1 + (rng.uniform(-1e-7, 1e-7) if not (sick and it == 9) else 2e-3),
                         "first_kl": rng.uniform(-4e-8, 4e-8), "instabilities": 3 if sick and it == 4 else 0,
                         "value_mean": -2.5 if it == 7 else 0.1 * it,
                         "loss": float("nan") if sick and it == 11 else 0.5, "wall_s": 2.0, "sps": 500.0})
        with (d / "metrics.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        if sick:                                          # a run a time limit stopped, to go on in a later lease
            cfg = yaml.safe_load((d / "config.yaml").read_text())
            (d / "config.yaml").write_text(yaml.safe_dump({**cfg, "total_steps": 100_000_000, "stop_at": 245}))
        digests = ["a3c4a671dd355561", "d38de03bfa874fe9" if sick else "a3c4a671dd355561"]
        (d / "devices.yaml").write_text(yaml.safe_dump([dict(start_iteration=0, model_digest=digests[0]),
                                                        dict(start_iteration=12, model_digest=digests[1])]))
    build_report([tmp_path / "runs"], tmp_path / "out")
    ok, sick = sorted(_csv(tmp_path / "out" / "health.csv"), key=lambda r: r["seed"])
    assert float(ok["first_ratio_off"]) <= 1e-7 and float(ok["first_kl"]) <= 4e-8 and ok["flags"] == ""
    assert int(ok["first_kl_stop"]) == 6 and float(ok["value_max"]) == 2.5 and ok["physics"] == "a3c4a671"
    assert float(sick["first_ratio_off"]) == pytest.approx(2e-3) and int(sick["unstable_episodes"]) == 3
    assert int(sick["nonfinite_iterations"]) == 1 and sick["physics"] == "a3c4a671 → d38de03b"   # as the runs table
    assert sick["flags"] == ("first-minibatch ratio off 1 by 2.0e-03; non-finite metrics in 1 iterations; "
                             "3 unstable episodes; physics changed: a3c4a671 → d38de03b; "
                             "stopped at iteration 20 of 245")
    assert "| ok |" in (tmp_path / "out" / "report.md").read_text()


def test_collect_keeps_the_small_artefacts_and_rebuilds_the_report(tmp_path):
    """experiments.collect: config, metrics and eval JSON of every run under a folder (archive or folder), without
    checkpoints or TensorBoard files; the report builds from what it kept; an oversized file is left out."""
    import tarfile
    from experiments import collect
    study = tmp_path / "runs" / "study"
    for arch in ("rmomo", "modumorph"):
        d, _ = make_run(study, f"ft-{arch}-s0", arch=arch)
        (d / "checkpoints" / "40").mkdir(parents=True)
        (d / "checkpoints" / "40" / "state").write_bytes(b"x" * 4096)
        (d / "tb").mkdir()
        (d / "tb" / "events.out").write_bytes(b"x")
    # the rmomo run was started on an H100 and resumed on an H200; the modumorph run is older than devices.yaml
    entry = dict(platform="gpu", num_devices=1, processes=1)
    (study / "ft-rmomo-s0" / "devices.yaml").write_text(yaml.safe_dump([
        dict(started="2025-01-01T00:00:00+00:00", start_iteration=0, device_kind="NVIDIA H100 80GB HBM3", **entry),
        dict(started="2025-01-02T00:00:00+00:00", start_iteration=20, device_kind="NVIDIA H200", **entry),
        dict(started="2025-01-03T00:00:00+00:00", start_iteration=30, device_kind="NVIDIA H200", **entry)]))
    (study / "ft-modumorph-s0" / "unhealthy.txt").write_text("iteration 1's value estimates average 4.6e+05\n")
    assert collect.main([f"runs=[{study}]", f"out={tmp_path / 'a.tar.gz'}"]) == 0
    with tarfile.open(tmp_path / "a.tar.gz") as tar:
        names = sorted(tar.getnames())
    assert names == sorted([f"study/ft-{a}-s0/{f}" for a in ("rmomo", "modumorph")
                            for f in ("config.yaml", "metrics.csv", "eval/train.json", "eval/test.json",
                                      "eval/variants.json")] + ["study/ft-rmomo-s0/devices.yaml",
                                                                "study/ft-modumorph-s0/unhealthy.txt"])
    (study / "ft-modumorph-s0" / "unhealthy.txt").unlink()
    assert collect.main([f"runs=[{study}]", f"out={tmp_path / 'results'}"]) == 0
    kept = tmp_path / "results" / "study"
    assert sorted(p.name for p in kept.iterdir()) == ["ft-modumorph-s0", "ft-rmomo-s0"]
    assert not (kept / "ft-rmomo-s0" / "checkpoints").exists()
    for f in ("metrics.csv", "devices.yaml"):
        assert (kept / "ft-rmomo-s0" / f).read_bytes() == (study / "ft-rmomo-s0" / f).read_bytes()
    # the report from the kept files is the report from the run directories
    def text(dirs, out):          # without the build time
        return re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d", "", build_report(find_run_dirs(dirs), out).read_text())
    assert text([kept], tmp_path / "report") == text([study], tmp_path / "report0").replace(str(study), str(kept))
    # a run stopped because it starts broken is in no figure or table, and the report says why
    (kept / "ft-rmomo-s0" / "unhealthy.txt").write_text("iteration 1's value estimates average 4.6e+05\n")
    md1 = build_report(find_run_dirs([kept]), tmp_path / "report1").read_text()
    assert "ft-rmomo-s0`: left out: it stopped because it starts broken (iteration 1's value estimates" in md1
    assert not any(l.startswith("| `") and "ft-rmomo-s0`" in l for l in md1.splitlines())
    (kept / "ft-rmomo-s0" / "unhealthy.txt").unlink()
    # the runs table names each run's devices (wall hours depend on them); "?" for a run without devices.yaml
    md = (tmp_path / "report" / "report.md").read_text()
    row = lambda arch: next(l for l in md.splitlines() if l.startswith(f"| `") and f"ft-{arch}-s0`" in l)
    assert "| device |" in md and "| NVIDIA H100 80GB HBM3 + NVIDIA H200 |" in row("rmomo")
    assert "| ? |" in row("modumorph")
    devices = {Path(r["run"]).name: r["device"] for r in _csv(tmp_path / "report" / "runs.csv")}
    assert devices == {"ft-rmomo-s0": "NVIDIA H100 80GB HBM3 + NVIDIA H200", "ft-modumorph-s0": "?"}
    assert collect.main([f"runs=[{study / 'ft-rmomo-s0'}]", f"out={tmp_path / 'one'}", "max_file_mb=0.01"]) == 0
    assert (tmp_path / "one" / "ft-rmomo-s0" / "config.yaml").exists()
    assert not (tmp_path / "one" / "ft-rmomo-s0" / "eval" / "variants.json").exists()     # > 10 KB: left out


def test_runs_of_one_seed_are_one_sample_in_the_claims(tmp_path):
    """The same seed run twice (e.g. on another GPU model) is one sample of the claims, the mean of its runs, and
    the report says so."""
    from mjx_morph.eval.runs import read_run
    from mjx_morph.eval.stats import repeated_seeds, seed_set_means
    made = [make_run(tmp_path / "runs", name, arch="rmomo", seed=seed, metrics=False)
            for name, seed in (("a-s0", 0), ("b-s0", 0), ("a-s1", 1))]
    runs = [read_run(p) for p, _ in made]
    means = seed_set_means(runs, "test")
    per = [np.mean(list(pr["test"].values())) for _, pr in made]
    assert means == pytest.approx([(per[0] + per[1]) / 2, per[2]])
    assert list(repeated_seeds(runs)) == [0]
    for seed in (0, 1):
        make_run(tmp_path / "runs", f"m-s{seed}", arch="modumorph", seed=seed, metrics=False)
    build_report([tmp_path / "runs"], tmp_path / "out")
    rows = _claim_rows(tmp_path / "out")
    assert rows[("ft", "rmomo", "test")]["model_seeds"] == "2"
    text = (tmp_path / "out" / "report.md").read_text()
    assert "ft, rmomo: 2 runs of seed 0" in text and "count as one seed in the claims" in text


def test_returns_table_counts_the_seeds_of_each_set(tmp_path):
    """A set that only some seeds evaluated says so: its own seed count in returns.csv, "[k of n seeds]" in the
    table."""
    make_run(tmp_path / "runs", "ft-rmomo-s0", seed=0, evals=("test", "variants"), metrics=False)
    make_run(tmp_path / "runs", "ft-rmomo-s1", seed=1, evals=("variants",), metrics=False)
    build_report([tmp_path / "runs"], tmp_path / "out")
    row = _csv(tmp_path / "out" / "returns.csv")[0]
    assert (row["seeds"], row["test_seeds"], row["variants_seeds"], row["train_seeds"]) == ("2", "1", "2", "0")
    line = next(ln for ln in (tmp_path / "out" / "report.md").read_text().splitlines() if ln.startswith("| ft | rmomo"))
    test_cell, variants_cell = line.split(" | ")[3:5]
    assert test_cell.endswith("[1 of 2 seeds]") and "seeds" not in variants_cell


def test_training_claim_reads_the_learning_curves_of_runs_that_reached_the_end(tmp_path):
    """Set "training": each seed's mean episode return over its last ~5% of iterations (metrics.csv), only runs at
    the furthest env steps of both models (a ModuMorph run cut short drops out), the verdict of claim_test; set
    "training_all": every run, up to the env steps the one cut short reached."""
    def final(d):                     # the last 2 of 40 iterations (ceil 5%), read from the file here
        rows = _csv(d / "metrics.csv")
        return np.mean([float(r["episode_return"]) for r in rows[-max(1, -(-len(rows) * 5 // 100)):]])
    runs = {(a, s): make_run(tmp_path / "runs", f"ft-{a}-s{s}", arch=a, seed=s, evals=())[0]
            for a in ("rmomo", "modumorph") for s in (0, 1)}
    make_run(tmp_path / "runs", "ft-modumorph-s2", arch="modumorph", seed=2, evals=(), iters=30)   # cut short
    build_report([tmp_path / "runs"], tmp_path / "out")
    r = _claim_rows(tmp_path / "out")[("ft", "rmomo", "training")]
    a = [final(runs[("rmomo", s)]) for s in (0, 1)]
    b = [final(runs[("modumorph", s)]) for s in (0, 1)]
    assert (r["model_seeds"], r["baseline_seeds"]) == ("2", "2")
    assert r["claim"] == "R-MoMo trains at least as well as ModuMorph"
    assert float(r["model_mean"]) == pytest.approx(np.mean(a))
    assert float(r["baseline_mean"]) == pytest.approx(np.mean(b))
    assert r["verdict"] == _verdict_ref(a, b, "level")[0]
    text = (tmp_path / "out" / "report.md").read_text()
    steps = float(_csv(runs[("rmomo", 0)] / "metrics.csv")[-1]["env_steps"])
    assert f"| ft | R-MoMo trains at least as well as ModuMorph | training to {steps / 1e6:.1f} M steps | 2/2 |" in text
    assert "R-MeMo" not in text                     # neither model ran: its claims are for another report
    # set "training_all": every run, each up to the env steps the one cut short reached (its last ~5% up to there)
    def up_to(d, steps):
        rows = [r for r in _csv(d / "metrics.csv") if float(r["env_steps"]) <= steps]
        return np.mean([float(r["episode_return"]) for r in rows[-max(1, -(-len(rows) * 5 // 100)):]])
    short = tmp_path / "runs" / "ft-modumorph-s2"
    cut = float(_csv(short / "metrics.csv")[-1]["env_steps"])
    r = _claim_rows(tmp_path / "out")[("ft", "rmomo", "training_all")]
    a = [up_to(runs[("rmomo", s)], cut) for s in (0, 1)]
    b = [up_to(d, cut) for d in (runs[("modumorph", 0)], runs[("modumorph", 1)], short)]
    assert a[0] != final(runs[("rmomo", 0)])
    assert (r["model_seeds"], r["baseline_seeds"]) == ("2", "3")
    assert float(r["model_mean"]) == pytest.approx(np.mean(a))
    assert float(r["baseline_mean"]) == pytest.approx(np.mean(b))
    assert r["verdict"] == _verdict_ref(a, b, "level")[0]
    assert f"| training_all to {cut / 1e6:.1f} M steps | 2/3 |" in text
    # the seeds' spread in training at 1/4 ... 4/4 of the env steps every run reached (the one cut short's end)
    spread = {(r["arch"], float(r["env_steps"])): r for r in _csv(tmp_path / "out" / "seed_spread.csv")}
    groups = {"rmomo": [runs[("rmomo", s)] for s in (0, 1)],
              "modumorph": [runs[("modumorph", 0)], runs[("modumorph", 1)], short]}
    assert len(spread) == 8
    for arch, dirs in groups.items():
        cells = []
        for f in (0.25, 0.5, 0.75, 1.0):
            v = np.array([up_to(d, f * cut) for d in dirs])
            row = spread[(arch, f * cut)]
            assert int(row["seeds"]) == len(dirs) and float(row["mean_train_return"]) == pytest.approx(v.mean())
            assert float(row["sd_over_mean"]) == pytest.approx(v.std(ddof=1) / abs(v.mean()))
            cells.append(f"{v.std(ddof=1) / abs(v.mean()):.2f}")
        assert f"| ft | {arch} | {len(dirs)} | {cut:,.0f} | " + " | ".join(cells) + " |" in text, cells


def test_pooled_returns_take_only_the_tasks_every_architecture_has(tmp_path):
    """Normalised returns pooled across tasks: per set, over the tasks that every architecture evaluated on that set
    has, so that one model's extra (harder) task does not sink its pooled mean; the task left out is named under
    Missing. Both tasks pooled where both models have them."""
    _, r_ft = make_run(tmp_path / "runs", "ft-rmomo-s0", "ft", "rmomo", evals=("test", "variants"), metrics=False)
    _, r_in = make_run(tmp_path / "runs", "incline-rmomo-s0", "incline", "rmomo", evals=("test", "variants"),
                       metrics=False, returns=(0, 300))
    _, m_ft = make_run(tmp_path / "runs", "ft-modumorph-s0", "ft", "modumorph", evals=("test", "variants"),
                       metrics=False)
    _, m_in = make_run(tmp_path / "runs", "incline-modumorph-s0", "incline", "modumorph", evals=("test",),
                       metrics=False)

    def norm(per_robot, task):
        lo, hi = TASK_RANGES[task]
        return [(v - lo) / (hi - lo) for v in per_robot.values()]

    md = build_report([tmp_path / "runs"], tmp_path / "out").read_text()
    rows = {r["arch"]: r for r in _csv(tmp_path / "out" / "returns_pooled.csv")}
    # test: both models have both tasks -> pooled over ft and incline
    for arch, (ft, inc) in {"rmomo": (r_ft, r_in), "modumorph": (m_ft, m_in)}.items():
        v = norm(ft["test"], "ft") + norm(inc["test"], "incline")
        assert float(rows[arch]["test_normalised"]) == pytest.approx(np.mean(v), rel=1e-9)
        assert int(rows[arch]["test_robots"]) == len(v)
    # variants: only R-MoMo has incline -> ft alone, for both
    for arch, ft in {"rmomo": r_ft, "modumorph": m_ft}.items():
        v = norm(ft["variants"], "ft")
        assert float(rows[arch]["variants_normalised"]) == pytest.approx(np.mean(v), rel=1e-9)
    missing = md[md.index("## Missing"):]
    assert "incline on variants (results of rmomo only)" in missing
    assert "variants: ft" in md and "test: ft, incline" in md


def test_eval_claims_compare_evaluations_at_the_same_env_steps(tmp_path):
    """An eval-set claim compares policies at one point of training: where a model's seeds were evaluated at different
    env steps, those at the steps both models have most seeds at; the others are named under Missing, and so is the
    mixing in the returns table. Two models evaluated at no common steps leave the claim untested."""
    at18, at20 = 18_022_400, 20_070_400
    runs = {(a, s): make_run(tmp_path / "runs", f"incline-{a}-s{s}", "incline", a, s, evals=("test",), metrics=False,
                             eval_steps=steps)[1]
            for a, s, steps in (("rmomo", 0, at20), ("rmomo", 1, at18), ("rmomo", 2, at18),
                                ("modumorph", 0, at18), ("modumorph", 1, at18))}
    md = build_report([tmp_path / "runs"], tmp_path / "out").read_text()
    r = _claim_rows(tmp_path / "out")[("incline", "rmomo", "test")]
    a = _seed_means([runs[("rmomo", s)] for s in (1, 2)], "test")
    b = _seed_means([runs[("modumorph", s)] for s in (0, 1)], "test")
    assert (r["model_seeds"], r["baseline_seeds"], float(r["env_steps"])) == ("2", "2", at18)
    assert float(r["model_mean"]) == pytest.approx(np.mean(a)) and float(r["baseline_mean"]) == pytest.approx(
        np.mean(b))
    assert "| incline | R-MoMo beats ModuMorph zero-shot on unseen topologies | test at 18.0 M steps | 2/2 |" in md
    missing = md[md.index("## Missing"):]
    assert "left out, evaluated at other steps: " in missing and "incline-rmomo-s0 (20.1M)" in missing
    assert "incline, rmomo: test evaluated at different env steps (18.0M: 2 run(s), 20.1M: 1 run(s))" in missing
    # the per-robot differences take the same evaluations as the claim
    diff = {row["robot"]: row for row in _csv(tmp_path / "out" / "robot_diff_incline.csv")}
    for robot, row in diff.items():
        assert float(row["rmomo_return"]) == pytest.approx(np.mean([runs[("rmomo", s)]["test"][robot] for s in (1, 2)]))
        assert float(row["modumorph_return"]) == pytest.approx(
            np.mean([runs[("modumorph", s)]["test"][robot] for s in (0, 1)]))
    assert len(diff) == len(TEST)
    # no steps in common: untested, and why
    for s in (0, 1):
        make_run(tmp_path / "apart", f"ft-rmomo-s{s}", arch="rmomo", seed=s, evals=("test",), metrics=False,
                 eval_steps=at20)
        make_run(tmp_path / "apart", f"ft-modumorph-s{s}", arch="modumorph", seed=s, evals=("test",), metrics=False,
                 eval_steps=at18)
    md = build_report([tmp_path / "apart"], tmp_path / "out2").read_text()
    assert not (tmp_path / "out2" / "claims.csv").exists()          # no claim could be tested
    assert ("R-MoMo beats ModuMorph zero-shot on unseen topologies (test: evaluated at different env steps, rmomo "
            "20.1M, modumorph 18.0M)") in md


def test_every_name_of_a_figure_gets_its_own_colour():
    """An architecture keeps its colour in every figure; an A/B study's arms (names beyond nets.ARCHS) take colours no
    name of the figure has (session 27's report drew MetaMorph and an R-MeMo arm in one blue)."""
    from mjx_morph.nets import ARCHS
    arms = [f"rmemo, scale_context={v}" for v in ("null", "true")] + [f"rmomo, arm{i}" for i in range(5)]
    colors = plots.arch_colors(["metamorph", "modumorph"] + arms)
    assert len(set(colors.values())) == len(colors)
    alone = plots.arch_colors(["metamorph"])
    assert colors["metamorph"] == alone["metamorph"] == plots.arch_colors(list(ARCHS))["metamorph"]
    assert plots.arch_colors(list(reversed(arms))) == plots.arch_colors(arms)     # arms' colours: by sorted name


def test_the_physics_each_run_trained_on_is_shown_and_a_mix_named(tmp_path):
    """The runs table names each run's model digest (devices.yaml); claims over runs of more than one physics (or of
    runs with and without one recorded) say so under Missing, per architecture, and a table splits each group's
    seeds by physics."""
    a, b = "a" * 16, "b" * 16
    recorded = {("rmemo", 0): None, ("rmemo", 1): [a], ("metamorph", 0): [a], ("metamorph", 1): [a, b]}
    per = {}
    for (arch, seed), digests in recorded.items():
        d, per[arch, seed] = make_run(tmp_path / "runs", f"ft-{arch}-s{seed}", arch=arch, seed=seed, metrics=False)
        if digests:
            (d / "devices.yaml").write_text(yaml.safe_dump(
                [{"start_iteration": 10 * i, "device_kind": "cpu", "model_digest": x} for i, x in enumerate(digests)]))
    md = build_report([tmp_path / "runs"], tmp_path / "out").read_text()
    rows = {(r["arch"], r["seed"]): r["physics"] for r in _csv(tmp_path / "out" / "runs.csv")}
    assert rows == {("rmemo", "0"): "", ("rmemo", "1"): a, ("metamorph", "0"): a, ("metamorph", "1"): f"{a} {b}"}
    assert "| aaaaaaaa → bbbbbbbb |" in md and "| – |" in md
    assert ("ft: the claims compare runs of more than one physics (model digest; runs per physics): metamorph: 1 "
            "aaaaaaaa, 1 aaaaaaaa → bbbbbbbb; rmemo: 1 not recorded, 1 aaaaaaaa") in md
    # each group's seeds split by physics, described (one run per physics here: its own returns)
    split = {(r["arch"], r["physics"]): r for r in _csv(tmp_path / "out" / "seeds_by_physics.csv")}
    assert set(split) == {("rmemo", ""), ("rmemo", a), ("metamorph", a), ("metamorph", f"{a} {b}")}
    for (arch, seed), digests in recorded.items():
        r = split[arch, " ".join(digests or [])]
        assert r["seeds"] == str(seed) and r["n_test"] == "1" and r["n_train"] == "0"
        assert float(r["test_return"]) == pytest.approx(np.mean(list(per[arch, seed]["test"].values())), rel=1e-5)
        assert float(r["variants_return"]) == pytest.approx(np.mean(list(per[arch, seed]["variants"].values())),
                                                            rel=1e-5)
    assert "| ft | rmemo | not recorded | 0 | – |" in md
    for arch, seed in recorded:                          # one physics everywhere: nothing to say
        (tmp_path / "runs" / f"ft-{arch}-s{seed}" / "devices.yaml").write_text(yaml.safe_dump([{"model_digest": a}]))
    assert "more than one physics" not in build_report([tmp_path / "runs"], tmp_path / "out2").read_text()
    assert not (tmp_path / "out2" / "seeds_by_physics.csv").exists()


def test_a_physics_computed_afterwards_is_marked_and_pooled_with_the_recorded_one(tmp_path):
    """A run that recorded no digest but has physics.yaml (experiments.digest record=...) shows its physics marked
    as computed (runs table `aaaaaaaa*`, runs.csv's physics_computed) and joins the seeds of the recorded digest in
    the seeds-by-physics table (its seed starred); a run's own record outranks a physics.yaml."""
    a, b = "a" * 16, "b" * 16
    dirs = {}
    for arch, seed in (("rmemo", 0), ("rmemo", 1), ("rmemo", 2), ("metamorph", 0)):
        dirs[arch, seed], _ = make_run(tmp_path / "runs", f"ft-{arch}-s{seed}", arch=arch, seed=seed, metrics=False)
    for key in (("rmemo", 1), ("metamorph", 0)):
        (dirs[key] / "devices.yaml").write_text(yaml.safe_dump([{"model_digest": a}]))
    (dirs["rmemo", 2] / "physics.yaml").write_text(yaml.safe_dump({"model_digest": a, "code": "c0ffee", "why": "w"}))
    (dirs["metamorph", 0] / "physics.yaml").write_text(yaml.safe_dump({"model_digest": b}))   # its record stands
    md = build_report([tmp_path / "runs"], tmp_path / "out").read_text()
    rows = {(r["arch"], r["seed"]): (r["physics"], r["physics_computed"]) for r in _csv(tmp_path / "out" / "runs.csv")}
    assert rows == {("rmemo", "0"): ("", ""), ("rmemo", "1"): (a, ""), ("rmemo", "2"): ("", a),
                    ("metamorph", "0"): (a, "")}
    assert "| aaaaaaaa* |" in md
    split = {(r["arch"], r["physics"]): r["seeds"] for r in _csv(tmp_path / "out" / "seeds_by_physics.csv")}
    assert split == {("rmemo", ""): "0", ("rmemo", a): "1, 2*", ("metamorph", a): "0"}
    assert "rmemo: 1 not recorded, 2 aaaaaaaa" in md
