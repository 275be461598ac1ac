"""One directory per run: resolved config, metrics (CSV + TensorBoard), Orbax checkpoints, figures.

    <run_dir>/config.yaml        the resolved config of the run (written once; a resume must match it)
    <run_dir>/metrics.csv        one row per iteration
    <run_dir>/tb/                TensorBoard event files
    <run_dir>/checkpoints/<it>/  Orbax checkpoints of the whole train state
    <run_dir>/learning_curve.png

Resuming: rerunning with the same run directory restores the newest checkpoint. Before anything is touched, the
config is compared with the saved one on the keys that shape the train state (architecture, task, robots, batch
geometry, model sizes, seed): a mismatch or an unreadable checkpoint raises `RunDirError` naming the file and
what differs, and the directory is left as it was. Metric rows of iterations after the restored checkpoint (an
interrupted run's last, unsaved iterations) are moved to `metrics.csv.orphaned` rather than deleted, and are
logged again by the resumed run.
"""
from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path
from typing import Any, Mapping

import jax
import numpy as np
import orbax.checkpoint as ocp
import yaml
from tensorboardX import SummaryWriter


class RunDirError(RuntimeError):
    pass


def _flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


class RunDir:
    def __init__(self, path: str | Path, config: Mapping, identity: tuple[str, ...]):
        """`identity`: dotted config keys (or key prefixes) that must agree between a run and its resume."""
        self.path = Path(path).resolve()
        self.config = dict(config)
        self.identity = identity
        cfg_file = self.path / "config.yaml"
        if cfg_file.exists():
            try:
                saved = yaml.safe_load(cfg_file.read_text()) or {}
            except yaml.YAMLError as e:
                raise RunDirError(f"{cfg_file}: unreadable config ({e}); nothing was changed") from None
            self._check_same(saved, cfg_file)
        self.path.mkdir(parents=True, exist_ok=True)
        if not cfg_file.exists():
            cfg_file.write_text(yaml.safe_dump(self.config, sort_keys=False))
        self._manager = None
        self._tb = None                  # TensorBoard writer, opened with the first logged row

    def _check_same(self, saved: Mapping, where: Path) -> None:
        a, b = _flatten(saved), _flatten(self.config)
        diffs = []
        for key in sorted(set(a) | set(b)):
            if any(key == p or key.startswith(p + ".") for p in self.identity) and a.get(key) != b.get(key):
                diffs.append(f"{key}: saved {a.get(key)!r}, now {b.get(key)!r}")
        if diffs:
            raise RunDirError(f"{where}: this run directory belongs to a different run ("
                              + "; ".join(diffs) + "). Use a new run_dir, or the same settings to resume; "
                              "nothing was changed")

    # ---- checkpoints ---------------------------------------------------------------------------------------
    @property
    def manager(self):
        if self._manager is None:
            self._manager = ocp.CheckpointManager(
                self.path / "checkpoints", options=ocp.CheckpointManagerOptions(max_to_keep=3, create=True))
        return self._manager

    def latest_step(self) -> int | None:
        if not (self.path / "checkpoints").exists():
            return None
        return self.manager.latest_step()

    def save(self, step: int, state) -> None:
        """Checkpoint the leaves of `state` (Orbax cannot store zero-size arrays, so those are left out and
        rebuilt from the live structure on restore)."""
        leaves = jax.tree_util.tree_leaves(state)
        payload = {f"leaf{i:05d}": x for i, x in enumerate(leaves) if x.size}
        self.manager.save(step, args=ocp.args.StandardSave(payload))
        self.manager.wait_until_finished()

    def restore(self, step: int, like):
        """Restore checkpoint `step` into the structure of `like` (an initial train state, or its
        `jax.eval_shape`)."""
        where = self.path / "checkpoints" / str(step)
        leaves, treedef = jax.tree_util.tree_flatten(like)
        abstract = {f"leaf{i:05d}": jax.ShapeDtypeStruct(x.shape, x.dtype) for i, x in enumerate(leaves) if x.size}
        try:
            got = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
            if set(got) != set(abstract):
                raise ValueError(f"{len(got)} arrays stored, {len(abstract)} expected")
            for k, a in abstract.items():
                if got[k].shape != a.shape or got[k].dtype != a.dtype:
                    raise ValueError(f"{k}: stored {got[k].shape} {got[k].dtype}, expected {a.shape} {a.dtype}")
        except Exception as e:  # noqa: BLE001 - any failure to read is reported as one user-facing error
            raise RunDirError(f"{where}: the checkpoint could not be restored into this run's train state "
                              f"({type(e).__name__}: {str(e)[:300]}). It may be corrupt or from another model; "
                              "nothing was changed") from None
        # uncommitted device arrays, like those of a fresh state: jitted functions then hit their compile cache
        # (Orbax returns committed arrays, which would make every jitted train function compile again)
        return jax.tree_util.tree_unflatten(
            treedef, [jax.numpy.asarray(np.asarray(got[f"leaf{i:05d}"])) if x.size else jax.numpy.zeros(x.shape, x.dtype)
                      for i, x in enumerate(leaves)])

    # ---- metrics -------------------------------------------------------------------------------------------
    def truncate_metrics(self, last_iteration: int) -> None:
        """Keep metric rows up to `last_iteration`; later rows move to metrics.csv.orphaned."""
        f = self.path / "metrics.csv"
        if not f.exists():
            return
        with f.open() as fh:
            rows = list(csv.DictReader(fh))
        keep = [r for r in rows if int(float(r["iteration"])) <= last_iteration]
        if len(keep) == len(rows):
            return
        shutil.copy(f, f.with_suffix(".csv.orphaned"))
        with f.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
            w.writeheader()
            w.writerows(keep)

    def log(self, row: Mapping[str, float]) -> None:
        f = self.path / "metrics.csv"
        row = {k: (float(v) if not isinstance(v, (int, str)) else v) for k, v in row.items()}
        new = not f.exists()
        with f.open("a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(row.keys()))
            if new:
                w.writeheader()
            w.writerow(row)
        if self._tb is None:
            self._tb = SummaryWriter(str(self.path / "tb"))
        step = int(row.get("env_steps", row["iteration"]))
        for k, v in row.items():
            if isinstance(v, (int, float)) and k not in ("iteration",) and math.isfinite(float(v)):
                self._tb.add_scalar(k, float(v), step)
        self._tb.flush()

    def read_metrics(self) -> list[dict[str, float]]:
        f = self.path / "metrics.csv"
        if not f.exists():
            return []
        with f.open() as fh:
            return [{k: float(v) for k, v in r.items() if v not in ("", None)} for r in csv.DictReader(fh)]

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
        if self._manager is not None:
            self._manager.close()
