"""The schema of a training run: `RunConfig`, built from the dataclasses of the stages it configures.

    cfg = compose_run_config(["env=csr", "arch=modumorph", "ppo.kl_threshold=0.03"])   # a typed RunConfig
    cfg = read_run_config("runs/ft-rmomo-s0/config.yaml")                             # a run's saved config

Every key has one home, and its default is stated there only:

| keys              | home                                             |
|-------------------|--------------------------------------------------|
| `env.*`           | `mjx_morph.sim.env.EnvConfig` (task, simulator options, context features) |
| `model.*`         | `mjx_morph.nets.zoo.ModelOptions` (overrides of the architecture's sizes and flags) |
| `ppo.*`           | `mjx_morph.ppo.config.PPOConfig`                 |
| everything else   | `RunConfig` below (robots, seed, steps, run directory, loop options) |

`env=<task>` picks a task (Hydra config group `env`, one option per task of `mjx_morph.sim.tasks.TASKS`);
`preset=<name>` applies one of `experiments/conf/preset/*.yaml`, YAML files that only override keys of this schema.
Unknown keys and values of the wrong type are refused with one line naming the key and the expected type
(`ConfigError`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterable, List, Optional

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from ..nets.precision import DEFAULT as DEFAULT_PRECISION
from ..nets.precision import check as check_precision
from ..nets.zoo import ModelOptions, recommended
from ..ppo.config import PPOConfig
from ..sim.env import EnvConfig
from ..sim.model import is_digest
from ..sim.tasks import TASKS
from .compile_cache import DEFAULT_COMPILE_CACHE

#: Hydra's config folder of the command-line tools (config.yaml with the defaults list, presets, studies)
CONF_DIR = Path(__file__).resolve().parents[2] / "experiments" / "conf"


@dataclasses.dataclass
class RunConfig:
    """One training run (`python -m experiments.run key=value ...`)."""
    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)
    arch: str = "rmomo"                 # one of mjx_morph.nets.ARCHS
    model: ModelOptions = dataclasses.field(default_factory=ModelOptions)
    precision: str = DEFAULT_PRECISION  # the networks' arithmetic: fp32 | tf32 | bf16 (mjx_morph.nets.precision;
                                        # the physics is always float32 at the highest matmul precision)
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    seed: int = 0
    seeds: Optional[List[int]] = None   # several seeds side by side in one compiled program, each its own run
                                        # (replaces `seed`; run_dir must then contain {seed}: run_dir="runs/x-s{seed}")
    robots: Optional[str] = None        # robot set or path; None: unimal100/train when the original robots exist,
                                        # else the shipped gen/train
    robots_root: Optional[str] = None   # folder of the original robots (None: $MJX_MORPH_UNIMALS, else
                                        # ../shared/unimals_100 beside the project)
    num_robots: Optional[int] = None    # use only the first N robots of the set (training-set-size runs)
    allow_outside_design_space: bool = False   # accept robot files with values far beyond the UNIMAL design space
                                        # (mjx_morph.unimal.design_space bounds); off: such a file is refused
    total_steps: int = 100_000_000      # env steps (control steps summed over envs); the schedule's horizon
    run_dir: Optional[str] = None       # None: runs/<task>-<arch>-s<seed>; rerun with the same run_dir to resume;
                                        # {seed} in it is replaced by the seed
    stop_after: Optional[int] = None    # end this invocation after N iterations (with a checkpoint)
    stop_at: Optional[int] = None       # end the run at iteration N of its schedule (a rerun trains no further;
                                        # e.g. the first 20 M steps of a 100 M schedule: total_steps=1e8 stop_at=245)
    time_limit_min: Optional[float] = None   # end this invocation after about N minutes (with a checkpoint)
    checkpoint_every: int = 50          # iterations between Orbax checkpoints (and always at the end)
    stall_min: Optional[float] = 10.0   # end the process (exit status 75) when one iteration after the first runs
                                        # this many minutes and 20x the slowest before it: a stalled device;
                                        # null: wait forever
    devices: Optional[int] = None       # devices the envs are sharded over (data parallel, same global batch);
                                        # None: every visible device (of every process)
    coordinator: Optional[str] = None   # several processes (hosts): "host:port" of process 0, or auto (JAX detects
                                        # SLURM, Open MPI, TPU); None: $MJX_MORPH_COORDINATOR, else one process
                                        # (mjx_morph/run/distributed.py)
    num_processes: Optional[int] = None  # processes of the run (None: $MJX_MORPH_NUM_PROCESSES)
    process_id: Optional[int] = None    # this process, 0 .. num_processes - 1 (None: $MJX_MORPH_PROCESS_ID)
    stop_unhealthy: bool = True         # end the run at its first health warning (run.loop.HealthWarnings: it
                                        # starts broken), with a checkpoint and unhealthy.txt in its run directory,
                                        # which a rerun refuses to resume unless stop_unhealthy=false
    phase_timing: bool = True           # rollout and update as two jitted calls, to log env steps/s per phase
    fast_compile: bool = False          # XLA CPU optimisations off: faster compiles, slower steps (tests, smoke)
    progress: bool = True               # progress bar with steps/s and ETA
    progress_every_min: Optional[float] = 1.0   # with progress=false: a plain progress line every N minutes (null: none)
    compile_cache: Optional[str] = DEFAULT_COMPILE_CACHE   # compiled programs kept across invocations; None: off
    allow_changes: List[str] = dataclasses.field(default_factory=list)
                                        # on a resume: training keys that may differ from the saved config
                                        # (e.g. [total_steps]); recorded in config_history.yaml
    resume_step: Optional[int] = None   # resume from this checkpoint instead of the newest (later ones are set aside)
    expect_physics: Optional[str] = None   # the model digest (its first 8 to 16 hex digits) this run must train on:
                                        # a config or checkout that builds other physics stops before compiling
                                        # (the seeds of a comparison; `python -m experiments.digest` prints a run's)

    def default_run_dir(self) -> Path:
        return Path("runs") / f"{self.env.task}-{self.arch}-s{self.seed}"

    def last_iteration(self) -> int:
        """The iteration the run ends at: its schedule's last (as the Trainer counts it), or stop_at."""
        last = self.ppo.iterations(self.total_steps)
        return last if self.stop_at is None else min(last, self.stop_at)

    def check(self) -> None:
        """Values the types cannot refuse: one line naming the key and what was expected (ValueError)."""
        positive = {"total_steps": self.total_steps, "checkpoint_every": self.checkpoint_every,
                    "num_robots": self.num_robots, "stop_after": self.stop_after,
                    "time_limit_min": self.time_limit_min, "resume_step": self.resume_step, "devices": self.devices,
                    "stop_at": self.stop_at, "progress_every_min": self.progress_every_min}
        for key, v in positive.items():
            if v is not None and v <= 0:
                raise ValueError(f"{key}={v}: expected a positive number" + (" or null" if key != "total_steps"
                                                                             and key != "checkpoint_every" else ""))
        if self.seeds is not None:
            if not self.seeds or len(set(self.seeds)) < len(self.seeds) or min(self.seeds) < 0:
                raise ValueError(f"seeds={self.seeds}: expected distinct non-negative seeds, or null for one run")
            if self.run_dir is not None and "{seed}" not in self.run_dir:
                raise ValueError(f"run_dir={self.run_dir}: with seeds={self.seeds} each seed needs its own run "
                                 "directory; put {seed} in it (quoted for Hydra: 'run_dir=\"runs/x-s{seed}\"')")
        if self.expect_physics is not None and not is_digest(self.expect_physics, prefix=True):
            raise ValueError(f"expect_physics={self.expect_physics}: expected 8 to 16 lowercase hex digits of a model "
                             "digest (devices.yaml's model_digest, or `python -m experiments.digest runs=[...]`)")
        self.ppo.check_values()
        check_precision(self.precision)


#: keys that shape the train state: a resume must agree on them (dotted keys or prefixes)
IDENTITY = ("env.task", "env.context_features", "arch", "model", "robots", "robots_root", "num_robots", "seed",
            "ppo.num_envs", "ppo.rollout_len", "ppo.window", "ppo.burn_in", "ppo.minibatch_size", "ppo.sampling")
#: keys of the loop alone, which a resume may change freely; every other key changes only through allow_changes
#: (env.linalg too: how MJX's Cholesky is computed, the same equations; runs saved before the key resume as they are)
FREE = ("run_dir", "devices", "seeds", "coordinator", "num_processes", "process_id", "stop_after", "stop_at",
        "time_limit_min", "checkpoint_every", "stall_min", "stop_unhealthy", "phase_timing", "fast_compile",
        "progress", "progress_every_min", "compile_cache", "allow_changes", "resume_step", "allow_outside_design_space",
        "expect_physics", "env.linalg")


class ConfigError(ValueError):
    """A config key that does not exist, or a value of the wrong type (one line)."""


def register(name: str, schema: type) -> None:
    """Make a schema dataclass available to Hydra's defaults lists under `name`."""
    ConfigStore.instance().store(name=name, node=schema)


def _register_run_schema() -> None:
    cs = ConfigStore.instance()
    cs.store(name="run_schema", node=RunConfig)
    for task in TASKS:
        cs.store(group="env", name=task, node=EnvConfig(task=task))


_register_run_schema()


def config_error(e: BaseException, overrides: Iterable[str] = ()) -> ConfigError:
    """One-line `ConfigError` for an exception of Hydra's composition or OmegaConf's validation."""
    cause = e
    while cause.__cause__ is not None and not isinstance(cause, OmegaConfBaseException):
        cause = cause.__cause__
    key = getattr(cause, "full_key", None)
    msg = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    given = next((o for o in overrides if key and o.lstrip("+~").split("=", 1)[0] == key), None)
    if key and ("not in struct" in str(cause) or "Could not override" in str(e) or "Could not append" in str(e)
                or type(cause).__name__ in ("ConfigAttributeError", "ConfigKeyError")):
        return ConfigError(f"unknown config key {key!r}" + (f" (in {given!r})" if given else ""))
    if type(cause).__name__ == "MissingMandatoryValue" and key:
        return ConfigError(f"{key}: required, no value given ({key}=...)")
    if key:
        return ConfigError(f"{given or key}: {msg}")
    if "Could not find" in str(e) and "env/" in str(e):
        bad = next((o for o in overrides if o.startswith("env=")), "env=?")
        return ConfigError(f"{bad}: unknown task; expected one of {', '.join(TASKS)}")
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return ConfigError(f"{first}: {msg}" if msg not in first else first)


def compose(config_name: str, overrides: Iterable[str] = (), schema: type = RunConfig,
            config_dir: Path = CONF_DIR) -> Any:
    """Compose `config_dir/config_name.yaml` with command-line `overrides` into an instance of `schema`; a run's
    config gets the architecture's RECOMMENDED model options it does not set (`with_recommended`)."""
    overrides = list(overrides)
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base=None):
            cfg = hydra_compose(config_name=config_name, overrides=overrides)
        cfg = to_schema(cfg, schema)
    except (HydraException, OmegaConfBaseException) as e:
        raise config_error(e, overrides) from None
    return with_recommended(cfg, overrides) if isinstance(cfg, RunConfig) else cfg


def with_recommended(cfg: RunConfig, overrides: Iterable[str] = ()) -> RunConfig:
    """`cfg` with the measured model options of its architecture (`nets.zoo.RECOMMENDED`) where the config leaves
    them unset (null) and no override names them: `model.scale_after_cell=null` keeps the spec's reading (what a
    run directory saved before the recommendation holds)."""
    keys = (o.lstrip("+~").split("=", 1)[0] for o in overrides)
    named = {k.removeprefix("model.") for k in keys if k.startswith("model.")}
    fill = recommended(cfg.arch, dataclasses.asdict(cfg.model), named)
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **fill)) if fill else cfg


def compose_run_config(overrides: Iterable[str] = ()) -> RunConfig:
    return compose("config", overrides)


def to_schema(cfg: Any, schema: type = RunConfig) -> Any:
    """A `schema` instance from a composed DictConfig, a plain dict or an instance (validated, resolved)."""
    if isinstance(cfg, schema):
        return cfg
    try:
        node = OmegaConf.merge(OmegaConf.structured(schema), cfg)
        return OmegaConf.to_object(node)
    except OmegaConfBaseException as e:
        raise config_error(e) from None


def to_dict(cfg: Any) -> dict:
    """A plain, resolved dict of a schema instance (what a run directory's config.yaml holds)."""
    return OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True)


def read_run_config(path: str | Path) -> RunConfig:
    """The RunConfig saved in a run directory's config.yaml; a file that does not fit the schema gives a
    ConfigError naming the file."""
    path = Path(path)
    try:
        data = OmegaConf.load(path)
    except Exception as e:  # noqa: BLE001 - yaml and io errors alike
        raise ConfigError(f"{path}: unreadable config ({type(e).__name__}: {e})") from None
    try:
        return to_schema(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
