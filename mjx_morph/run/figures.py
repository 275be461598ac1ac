"""The figure a training run draws for itself: its learning curve (matplotlib, Agg backend)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def learning_curve(rows: Sequence[Mapping[str, float]], out: str | Path, title: str = "") -> Path:
    """Mean train episode return (and length) against env steps, from metric rows of one run."""
    rows = [r for r in rows if np.isfinite(r.get("episode_return", np.nan))]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    if rows:
        steps = np.array([r["env_steps"] for r in rows])
        for ax, key, label in ((axes[0], "episode_return", "mean episode return"),
                               (axes[1], "episode_length", "mean episode length")):
            y = np.array([r.get(key, np.nan) for r in rows])
            ax.plot(steps, y, color="tab:blue", alpha=0.35, lw=1)
            if len(y) >= 5:  # a light moving average over ~5% of the run
                k = max(1, len(y) // 20)
                ax.plot(steps[k - 1:], np.convolve(y, np.ones(k) / k, mode="valid"), color="tab:blue", lw=2)
            ax.set_xlabel("env steps")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
    else:
        axes[0].text(0.5, 0.5, "no finished episodes yet", ha="center", va="center", transform=axes[0].transAxes)
    fig.suptitle(title)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
