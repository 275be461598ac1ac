"""Trainable parameter counts of every architecture of the zoo.

    python -m experiments.params env=ft                  # one task: ft, incline, csr or obstacle
    python -m experiments.params env=csr
    python -m experiments.params all_envs=true           # every task in experiments/conf/env, one block each
    python -m experiments.params archs=[rmemo,rmomo]     # a subset

Output: one line per architecture, `<arch> <trainable parameters>`, optionally followed by a note in
parentheses. With all_envs=true each task's block starts with a `# env=<name> ...` line. The count comes
from the Flax parameters that `Model.init` creates (traced with jax.eval_shape, so no compute), built
from `experiments/conf/arch/<arch>.yaml` and the task's env config (height map, decoder layers).

Reference numbers: the paper's table (ft; incline has identical networks) and the spec's csr / obstacle
numbers (spec/architecture.md §3). Where ours differ, it is because the original ModuMorph code also
builds a plain `limb_embed` and a plain decoder that its forward pass never calls; we do not create them,
and the note gives the difference. Any other difference is reported as MISMATCH and the exit code is 1.
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from mjx_morph.nets import ARCHS, Model, model_from_config

CONF = Path(__file__).resolve().parent / "conf"

#: (env, arch) -> (reference count, where it comes from)
REFERENCES: dict[tuple[str, str], tuple[int, str]] = {
    **{(env, arch): (n, "paper") for env in ("ft", "incline") for arch, n in
       (("metamorph", 3_312_515), ("rmemo", 3_568_259), ("modumorph", 5_232_774), ("rmomo", 5_563_526))},
    ("csr", "metamorph"): (3_525_955, "spec §3"),
    ("csr", "modumorph"): (8_608_262, "spec §3"),
    ("obstacle", "metamorph"): (3_534_275, "spec §3"),
    ("obstacle", "modumorph"): (9_689_862, "spec §3"),
}


def _compose_group(group: str, name: str) -> DictConfig:
    overrides = [f"+{group}={name}"]
    if GlobalHydra.instance().is_initialized():          # inside a Hydra app
        cfg = compose(config_name=None, overrides=overrides)
    else:
        with initialize_config_dir(config_dir=str(CONF), version_base=None):
            cfg = compose(config_name=None, overrides=overrides)
    return cfg[group]


def arch_config(name: str) -> DictConfig:
    """experiments/conf/arch/<name>.yaml, composed by Hydra (struct mode: unknown keys are errors)."""
    cfg = _compose_group("arch", name)
    if cfg.name != name:
        raise ValueError(f"conf/arch/{name}.yaml has name {cfg.name!r}")
    return cfg


def env_config(name: str) -> DictConfig:
    return _compose_group("env", name)


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


def count_line(arch: str, env_cfg: DictConfig) -> tuple[str, bool]:
    """('<arch> <count>[  (note)]', ok)."""
    model = model_from_config(arch_config(arch), env_cfg)
    n = model.num_params()
    line, ok = f"{arch} {n}", True
    ref = REFERENCES.get((str(env_cfg.name), arch))
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
    return line, ok


@hydra.main(version_base=None, config_path="conf", config_name="params")
def main(cfg: DictConfig) -> None:
    archs = list(cfg.archs) if cfg.archs is not None else list(ARCHS)
    unknown = [a for a in archs if a not in ARCHS]
    if unknown:
        raise SystemExit(f"unknown architecture(s) {unknown}; known: {list(ARCHS)}")
    if cfg.all_envs:
        order = ["ft", "incline", "csr", "obstacle"]
        names = sorted((p.stem for p in (CONF / "env").glob("*.yaml")),
                       key=lambda n: (order.index(n) if n in order else len(order), n))
        envs = [env_config(n) for n in names]
    else:
        envs = [cfg.env]
    ok = True
    for env in envs:
        if cfg.all_envs:
            print(f"# env={env.name} hfield_obs={env.hfield_obs} decoder_dims={OmegaConf.to_container(env.decoder_dims)}")
        for arch in archs:
            line, good = count_line(arch, env)
            ok &= good
            print(line, flush=True)
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main()
