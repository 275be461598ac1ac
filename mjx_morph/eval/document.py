"""The report's markdown document and its tables: figures under section headings, tables written as CSV (full
precision) and shown as markdown (formatted cells), and a list of what is missing.

    doc = Document(out_dir)
    doc.section("Returns")
    doc.figure(png_path, "caption")                              # under the current section
    doc.table("Returns (main runs)", "returns", header, rows)    # out_dir/returns.csv and a markdown table
    doc.missing.append("what could not be drawn, and why")
    doc.write("title", runs=12)                                  # out_dir/report.md

report.md: the title, `## Runs` with the lead table (`table(..., lead=True)`), one `## <section>` per section with
figures (in the order the sections were started), `## Tables` with every other table, `## Missing`.
"""
from __future__ import annotations

import csv
import datetime
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np


# ---- cells --------------------------------------------------------------------------------------------------------
def fmt(x, nd: int = 1) -> str:
    """A number with `nd` decimals (an integer as is); "–" for None or a non-finite float."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return f"{x:.{nd}f}"


def pm(m, ci, nd: int = 1) -> str:
    """"m ± ci" with `nd` decimals ("m" without a finite ci, "–" without a finite m)."""
    if m is None or not math.isfinite(m):
        return "–"
    return f"{m:.{nd}f} ± {ci:.{nd}f}" if ci is not None and math.isfinite(ci) else f"{m:.{nd}f}"


def fmt_steps(x: float) -> str:
    """Env steps: "12.3M" from a million on."""
    if not math.isfinite(x):
        return "–"
    return f"{x / 1e6:.1f}M" if x >= 1e6 else f"{x:,.0f}"


def csv_value(v):
    """A CSV cell: floats in full precision (repr), empty for None and non-finite floats."""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return "" if v is None else v


# ---- tables -------------------------------------------------------------------------------------------------------
def write_csv(path: Path, header: Sequence, rows: Sequence[Sequence]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            w.writerow([csv_value(v) for v in r])


def md_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A markdown table; floats with 3 decimals, "|" escaped."""
    def cell(v):
        if isinstance(v, float):
            v = fmt(v, 3)
        return str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(map(cell, header)) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


@dataclass
class Table:
    title: str
    header: list[str]          # markdown header
    rows: list[list]           # markdown rows
    csv_name: str
    note: str


# ---- the document -------------------------------------------------------------------------------------------------
class Document:
    def __init__(self, out: Path):
        self.out = out
        self.sections: list[str] = []                        # headings, in the order started
        self.figures: list[tuple[str, str, str]] = []         # (section heading, file, caption)
        self.lead: Table | None = None                       # shown under "## Runs"
        self.tables: list[Table] = []
        self.missing: list[str] = []

    def section(self, heading: str) -> None:
        """Start a section: the figures that follow go under `## heading`."""
        self.sections.append(heading)

    def figure(self, path: Path, caption: str) -> None:
        self.figures.append((self.sections[-1], path.name, caption))

    def table(self, title: str, name: str, header: Sequence[str], rows: Sequence[Sequence], md_header=None,
              md_rows=None, note: str = "", lead: bool = False) -> None:
        """Write `rows` to out/<name>.csv under `header`; show `md_rows` (default: rows) under `md_header` (default:
        header) in report.md, with `note` below it."""
        write_csv(self.out / f"{name}.csv", header, rows)
        table = Table(title, list(md_header or header), [list(r) for r in (md_rows if md_rows is not None else rows)],
                      f"{name}.csv", note)
        if lead:
            self.lead = table
        else:
            self.tables.append(table)

    def write(self, title: str, runs: int) -> Path:
        """Write out/report.md (`runs`: the number of runs read, for its first line); returns its path."""
        lines = [f"# {title}", "", f"Generated {datetime.datetime.now():%Y-%m-%d %H:%M} from {runs} run(s).", ""]
        lines += ["## Runs", ""]
        if self.lead:
            lines += [md_table(self.lead.header, self.lead.rows), "",
                      f"*{self.lead.note}* ([{self.lead.csv_name}]({self.lead.csv_name}))", ""]
        for sec in self.sections:
            figs = [f for f in self.figures if f[0] == sec]
            if not figs:
                continue
            lines += [f"## {sec}", ""]
            for _, name, cap in figs:
                lines += [f"![{cap}]({name})", "", f"*{cap}*", ""]
        lines += ["## Tables", ""]
        for tb in self.tables:
            lines += [f"### {tb.title}", "", md_table(tb.header, tb.rows), ""]
            lines += [(f"*{tb.note}* " if tb.note else "") + f"([{tb.csv_name}]({tb.csv_name}))", ""]
        lines += ["## Missing", ""]
        lines += [f"- {m}" for m in self.missing] or ["Nothing: every figure could be drawn."]
        lines.append("")
        path = self.out / "report.md"
        path.write_text("\n".join(lines))
        return path
