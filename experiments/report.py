"""Figures, tables and a markdown report from finished runs: `python -m experiments.report runs=[...] out=<dir>`.

    python -m experiments.report runs=[runs/ft-rmomo-s0,runs/ft-modumorph-s0] out=reports/ft
    python -m experiments.report runs=[runs/studies/train_size] out=reports/size      # a folder of run dirs
    python -m experiments.report runs=[runs] out=reports/all 'compare=[rmomo,metamorph]'
    python -m experiments.report runs=[results/paper_s26,results/paper_s28] out=reports/ft looks=2   # 2nd look
    python -m experiments.report runs=[...] out=reports/all 'looks={ft/rmomo:5,rmemo:3}'   # looks per claim model

Writes <out>/report.md with learning curves, zero-shot returns (train/test/variants), per-robot differences,
whether the paper's claims are reproduced (claims.csv, claims.png), the seeds' spread in training as it goes on
(seed_spread.csv), reward per timestep, training-set-size and
single-context-feature figures (PNG) and tables (also as CSV); what could not be drawn is listed under "Missing".
`looks=k`: the claims' comparisons were looked at k times as seeds came in (this report the k-th); their CIs are then
at 1 - 0.05 / k and a claim holds at p < 0.025 / k (Bonferroni). Where the models' comparisons were looked at
different numbers of times, `looks={<model>: k, <task>/<model>: k, ...}` gives each its own (unlisted: one look;
a model is the claim's, rmomo or rmemo).
See mjx_morph.eval.report.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any

from omegaconf import MISSING

from mjx_morph.eval.report import build_report
from mjx_morph.eval.runs import find_run_dirs
from mjx_morph.run import register

from . import cli


@dataclasses.dataclass
class ReportConfig:
    runs: Any = MISSING                 # run directories (with config.yaml) or folders holding run directories
    out: str = MISSING                  # output folder: report.md, figures (PNG) and tables (CSV)
    compare: Any = dataclasses.field(default_factory=lambda: ["rmomo", "modumorph"])
                                        # per-robot difference a - b; a task lacking one: its first two archs
    title: str = "mjx_morph report"
    looks: Any = 1                      # how many times the claims' comparisons were looked at as seeds came in:
                                        # their CIs at 1 - 0.05 / looks, reproduced at p < 0.025 / looks (Bonferroni);
                                        # or per claim model, {rmomo: 5, incline/rmemo: 2} (unlisted: 1)


register("report_schema", ReportConfig)


def report(c: ReportConfig) -> None:
    runs = c.runs if isinstance(c.runs, (list, tuple)) else [c.runs]
    compare = c.compare if isinstance(c.compare, (list, tuple)) else [c.compare]
    dirs = find_run_dirs(str(r) for r in runs)
    if not dirs:
        raise ValueError("no run directories given")
    print(f"[mjx_morph] building the report of {len(dirs)} runs into {c.out} (figures, tables, report.md)...",
          flush=True)
    path = build_report(dirs, c.out, compare=[str(x) for x in compare], title=str(c.title), looks=c.looks)
    print(f"[mjx_morph] report: {path} ({len(dirs)} runs)")


def main(argv=None) -> int:
    return cli.main(report, "report_schema", ReportConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
