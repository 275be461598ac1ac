"""Figures, tables and a markdown report from finished runs: `python -m experiments.report runs=[...] out=<dir>`.

    python -m experiments.report runs=[runs/ft-rmomo-s0,runs/ft-modumorph-s0] out=reports/ft
    python -m experiments.report runs=[runs/studies/train_size] out=reports/size      # a folder of run dirs
    python -m experiments.report runs=[runs] out=reports/all 'compare=[rmomo,metamorph]'
    python -m experiments.report runs=[results/paper_s26,results/paper_s28] out=reports/ft looks=2   # 2nd look
    python -m experiments.report runs=[...] out=reports/all 'looks={ft/rmomo:5,rmemo:3}'   # looks per claim model
    python -m experiments.report manifest=results/claims.yaml out=reports/claims    # the runs and looks as data

Writes <out>/report.md with learning curves, zero-shot returns (train/test/variants), per-robot differences,
whether the paper's claims are reproduced (claims.csv, claims.png), the seeds' spread in training as it goes on
(seed_spread.csv), reward per timestep, training-set-size and
single-context-feature figures (PNG) and tables (also as CSV); what could not be drawn is listed under "Missing".
`looks=k`: the claims' comparisons were looked at k times as seeds came in (this report the k-th); their CIs are then
at 1 - 0.05 / k and a claim holds at p < 0.025 / k (Bonferroni). Where the models' comparisons were looked at
different numbers of times, `looks={<model>: k, <task>/<model>: k, ...}` gives each its own (unlisted: one look;
a model is the claim's, rmomo or rmemo).
`manifest=<yaml>`: the runs and the looks from a file instead (`mjx_morph.eval.runs.read_manifest`;
`results/claims.yaml` holds those of docs/results.md's claims table, with the runs that wait for the next look and
those left out).
See mjx_morph.eval.report.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any, Optional

from omegaconf import MISSING

from mjx_morph.eval.report import build_report
from mjx_morph.eval.runs import find_run_dirs, read_manifest
from mjx_morph.run import register

from . import cli


@dataclasses.dataclass
class ReportConfig:
    runs: Any = None                    # run directories (with config.yaml) or folders holding run directories
    out: str = MISSING                  # output folder: report.md, figures (PNG) and tables (CSV)
    compare: Any = dataclasses.field(default_factory=lambda: ["rmomo", "modumorph"])
                                        # per-robot difference a - b; a task lacking one: its first two archs
    title: str = "mjx_morph report"
    looks: Any = None                   # how many times the claims' comparisons were looked at as seeds came in:
                                        # their CIs at 1 - 0.05 / looks, reproduced at p < 0.025 / looks (Bonferroni);
                                        # or per claim model, {rmomo: 5, incline/rmemo: 2} (unlisted; None: 1)
    manifest: Optional[str] = None      # a YAML of the runs and looks instead of runs= and looks= (read_manifest)


register("report_schema", ReportConfig)


def report(c: ReportConfig) -> None:
    compare = c.compare if isinstance(c.compare, (list, tuple)) else [c.compare]
    looks = 1 if c.looks is None else c.looks
    if c.manifest is not None:
        if c.runs is not None or c.looks is not None:
            raise ValueError(f"manifest={c.manifest}: it gives the runs and the looks; drop runs= and looks=")
        m = read_manifest(c.manifest)
        if not m.runs:
            raise ValueError(f"{m.path}: runs: nothing pooled yet ({len(m.pending)} pending for the first look); "
                             f"report them with runs=[...] or move them into runs at the look")
        dirs, looks = m.runs, m.looks
        print(f"[mjx_morph] {m.path}: {len(m.runs)} runs at looks {looks}; {len(m.pending)} pending for the next look "
              f"and {len(m.excluded)} excluded, neither pooled", flush=True)
    else:
        if c.runs is None:
            raise ValueError("runs=[...] or manifest=<yaml>: which runs to report")
        dirs = find_run_dirs(str(r) for r in (c.runs if isinstance(c.runs, (list, tuple)) else [c.runs]))
    if not dirs:
        raise ValueError("no run directories given")
    print(f"[mjx_morph] building the report of {len(dirs)} runs into {c.out} (figures, tables, report.md)...",
          flush=True)
    path = build_report(dirs, c.out, compare=[str(x) for x in compare], title=str(c.title), looks=looks)
    print(f"[mjx_morph] report: {path} ({len(dirs)} runs)")


def main(argv=None) -> int:
    return cli.main(report, "report_schema", ReportConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
