"""Trainable parameter counts of every architecture of the zoo.

    python -m experiments.params env=ft                  # one task: ft, incline, csr or obstacle
    python -m experiments.params env=csr
    python -m experiments.params all_envs=true           # every task of mjx_morph.sim.tasks, one block each
    python -m experiments.params archs=[rmemo,rmomo]     # a subset

Output: one line per architecture, `<arch> <trainable parameters>`, optionally followed by a note in
parentheses. With all_envs=true each task's block starts with a `# env=<name> ...` line. The count comes
from the Flax parameters that `Model.init` creates (traced with jax.eval_shape, so no compute), built as a
training run builds it (`mjx_morph.run.make_model_for`: the architecture's defaults, the task's height map and
decoder layers), with the spec's reading of every flag; where a run's measured defaults (`nets.zoo.RECOMMENDED`,
e.g. R-MeMo's context MLP) change the count, a note gives the count a run has.

Reference numbers: the paper's table (ft; incline has identical networks) and the csr / obstacle counts of the
original MetaMorph / ModuMorph code. Where ours differ, it is because the original ModuMorph code also
builds a plain `limb_embed` and a plain decoder that its forward pass never calls; we do not create them,
and the note gives the difference. Any other difference is reported as MISMATCH and the exit code is 1.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import List, Optional

from mjx_morph.nets import ARCHS, Model
from mjx_morph.nets.zoo import RECOMMENDED
from mjx_morph.run import RunConfig, make_model_for, register
from mjx_morph.run.config import with_recommended
from mjx_morph.sim.env import EnvConfig
from mjx_morph.sim.tasks import TASKS

from . import cli

#: (env, arch) -> (reference count, where it comes from)
REFERENCES: dict[tuple[str, str], tuple[int, str]] = {
    **{(env, arch): (n, "paper") for env in ("ft", "incline") for arch, n in
       (("metamorph", 3_312_515), ("rmemo", 3_568_259), ("modumorph", 5_232_774), ("rmomo", 5_563_526))},
    ("csr", "metamorph"): (3_525_955, "original code"),
    ("csr", "modumorph"): (8_608_262, "original code"),
    ("obstacle", "metamorph"): (3_534_275, "original code"),
    ("obstacle", "modumorph"): (9_689_862, "original code"),
}


@dataclasses.dataclass
class ParamsConfig:
    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)   # env=<task>: ft | incline | csr | obstacle
    archs: Optional[List[str]] = None   # None: every architecture of mjx_morph.nets.ARCHS
    all_envs: bool = False              # one block per task; `env` is then ignored


register("params_schema", ParamsConfig)


def model_of(arch: str, task: str) -> Model:
    return make_model_for(RunConfig(env=EnvConfig(task=task), arch=arch))


def unused_in_original(model: Model) -> int:
    """Parameters of the plain limb_embed and plain decoder that the original ModuMorph code builds (in actor
    and critic) but never calls; 0 for the MetaMorph family."""
    net = model.net
    if net.base != "modu":
        return 0
    n = 0
    for out in (2, 1):
        n += net.embed_in * net.d_model + net.d_model
        dims = net.decoder_layers(out)
        n += sum(a * b + b for a, b in zip(dims[:-1], dims[1:]))
    return n


def count_line(arch: str, task: str) -> tuple[str, bool]:
    """('<arch> <count>[  (note)]', ok)."""
    model = model_of(arch, task)
    n = model.num_params()
    line, ok = f"{arch} {n}", True
    ref = REFERENCES.get((task, arch))
    if ref is not None:
        want, where = ref
        extra = unused_in_original(model)
        if n == want:
            line += f"  (= {where})"
        elif extra and n + extra == want:
            line += (f"  ({where}: {want}, which also counts {extra} parameters of a plain limb_embed and decoder "
                     f"that the original code builds but never calls; we do not create them)")
        else:
            line += f"  ({where}: {want}; MISMATCH by {n - want:+d})"
            ok = False
    recommended = RECOMMENDED.get(arch, {})
    if recommended:
        n_run = make_model_for(with_recommended(RunConfig(env=EnvConfig(task=task), arch=arch))).num_params()
        if n_run != n:
            changed = ", ".join(f"{k}={v}" for k, v in recommended.items())
            line += f"  (a run, with the measured default {changed}: {n_run}, {n_run - n:+d})"
    return line, ok


def counts(c: ParamsConfig) -> None:
    archs = list(c.archs) if c.archs is not None else list(ARCHS)
    unknown = [a for a in archs if a not in ARCHS]
    if unknown:
        raise ValueError(f"unknown architecture(s) {unknown}; known: {list(ARCHS)}")
    ok = True
    for task in (list(TASKS) if c.all_envs else [c.env.task]):
        if c.all_envs:
            t = TASKS[task]
            print(f"# env={task} hfield_obs={t.hfield_obs} decoder_dims={list(t.decoder_dims)}")
        for arch in archs:
            line, good = count_line(arch, task)
            ok &= good
            print(line, flush=True)
    if not ok:
        raise SystemExit(1)


def main(argv=None) -> int:
    return cli.main(counts, "params", ParamsConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
