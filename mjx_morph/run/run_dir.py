"""One directory per run: resolved config, metrics (CSV + TensorBoard), Orbax checkpoints, figures.

    <run_dir>/config.yaml        the resolved config of the run (written once; a resume must match it)
    <run_dir>/metrics.csv        one row per iteration
    <run_dir>/tb/                TensorBoard event files
    <run_dir>/checkpoints/<it>/  Orbax checkpoints of the whole train state
    <run_dir>/learning_curve.png

    <run_dir>/config_history.yaml  changes accepted on a resume (`allow_changes`), in order
    <run_dir>/devices.yaml         one entry per invocation (start or resume): when, from which iteration, on what
                                   devices (platform, device_kind, num_devices, processes): wall times depend on it;
                                   the machine's parts of JAX's compile-cache key (jax, platform_version,
                                   topology): two machines share cached programs only where these agree; and the
                                   env's model digest (`UnimalEnv.digest`: the physics it simulates)
    <run_dir>/physics.yaml         only for a run that recorded no digest (trained before session 45): its physics
                                   computed afterwards from its config by a checkout whose physics code was the
                                   run's (`python -m experiments.digest ... record=WHY`), with the checkout's
                                   commit and the reason; the report marks such a run's physics as computed

Opening a run directory (`RunDir(...)`) writes nothing; `create()` makes the directory and writes config.yaml once
the caller has validated everything else, so a failed start leaves no trace.

Resuming: rerunning with the same run directory restores the newest checkpoint. Before anything is touched, the
config is compared with the saved one: keys that shape the train state (architecture, task, robots, batch geometry,
model sizes, seed: `identity`) must agree; any other training key (learning rate, epochs, total steps, simulator
options, ...) must agree too unless the resume names it in `allow_changes`, and then the change is recorded in
config_history.yaml and config.yaml is updated; only the loop's own keys (`free`: run_dir, stop_after, progress,
...) may differ silently. The physics must agree too: the env's model digest against the one devices.yaml recorded
last (`check_digest`; `allow_changes=[model_digest]` accepts a change). A mismatch, an unreadable config or an
unreadable checkpoint raises `RunDirError` naming the file and what differs, and the directory is left as it was.

Metric rows of iterations after the restored checkpoint (an interrupted run's last, unsaved iterations; all rows of
a run that crashed before its first checkpoint) are moved to `metrics.csv.orphaned` rather than deleted and are
logged again by the resumed run; TensorBoard's events are rebuilt from the rows kept (the old ones move to
`tb.orphaned/`), so neither shows an iteration twice.

Several processes (`mjx_morph/run/distributed.py`): every process opens the run directory and takes part in saving
and restoring checkpoints (Orbax writes and reads each process's shards of the global arrays); only process 0
writes config.yaml, devices.yaml, metrics, TensorBoard and moves files. A reader (`RunDir(path)` without a config)
restores on its own process, so process 0 alone can load a checkpoint (evaluation) while the others wait.
"""
from __future__ import annotations

import csv
import datetime
import math
import shutil
from pathlib import Path
from typing import Any, Mapping

import jax
import numpy as np
import orbax.checkpoint as ocp
import yaml
from tensorboardX import SummaryWriter

from ..sim.model import is_digest
from .distributed import barrier, is_main, several


class RunDirError(RuntimeError):
    pass


def flatten_config(d: Mapping, prefix: str = "") -> dict[str, Any]:
    """A nested config as {dotted key: value}."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten_config(v, key + "."))
        else:
            out[key] = v
    return out


def _aside(path: Path) -> Path:
    """`path`, or `path.N` for the first N that does not exist yet (files set aside are never overwritten)."""
    if not path.exists():
        return path
    n = 1
    while path.with_name(f"{path.name}.{n}").exists():
        n += 1
    return path.with_name(f"{path.name}.{n}")


def _number(text: str | None) -> int | float:
    """A CSV cell back as the number it was logged as (int or float; nan for an empty cell)."""
    if text in ("", None):
        return float("nan")
    try:
        return int(text)
    except ValueError:
        return float(text)


def _cell(value: int | float | str) -> int | str:
    """A metric as metrics.csv writes it: a whole number as an integer, any other number as the shortest text that
    reads back as the same float32. The learner's metrics are float32, so they lose nothing; host timings keep 7
    digits. About half the bytes of float64's 17 digits: every finished run's metrics.csv is committed under results/,
    and the checkout travels to the GPU machine within a size limit (tools/device_job.sh fit)."""
    if isinstance(value, (int, str)):
        return value
    x = float(value)
    if x.is_integer() and abs(x) < 2 ** 53:
        return int(x)
    return str(np.float32(x))


def at_float32(tree):
    """Every float of a JSON-like tree (dicts, lists) at float32's precision, as the float whose text is float32's
    shortest: what eval/*.json store (returns are sums of float32 rewards; 7 digits are all they hold), ~30% fewer
    bytes than float64's 17 digits in the committed results."""
    if isinstance(tree, dict):
        return {k: at_float32(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [at_float32(v) for v in tree]
    if isinstance(tree, float) and math.isfinite(tree) and not tree.is_integer():
        return float(str(np.float32(tree)))
    return tree


def _write_atomic(path: Path, text: str) -> None:
    """Write a file whole or not at all (other processes may read it meanwhile)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def matches_key(key: str, prefixes) -> bool:
    """`key` is one of the dotted `prefixes` or lies below one."""
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def cache_key_machine() -> dict:
    """What of the machine goes into JAX's persistent compile-cache key besides the program and the compiler options
    (jax/_src/cache_key.py): JAX's version, the backend's platform version (on a GPU, CUDA's and the driver's) and
    the fingerprint of the devices' topology. A cache brought from another machine (tools/device_job.sh) serves only
    where all three agree: session 32's 4-GPU host compiled afresh the programs a one-GPU host's cache held, with
    the same device kind."""
    devices = jax.devices()
    out = {"jax": jax.__version__, "platform_version": str(devices[0].client.platform_version)}
    try:
        from jax._src.lib import xla_client      # not public: the same call cache_key.py makes; absent, left out
        out["topology"] = f"{xla_client.get_topology_for_devices(devices).fingerprint():016x}"
    except Exception:       # a backend without a serialisable topology (JAX then hashes the device kinds alone)
        pass
    return out


#: a run's physics computed afterwards (see the module's docstring); never written where devices.yaml records one
COMPUTED_PHYSICS = "physics.yaml"


def invoked_values(entries: list, key: str) -> list[str]:
    """The distinct values of `key` over devices.yaml's `entries` (`read_invocations`), in order; [] for none."""
    return list(dict.fromkeys(str(e[key]) for e in entries if isinstance(e, dict) and e.get(key)))


def recorded_digests(run_dir: str | Path) -> list[str]:
    """The distinct model digests `run_dir`'s invocations recorded (devices.yaml), in order; [] for none."""
    return invoked_values(read_invocations(run_dir), "model_digest")


def read_computed_physics(run_dir: str | Path) -> dict | None:
    """`run_dir`/physics.yaml (model_digest, computed, code, why), None where there is none; ValueError (one
    line: what is wrong) where it cannot be read or names no 16-digit digest."""
    f = Path(run_dir) / COMPUTED_PHYSICS
    if not f.is_file():
        return None
    try:
        data = yaml.safe_load(f.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise ValueError(f"{f}: unreadable ({type(e).__name__})") from None
    digest = data.get("model_digest") if isinstance(data, dict) else None
    if not is_digest(digest):
        raise ValueError(f"{f}: expected a mapping with model_digest: 16 hex digits, found {digest!r}")
    return data


def write_computed_physics(run_dir: str | Path, digest: str, why: str, code: str) -> bool:
    """Record `digest` as the physics of `run_dir`, a run that recorded none, computed afterwards by the checkout
    `code` (a commit) for the reason `why`. False where physics.yaml already says so; RunDirError, writing nothing,
    where devices.yaml records a digest (the run's own record stands) or physics.yaml names another."""
    run_dir = Path(run_dir)
    if not why.strip():
        raise RunDirError(f"{run_dir}: record= needs the reason this checkout's physics is the run's (e.g. the "
                          "commits between them that touch mjx_morph/sim or mjx_morph/unimal)")
    try:
        recorded, before = recorded_digests(run_dir), read_computed_physics(run_dir)
    except ValueError as e:
        raise RunDirError(f"{run_dir}: {e}; nothing was written") from None
    if recorded:
        raise RunDirError(f"{run_dir / 'devices.yaml'}: the run recorded its physics ({', '.join(recorded)}) while "
                          "it trained; a computed one is only for runs that recorded none. Nothing was written")
    if before is not None:
        if before["model_digest"] != digest:
            raise RunDirError(f"{run_dir / COMPUTED_PHYSICS}: names {before['model_digest']}, this checkout "
                              f"computes {digest}: one of the two checkouts' physics is not the run's; nothing "
                              "was written")
        return False
    entry = {"model_digest": digest,
             "computed": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
             "code": code, "why": why.strip()}
    try:
        _write_atomic(run_dir / COMPUTED_PHYSICS, yaml.safe_dump(entry, sort_keys=False))
    except OSError as e:
        raise RunDirError(f"{run_dir}: cannot write {COMPUTED_PHYSICS} ({e.strerror or e})") from None
    return True


def read_invocations(run_dir: str | Path) -> list:
    """The entries of `run_dir`/devices.yaml, one per invocation ([] where there is none); ValueError (one line:
    what is wrong, and where) where it cannot be read."""
    f = Path(run_dir) / "devices.yaml"
    if not f.is_file():
        return []
    try:
        entries = yaml.safe_load(f.read_text()) or []
    except (OSError, yaml.YAMLError) as e:
        mark = getattr(e, "problem_mark", None)
        raise ValueError(type(e).__name__ + (f" at line {mark.line + 1}" if mark else "")) from None
    if not isinstance(entries, list):
        raise ValueError("not a list")
    return entries


class RunDir:
    def __init__(self, path: str | Path, config: Mapping | None = None, identity: tuple[str, ...] = (),
                 free: tuple[str, ...] = (), allow_changes: tuple[str, ...] = ()):
        """Open the run directory `path` for the run of `config` (a plain dict), writing nothing. With a `config`
        and a saved config.yaml, the two must agree on every key except the `free` ones; keys (or prefixes) in
        `allow_changes` may differ unless they are `identity` keys. Without a `config` (readers) nothing is
        checked."""
        self.path = Path(path).resolve()
        self.config = dict(config or {})
        self._reader = config is None
        self._manager = None
        self._tb = None                  # TensorBoard writer, opened with the first logged row
        self.changes: list[str] = []     # accepted changes of this resume, "key: old -> new"
        cfg_file = self.path / "config.yaml"
        if config is not None and cfg_file.exists():
            try:
                saved = yaml.safe_load(cfg_file.read_text()) or {}
            except (yaml.YAMLError, UnicodeDecodeError) as e:
                raise RunDirError(f"{cfg_file}: unreadable config ({type(e).__name__}); nothing was changed") from None
            self._check(saved, cfg_file, identity, free, allow_changes)

    def _check(self, saved: Mapping, where: Path, identity, free, allowed) -> None:
        a, b = flatten_config(saved), flatten_config(self.config)
        fixed, changed = [], []
        for key in sorted(set(a) | set(b)):
            if a.get(key) == b.get(key) or matches_key(key, free):
                continue
            diff = f"{key}: saved {a.get(key)!r}, now {b.get(key)!r}"
            if a.get(key) is None:               # e.g. a default recommended since the run began
                diff += (f" (saved {'null' if key in a else 'without the key'}: pass {key}=null to resume with the "
                         "meaning it had)")
            if matches_key(key, identity):
                fixed.append(diff)
            elif matches_key(key, allowed):
                changed.append(f"{key}: {a.get(key)!r} -> {b.get(key)!r}")
            else:
                fixed.append(diff + " (allow_changes=[" + key + "] to accept it)")
        if fixed:
            raise RunDirError(f"{where}: this run directory belongs to a different run ("
                              + "; ".join(fixed) + "). Use a new run_dir, or the same settings to resume; "
                              "nothing was changed")
        self.changes = changed

    def create(self) -> None:
        """Make the directory and write config.yaml (a new run), or record this resume's accepted changes
        (process 0; the others write nothing)."""
        if not is_main():
            return
        cfg_file = self.path / "config.yaml"
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            if not cfg_file.exists():
                _write_atomic(cfg_file, yaml.safe_dump(self.config, sort_keys=False))
            elif self.changes:
                entry = {"time": datetime.datetime.now().isoformat(timespec="seconds"),
                         "iteration": self.latest_step(), "changes": self.changes}
                with (self.path / "config_history.yaml").open("a") as fh:
                    fh.write(yaml.safe_dump([entry], sort_keys=False))
                _write_atomic(cfg_file, yaml.safe_dump(self.config, sort_keys=False))
        except OSError as e:
            raise RunDirError(f"{self.path}: cannot write the run directory ({e.strerror or e}); "
                              "choose another run_dir") from None

    def record_invocation(self, start_iteration: int, num_devices: int, model_digest: str | None = None,
                          cholesky: str | None = None) -> None:
        """Append this invocation's entry to devices.yaml (process 0; the others write nothing), with the env's
        `model_digest` (`UnimalEnv.digest`) and the Cholesky MJX ran with (`sim.linalg.resolve(env.linalg)`:
        "auto" stands for another on another backend) where given."""
        if not is_main():
            return
        dev = jax.devices()[0]
        entry = {"started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                 "start_iteration": int(start_iteration), "platform": dev.platform, "device_kind": dev.device_kind,
                 "num_devices": int(num_devices), "processes": jax.process_count(), **cache_key_machine()}
        if model_digest is not None:
            entry["model_digest"] = model_digest
        if cholesky is not None:
            entry["cholesky"] = cholesky
        with (self.path / "devices.yaml").open("a") as fh:
            fh.write(yaml.safe_dump([entry], sort_keys=False))

    def recorded_digest(self) -> tuple[str, int] | None:
        """The model digest of the last invocation that recorded one (devices.yaml) and the iteration it started
        at; None for a new run or one from before digests were recorded (session 45)."""
        try:
            entries = read_invocations(self.path)
        except ValueError as e:
            raise RunDirError(f"{self.path / 'devices.yaml'}: unreadable ({e}); it records the physics each "
                              "invocation trained on: restore it, or move it aside to resume without that check; "
                              "nothing was changed") from None
        for e in reversed(entries):
            if isinstance(e, dict) and e.get("model_digest"):
                return str(e["model_digest"]), int(e.get("start_iteration", 0))
        return None

    def check_digest(self, digest: str, allowed: tuple[str, ...] = ()) -> None:
        """On a resume: the env must simulate what the run trained on so far, i.e. give the model digest its last
        invocation recorded, unless `allowed` (allow_changes) names `model_digest`; then the change is recorded in
        config_history.yaml with the config's. Raises RunDirError, writing nothing."""
        before = self.recorded_digest()
        if before is None or before[0] == digest:
            return
        if "model_digest" in allowed:
            self.changes.append(f"model_digest: {before[0]!r} -> {digest!r}")
            return
        raise RunDirError(
            f"{self.path / 'devices.yaml'}: the robots now compile to other physics than this run trained on "
            f"(model digest {before[0]} from iteration {before[1]} on, now {digest}): the code or MuJoCo changed the "
            "models (masses, inertias, geometry, contacts, solver options or the observation's constants; see `git "
            "log -- mjx_morph/unimal mjx_morph/sim`). A run trains on one physics: start a new run_dir, or resume "
            "with allow_changes=[model_digest] to train on knowingly (recorded in config_history.yaml); nothing "
            "was changed")

    # ---- checkpoints ---------------------------------------------------------------------------------------
    @property
    def manager(self):
        if self._manager is None:
            kw = dict(create=True)
            if self._reader and several():     # a reader: this process alone, among several
                me = jax.process_index()
                kw = dict(create=False, multiprocessing_options=ocp.options.MultiprocessingOptions(
                    primary_host=me, active_processes={me}, barrier_sync_key_prefix=f"reader{me}"))
            self._manager = ocp.CheckpointManager(
                self.path / "checkpoints", options=ocp.CheckpointManagerOptions(max_to_keep=3, **kw))
        return self._manager

    def latest_step(self) -> int | None:
        if not (self.path / "checkpoints").exists():
            return None
        return self.manager.latest_step()

    def steps(self) -> list[int]:
        """Iterations of the checkpoints present, ascending."""
        if not (self.path / "checkpoints").exists():
            return []
        return sorted(self.manager.all_steps())

    def set_aside_after(self, step: int) -> list[int]:
        """Move every checkpoint after `step` to checkpoints.orphaned/ (resuming from an earlier checkpoint; process 0
        moves, every process then reopens the checkpoints)."""
        later = [k for k in self.steps() if k > step]
        if later:
            if self._manager is not None:
                self._manager.close()
                self._manager = None
            if is_main():
                dest = self.path / "checkpoints.orphaned"
                dest.mkdir(exist_ok=True)
                for k in later:
                    shutil.move(str(self.path / "checkpoints" / str(k)), str(_aside(dest / str(k))))
            barrier("checkpoints set aside")
        return later

    def save(self, step: int, state) -> None:
        """Checkpoint the leaves of `state` (Orbax cannot store zero-size arrays, so those are left out and
        rebuilt from the live structure on restore). With several processes every one calls it (with the same
        global arrays) and writes its own shards."""
        leaves = jax.tree_util.tree_leaves(state)
        payload = {f"leaf{i:05d}": x for i, x in enumerate(leaves) if x.size}
        self.manager.save(step, args=ocp.args.StandardSave(payload))
        self.manager.wait_until_finished()

    def restore(self, step: int, like):
        """Restore checkpoint `step` into the structure of `like` (an initial train state, or its
        `jax.eval_shape`): each array straight into the sharding of its `like` (a global array of several devices
        or processes: each process reads its own shards, whatever the layout it was saved from), or onto this
        process's first device where `like` has none."""
        where = self.path / "checkpoints" / str(step)
        leaves, treedef = jax.tree_util.tree_flatten(like)
        local = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        shardings = [getattr(x, "sharding", None) or local for x in leaves]
        abstract = {f"leaf{i:05d}": jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=shardings[i])
                    for i, x in enumerate(leaves) if x.size}
        try:
            got = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
            if set(got) != set(abstract):
                raise ValueError(f"{len(got)} arrays stored, {len(abstract)} expected")
            for k, a in abstract.items():
                if got[k].shape != a.shape or got[k].dtype != a.dtype:
                    raise ValueError(f"{k}: stored {got[k].shape} {got[k].dtype}, expected {a.shape} {a.dtype}")
        except Exception as e:  # noqa: BLE001 - any failure to read is reported as one user-facing error
            reason = str(e).strip().splitlines()[0][:160] if isinstance(e, ValueError) else type(e).__name__
            earlier = [k for k in self.steps() if k < step]
            hint = (f" To resume from an earlier checkpoint ({', '.join(map(str, earlier))}), rerun with "
                    f"resume_step={earlier[-1]}: the later checkpoints are then moved to checkpoints.orphaned/."
                    if earlier else "")
            raise RunDirError(f"{where}: the checkpoint could not be restored into this run's train state "
                              f"({reason}); it may be corrupt or from another model. Nothing was changed.{hint}"
                              ) from None
        # one device: uncommitted device arrays, like those of a fresh state, so that jitted functions hit their
        # compile cache (Orbax returns committed arrays, which would make every jitted train function compile
        # again); several devices: the global arrays as restored, already in the train state's layout
        def leaf(i, x):
            if not x.size:
                return x if isinstance(x, jax.Array) else jax.numpy.zeros(x.shape, x.dtype)
            y = got[f"leaf{i:05d}"]
            return jax.numpy.asarray(np.asarray(y)) if len(shardings[i].device_set) == 1 else y
        return jax.tree_util.tree_unflatten(treedef, [leaf(i, x) for i, x in enumerate(leaves)])

    # ---- metrics -------------------------------------------------------------------------------------------
    def truncate_metrics(self, last_iteration: int) -> None:
        """Keep the metric rows up to `last_iteration` (0: none, a fresh start); the whole old file moves to
        metrics.csv.orphaned[.N] and TensorBoard's events to tb.orphaned[.N]/, and the kept rows are logged again
        into fresh events (process 0)."""
        f = self.path / "metrics.csv"
        if not is_main() or not f.exists():
            return
        with f.open() as fh:
            rows = list(csv.DictReader(fh))
        keep = [r for r in rows if int(float(r["iteration"])) <= last_iteration]
        if len(keep) == len(rows):
            return
        shutil.move(str(f), str(_aside(f.with_suffix(".csv.orphaned"))))
        if (self.path / "tb").exists():
            shutil.move(str(self.path / "tb"), str(_aside(self.path / "tb.orphaned")))
        for r in keep:
            self.log({k: _number(v) for k, v in r.items()})

    def log(self, row: Mapping[str, float]) -> None:
        """Append one row to metrics.csv and TensorBoard (process 0; the others write nothing)."""
        if not is_main():
            return
        f = self.path / "metrics.csv"
        row = {k: (float(v) if not isinstance(v, (int, str)) else v) for k, v in row.items()}
        new = not f.exists()
        with f.open("a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(row.keys()))
            if new:
                w.writeheader()
            w.writerow({k: _cell(v) for k, v in row.items()})
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
