"""Figures people would rather look at than read (matplotlib, Agg backend)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


# ---- report figures (mjx_morph.eval.report) ------------------------------------------------------------------------
def arch_colors(archs: Sequence[str]) -> dict[str, tuple]:
    """A fixed colour per architecture (its place in mjx_morph.nets.ARCHS), the same in every figure; other names (an
    A/B study's arms, "rmemo, scale_context=true") take, in sorted order, the colours no name of this figure has."""
    try:
        from ..nets import ARCHS
    except Exception:  # noqa: BLE001 - colours only
        ARCHS = ()
    palette = list(plt.get_cmap("tab10").colors) + list(plt.get_cmap("Dark2").colors)
    out = {a: palette[ARCHS.index(a)] for a in archs if a in ARCHS}
    used = set(out.values())
    free = [c for c in palette[len(ARCHS):] + palette[:len(ARCHS)] if c not in used]
    for i, a in enumerate(sorted(a for a in archs if a not in out)):
        out[a] = free[i % len(free)]
    return out


def _legend(ax, fontsize: int) -> None:
    """The axes' legend where it fits: inside ("best") for a few short names, else outside on the right, where it
    covers no curve (an A/B study's long arm names)."""
    labels = ax.get_legend_handles_labels()[1]
    if len(labels) > 4 or max((len(x) for x in labels), default=0) > 32:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=fontsize, borderaxespad=0)
    else:
        ax.legend(loc="best", fontsize=fontsize)


def _save(fig, out: str | Path, dpi: int = 110) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def _millions(ax) -> None:
    from matplotlib.ticker import FuncFormatter
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v / 1e6:g}M"))


def mean_curves(curves: Mapping[str, tuple], out: str | Path, title: str = "", xlabel: str = "env steps",
                ylabel: str = "mean episode return", labels: Mapping[str, str] | None = None,
                members: Mapping[str, Sequence[tuple]] | None = None,
                tails: Mapping[str, tuple] | None = None) -> Path:
    """One line per key from `curves[key] = (x, mean, lo, hi)`, shaded between lo and hi where finite (pass
    lo = hi = None for no band); `members[key]`: curves (x, y) drawn thin in the key's colour (e.g. each seed);
    `tails[key] = (x, mean, lo, hi, label)`: a dashed continuation in the key's colour, with its own legend entry."""
    colors = arch_colors(list(curves))
    fig, ax = plt.subplots(figsize=(7, 4.2))

    def band(x, lo, hi, color, alpha):
        if lo is not None and hi is not None:
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            ok = np.isfinite(lo) & np.isfinite(hi)
            if ok.any():
                ax.fill_between(x, np.where(ok, lo, np.nan), np.where(ok, hi, np.nan), color=color, alpha=alpha, lw=0)

    for key, (x, mean, lo, hi) in curves.items():
        for mx, my in (members or {}).get(key, ()):
            ax.plot(mx, my, color=colors[key], lw=0.8, alpha=0.6)
        x, mean = np.asarray(x, float), np.asarray(mean, float)
        ax.plot(x, mean, color=colors[key], lw=2, label=(labels or {}).get(key, key))
        band(x, lo, hi, colors[key], 0.2)
        if key in (tails or {}):
            tx, tm, tlo, thi, tlabel = tails[key]
            tx = np.asarray(tx, float)
            ax.plot(tx, np.asarray(tm, float), color=colors[key], lw=2, ls="--", label=tlabel)
            band(tx, tlo, thi, colors[key], 0.12)
    if max((np.nanmax(np.asarray(c[0], float)) for c in curves.values() if len(c[0])), default=0) >= 1e6:
        _millions(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    _legend(ax, 9)
    return _save(fig, out)


def bar_panels(panels: Sequence[Mapping], out: str | Path, title: str = "") -> Path:
    """Grouped bar charts side by side. Each panel: `groups` (x labels), `series` {name: (means, ci95s)} with one
    value per group (nan: no bar), `ylabel`, optional `title` and `refs` {name: value} (dashed horizontal lines
    in the series' colour, labelled `ref_label.format(name)`)."""
    names = list(dict.fromkeys(n for p in panels for n in p["series"]))
    colors = arch_colors(names)
    widths = [max(3.5, 0.3 * len(p["groups"]) * max(1, len(p["series"])) + 1.5) for p in panels]
    fig, axes = plt.subplots(1, len(panels), figsize=(min(sum(widths), 24), 4.4),
                             gridspec_kw={"width_ratios": widths}, squeeze=False, layout="constrained")
    for ax, p in zip(axes[0], panels):
        groups, series = list(p["groups"]), p["series"]
        k = max(1, len(series))
        w = 0.8 / k
        x = np.arange(len(groups))
        for j, (name, (means, cis)) in enumerate(series.items()):
            means = np.asarray(means, float)
            cis = np.nan_to_num(np.asarray(cis, float), nan=0.0)
            sel = np.isfinite(means)                       # no bar where there is no value
            ax.bar((x + (j - (k - 1) / 2) * w)[sel], means[sel], w, yerr=cis[sel], capsize=2,
                   color=colors[name], label=name, error_kw={"lw": 1, "ecolor": "0.25"})
        for name, v in (p.get("refs") or {}).items():
            if v is not None and np.isfinite(v):
                ax.axhline(v, color=colors.get(name, "0.3"), ls="--", lw=1.3,
                           label=p.get("ref_label", "{}").format(name))
        ax.set_xticks(x)
        long = max((len(g) for g in groups), default=0) > 9
        ax.set_xticklabels(groups, rotation=30 if long else 0, ha="right" if long else "center")
        ax.set_ylabel(p.get("ylabel", ""))
        ax.set_title(p.get("title", ""), fontsize=10)
        ax.axhline(0, color="0.3", lw=0.6)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, out)


def robot_difference(names: Sequence[str], a_vals: Sequence[float], b_vals: Sequence[float], a: str, b: str,
                     out: str | Path, title: str = "", unit: str = "test return") -> Path:
    """Left: per-robot a - b as horizontal bars, in the given order (top first); right: both per-robot values in
    the same order. Robot names are shown up to 120 robots."""
    a_vals, b_vals = np.asarray(a_vals, float), np.asarray(b_vals, float)
    d = a_vals - b_vals
    n = len(names)
    colors = arch_colors([a, b])
    show = n <= 120
    height = (max(4.0, 0.15 * n + 1.6) if show else 9.0)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, height), sharey=True, layout="constrained")
    y = np.arange(n)[::-1]
    ax1.barh(y, d, color=[colors[a] if v >= 0 else colors[b] for v in d], height=0.8)
    ax1.axvline(0, color="0.2", lw=0.8)
    better = int((d > 0).sum())
    ax1.set_title(f"{a} − {b}: mean {d.mean():.3g}; {a} better on {better}/{n}" if n else f"{a} − {b}",
                  fontsize=10)
    ax1.set_xlabel(f"difference in {unit}")
    ax2.hlines(y, np.minimum(a_vals, b_vals), np.maximum(a_vals, b_vals), color="0.7", lw=1)
    ax2.scatter(a_vals, y, color=colors[a], s=14, label=a, zorder=3)
    ax2.scatter(b_vals, y, color=colors[b], s=14, marker="s", label=b, zorder=3)
    ax2.set_xlabel(unit)
    ax2.set_title("per-robot values (same order)", fontsize=10)
    ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, borderaxespad=0)
    for ax in (ax1, ax2):
        ax.grid(axis="x", alpha=0.3)
        ax.set_ylim(-0.7, n - 0.3)
    if show:
        ax1.set_yticks(y)
        ax1.set_yticklabels(names, fontsize=7 if n > 40 else 8)
    else:
        ax1.set_yticks([])
        ax1.set_ylabel(f"{n} robots, sorted by difference")
    if title:
        fig.suptitle(title)
    return _save(fig, out)


def reward_per_step(series: Mapping[str, tuple], out: str | Path, zero_steps: int | None = None,
                    alive: Mapping[str, Sequence[float]] | None = None, title: str = "") -> Path:
    """`series[name] = (reward trace, zero-state trace or None)`: solid line per name, the zero-state one dashed
    in the same colour; a vertical marker at `zero_steps`. `alive` (optional): fraction of episodes still running,
    in a second panel."""
    colors = arch_colors(list(series))
    rows = 2 if alive else 1
    fig, axes = plt.subplots(rows, 1, figsize=(8, 4.2 if rows == 1 else 6.4), sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.3][:rows]})
    ax = axes[0][0]
    for name, (trace, zero) in series.items():
        ax.plot(np.arange(len(trace)), trace, color=colors[name], lw=1.4, label=name)
        if zero is not None:
            ax.plot(np.arange(len(zero)), zero, color=colors[name], lw=1.4, ls="--",
                    label=f"{name}, state held at 0 for the first {zero_steps} steps")
    longest = max((len(tr) for tr, _ in series.values()), default=0)
    if zero_steps and zero_steps < longest and any(z is not None for _, z in series.values()):
        for a in axes[:, 0]:
            a.axvline(zero_steps, color="0.3", ls=":", lw=1)
    ax.set_ylabel("mean reward per step")
    ax.grid(alpha=0.3)
    ax.set_title(title)
    if alive:
        ax2 = axes[1][0]
        for name, tr in alive.items():
            ax2.plot(np.arange(len(tr)), tr, color=colors.get(name, "0.3"), lw=1.2)
        ax2.set_ylabel("episodes running")
        ax2.set_ylim(0, 1.05)
        ax2.grid(alpha=0.3)
    axes[-1][0].set_xlabel("time step")
    fig.tight_layout()
    _legend(ax, 8)                  # after the layout, so that a legend outside the axes does not squeeze them
    return _save(fig, out)


def errorbar_lines(series: Mapping[str, tuple], out: str | Path, title: str = "", xlabel: str = "",
                   ylabel: str = "") -> Path:
    """`series[name] = (x, mean, ci95)`: one line with 95% CI error bars per name."""
    colors = arch_colors(list(series))
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    xs = set()
    for j, (name, (x, m, ci)) in enumerate(series.items()):
        x = np.asarray(x, float)
        xs.update(x.tolist())
        ax.errorbar(x, m, yerr=np.nan_to_num(np.asarray(ci, float), nan=0.0), color=colors[name], marker="o",
                    capsize=3, lw=1.6, label=name)
    ax.set_xticks(sorted(xs))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _legend(ax, 9)
    return _save(fig, out)


#: the colour of each claim verdict (mjx_morph.eval.stats): reproduced, not reproduced, and every inconclusive kind
VERDICT_COLORS = {"reproduced": "tab:green", "not reproduced": "tab:red"}


def intervals(rows: Sequence[Mapping], out: str | Path, title: str = "", xlabel: str = "",
              refs: Mapping[float, str] | None = None) -> Path:
    """A forest plot: one row per `rows[i]` (top to bottom) with keys label, value, lo, hi (an interval; nan: the point
    alone), verdict (its colour, VERDICT_COLORS, grey otherwise) and note (written right of the axes); `refs[x] =
    label`: vertical reference lines, solid at 0 and dashed elsewhere, named in the legend where labelled."""
    n = len(rows)
    fig, ax = plt.subplots(figsize=(10.0, 1.2 + 0.36 * max(n, 1)))
    y = np.arange(n)[::-1]
    for yi, r in zip(y, rows):
        c = VERDICT_COLORS.get(r["verdict"], "0.45")
        lo, hi = float(r["lo"]), float(r["hi"])
        if np.isfinite(lo) and np.isfinite(hi):
            ax.plot([lo, hi], [yi, yi], color=c, lw=2.2, solid_capstyle="butt")
        ax.plot([r["value"]], [yi], "o", color=c, ms=6)
        ax.annotate(r.get("note", ""), xy=(1.01, yi), xycoords=("axes fraction", "data"), va="center", fontsize=8)
    handles = []
    for x, label in (refs or {}).items():
        line = ax.axvline(x, color="0.2" if x == 0 else "0.5", lw=1.0, ls="-" if x == 0 else "--", label=label)
        if label:
            handles.append(line)
    for v, c in (*VERDICT_COLORS.items(), ("inconclusive", "0.45")):
        if any(VERDICT_COLORS.get(r["verdict"], "0.45") == c for r in rows):
            handles.append(plt.Line2D([], [], color=c, marker="o", lw=2.2, label=v))
    ax.set_yticks(y)
    ax.set_yticklabels([r["label"] for r in rows], fontsize=8)
    ax.set_ylim(-0.7, n - 0.3)
    ax.set_xlabel(xlabel)
    ax.set_title(title)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    if handles:
        fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(handles), fontsize=8,
                   frameon=False)
    return _save(fig, out)
