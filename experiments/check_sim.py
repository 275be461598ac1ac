"""Fidelity check of the padded, stacked MJX simulation against each robot alone in MuJoCo C.

    python -m experiments.check_sim unimal100/train                 # default solver settings (16 / 8)
    python -m experiments.check_sim unimal100/test mujoco_defaults=true   # MuJoCo's defaults (100 / 50) too
    python -m experiments.check_sim gen/train iterations=100 ls_iterations=50 steps=25
    python -m experiments.check_sim unimal100/train mutated=1000    # 1000 mutants of the train robots, one tree
    python -m experiments.check_sim unimal100/train unpadded_mjx=true   # + each robot alone in MJX (~10 s each)
    python -m experiments.check_sim unimal100/train unpadded_mjx=true x64=true   # both MJX runs in float64
    python -m experiments.check_sim unimal100/train mutated=1000 unpadded_mjx=true unpadded_range=0:100 \
        csv=mutants_0-100.csv     # robots 0-99 alone in MJX (a slice of a long check), per-robot rows to a CSV
    python -m experiments.check_sim merge=[mutants_0-100.csv,mutants_100-200.csv]   # slices' CSVs as one check
    python -m experiments.check_sim unimal100/train task=csr        # height-field tasks: MJX vs MuJoCo C, same patches
    python -m experiments.check_sim unimal100/train task=incline    # the incline: MJX vs MuJoCo C on MetaMorph's slab
    python -m experiments.check_sim unimal100/train task=csr num_robots=5 hfield_contacts=mjx   # MJX's own collider
    python -m experiments.check_sim unimal100/train task=csr 'trace=[mvt-5506-12-4]'   # one robot step by step
    python -m experiments.check_sim unimal100/train task=csr x64=true     # the env in float64: float32's share
    python -m experiments.check_sim unimal100/train task=incline x64=true c_gap=true   # MuJoCo C with MJX's gap
    python -m experiments.check_sim unimal100/train c_gap=true      # ft too: the robots the gap alone moves
    python -m experiments.check_sim unimal100/train c_defaults=true # MuJoCo C converged (MetaMorph's solver)

Prints per robot the worst body-position error (m) over `steps` control steps of the padded MJX robot against the
robot alone in MuJoCo C on MetaMorph's floor, split into the padding's share (padded vs alone, both MuJoCo C) and
MJX's (padded MJX vs padded MuJoCo C), with `unpadded_mjx=true` also the padding's share in float32 MJX (padded MJX
vs the robot alone in MJX; with `x64=true` in float64, where the padding is all that differs), then median / 99th
percentile / max of each (see mjx_morph/sim/fidelity.py), and exits 1 when any robot is over the tolerance (1e-3 m
by default). With `task=` (incline, csr, obstacle): the padded MJX against the padded MuJoCo C on MetaMorph's
ground, beside the same MJX run from a start one float32 ulp away (`ulp`: a robot over the tolerance with an ulp
spread as large follows a chaotic trajectory) and MuJoCo C restarted from MJX's state before each control step
(`step`: the physics compared one step at a time, without the trajectory's amplification). `trace=[NAME, ...]`
(names or their beginnings) prints those robots step by step: the three errors and MuJoCo C's contacts per substep,
in its own run and restarted from MJX's state, with the contacts themselves at the step of the largest step error.
"""
from __future__ import annotations

import csv
import dataclasses
import sys
import time
from pathlib import Path
from typing import List

import jax
import numpy as np

from mjx_morph.run import register
from mjx_morph.sim import fidelity, linalg
from mjx_morph.sim.env import EnvConfig
from mjx_morph.sim.model import self_pair_summary
from mjx_morph.sim.padding import SolverOptions
from mjx_morph.sim.supertree import build_shared_tree
from mjx_morph.sim.tasks import get_task
from mjx_morph.unimal.mutations import mutated_robots
from mjx_morph.unimal.sets import load_set

from . import cli

_ENV = EnvConfig()


@dataclasses.dataclass
class CheckSimConfig:
    set: str = ""                            # robot set name or path (unimal100/train, gen/train, a folder, ...)
    iterations: int = _ENV.iterations        # solver iterations (the env's default)
    ls_iterations: int = _ENV.ls_iterations  # line-search iterations (the env's default)
    mujoco_defaults: bool = False            # also check at MuJoCo's defaults (100 / 50)
    self_collision: bool = _ENV.self_collision
    steps: int = 25                          # control steps compared
    tolerance: float = fidelity.TOLERANCE    # m; robots over it make the exit status 1
    seed: int = 0
    floor_contacts: str = "box"              # box: MetaMorph's floor (MuJoCo C box, its rule in MJX); plane: a plane
    matmul_precision: str = _ENV.matmul_precision   # MJX's matmul precision: highest | default (TF32 on GPUs)
    linalg: str = _ENV.linalg                # MJX's Cholesky: auto (pallas on a GPU, else jax) | jax (JAX's own) |
                                             # pallas (sim/gpu_linalg.py's kernels)
    task: str = "ft"                         # incline | csr | obstacle: compare the padded MJX env with the same padded
                                             # model in MuJoCo C on MetaMorph's slab or on the same height-field
                                             # patches (fidelity.compare_task)
    mutated: int = 0                         # > 0: check this many robots made from the set by DERL's mutation
                                             # operators (one random operator each) instead of the set itself
    num_robots: int = 0                      # > 0: only the set's first num_robots robots
    hfield_contacts: str = _ENV.hfield_contacts   # csr / obstacle: the env's height-field rule (mujoco | mjx)
    hfield_contacts_per_geom: int = _ENV.hfield_contacts_per_geom
    hfield_candidates: int = _ENV.hfield_candidates     # prisms per group tested exactly (0: all)
    contact_budget: int = _ENV.contact_budget     # csr / obstacle: the env's cap on contacts per env (0: none)
    flat_contact_budget: int = _ENV.flat_contact_budget   # ft / incline: the same cap, the env's default (0: none)
    unpadded_mjx: bool = False               # also run each robot alone in MJX: the padding's share in float32
                                             # (one compilation per robot, ~10 s each on a CPU)
    x64: bool = False                        # run MJX in float64 (jax.enable_x64): with unpadded_mjx, padding_mjx
                                             # is the padding's own error in MJX without float32's rounding; with
                                             # task=..., the env in float64 against MuJoCo C (float32's share)
    c_gap: bool = False                      # MuJoCo C with MJX's robot-robot contact gap too
                                             # (model.SELF_CONTACT_GAP): only the engines differ
    c_defaults: bool = False                 # MuJoCo C at MuJoCo's default solver iterations (100 / 50,
                                             # MetaMorph's) whatever MJX runs: our physics against the paper's
    unpadded_range: str = ""                 # "lo:hi": with unpadded_mjx, only robots lo..hi-1 alone in MJX (the
                                             # rest print nan), each as in a run over all robots: slices add up
    trace: List[str] = dataclasses.field(default_factory=list)   # task=...: robots (names or their beginnings)
                                             # printed step by step, with MuJoCo C's contacts
    csv: str = ""                            # also write one row per robot (every printed column) to this CSV file
    merge: List[str] = dataclasses.field(default_factory=list)   # instead of a check: the CSV files of one check's
                                             # slices (unpadded_range) read as one, summarised (and written to csv=)


register("check_sim_schema", CheckSimConfig)


def _range(text: str, n: int) -> range | None:
    """`unpadded_range` "lo:hi" as a range of robot indices (None: all)."""
    if not text:
        return None
    try:
        lo, hi = (int(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"unpadded_range={text!r}: expected lo:hi, two robot indices") from None
    if not 0 <= lo < hi <= n:
        raise ValueError(f"unpadded_range={text!r}: expected 0 <= lo < hi <= {n}, the number of robots")
    return range(lo, hi)


PADDED = ("error", "padding", "mjx", "sensitivity")        # the columns of the padded run (the same in every slice)
ALONE = ("padding_mjx", "mjx_alone", "mjx_ulp")          # the columns of the robots run alone in MJX (one slice's)


def merge_slices(paths: List[str]) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of one check from the CSV files of its slices (`unpadded_range`): every file must hold the same
    robots with the same padded columns (the same check: same set, settings and seed); each robot's alone columns come
    from the file that measured it (nan where none did; a robot measured twice must have the same values)."""
    if not paths:
        raise ValueError("merge: expected the CSV files of a check's slices, got none")
    files = []
    for path in paths:
        if not Path(path).is_file():
            raise ValueError(f"merge: {path}: no such file")
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        if not rows or not {"robot", *PADDED, *ALONE} <= set(rows[0]):
            raise ValueError(f"merge: {path}: not a check_sim CSV with unpadded_mjx columns; expected the header "
                             f"robot,...,{','.join(PADDED + ALONE)}")
        files.append((path, rows[0], rows[1:]))
    first, header, merged = files[0][0], files[0][1], [list(r) for r in files[0][2]]
    col = {k: i for i, k in enumerate(header)}
    measured = lambda r: any(r[col[k]] != "nan" for k in ALONE)
    where = {r[0]: first for r in merged if measured(r)}
    for path, head, rows in files[1:]:
        if head != header or [r[0] for r in rows] != [r[0] for r in merged]:
            raise ValueError(f"merge: {path}: other columns or robots than {first}; expected slices of one check")
        for mine, r in zip(merged, rows):
            bad = next((k for k in header if k not in ALONE and r[col[k]] != mine[col[k]]), None)
            if bad:
                raise ValueError(f"merge: {path}: {r[0]}: {bad} {r[col[bad]]} differs from {first}'s "
                                 f"{mine[col[bad]]}; expected slices of one check (same set, settings and seed)")
            if not measured(r):
                continue
            if r[0] in where and any(r[col[k]] != mine[col[k]] for k in ALONE):
                raise ValueError(f"merge: {path}: {r[0]} was run alone in {where[r[0]]} too, with other values")
            for k in ALONE:
                mine[col[k]] = r[col[k]]
            where[r[0]] = path
    return header, merged


def _cholesky(name: str) -> str:
    """The Cholesky setting as the header names it: "auto" with what it stands for on this backend."""
    return f"{name} ({linalg.resolve(name)})" if name == "auto" else name


def _reference(a: CheckSimConfig) -> str:
    """What the MuJoCo C reference was given beyond its own model (`c_gap`, `c_defaults`), for a summary line."""
    it, ls = fidelity.MUJOCO_SOLVER
    return ((", MuJoCo C with MJX's robot-robot contact gap" if a.c_gap else "")
            + (f", MuJoCo C at {it} / {ls} iterations (MuJoCo's defaults)" if a.c_defaults else ""))


def print_summary(field: str, values, width: int = 8) -> None:
    """One line of a column's spread: median, 99th percentile and maximum, in metres."""
    s = fidelity.summary(list(values))
    print(f"# {field:{width}s} median {s['median']:.2e}  p99 {s['p99']:.2e}  max {s['max']:.2e} m")


def write_rows(path: str, header: list, rows: list) -> None:
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([header, *rows])
    print(f"# per-robot rows written to {path}")


def merge(a: CheckSimConfig) -> None:
    header, rows = merge_slices(a.merge)
    col = {k: header.index(k) for k in header}
    alone = [r for r in rows if r[col["mjx_alone"]] != "nan"]
    print(f"# {len(a.merge)} slices: {len(alone)} of {len(rows)} robots run alone in MJX")
    for field in PADDED + ALONE:
        print_summary(field, (float(r[col[field]]) for r in rows), width=11)
    over = {}
    for field in ("error", "mjx_alone"):
        over[field] = [r for r in rows if float(r[col[field]]) > a.tolerance]
        names = ", ".join(f"{r[0]} ({float(r[col[field]]):.2e})" for r in over[field])
        print(f"# {field}: {len(over[field])} of {len(alone) if field in ALONE else len(rows)} over "
              f"{a.tolerance:g} m" + (f": {names}" if names else ""))
    if a.csv:
        write_rows(a.csv, header, rows)
    if over["error"]:           # as the check itself: padded robots over the tolerance make the exit status 1
        raise SystemExit(1)


def check(a: CheckSimConfig) -> None:
    if a.merge:
        return merge(a)
    if not a.set:
        raise ValueError("set: required, no value given (python -m experiments.check_sim SET ...)")
    rs = load_set(a.set)
    if a.mutated:
        robots = mutated_robots(rs.robots, a.mutated, seed=a.seed)
        rs = dataclasses.replace(rs, name=f"{rs.name} mutated x{a.mutated}", robots=tuple(robots))
    if a.num_robots > 0:
        rs = dataclasses.replace(rs, name=f"{rs.name}[:{a.num_robots}]", robots=tuple(rs.robots[:a.num_robots]))
    if a.task != "ft":
        return check_task(a, rs)
    if a.trace:
        raise ValueError(f"trace={a.trace}: needs task=incline, csr or obstacle (ft's check runs each robot alone)")
    alone = _range(a.unpadded_range, len(rs))
    if alone is not None and not a.unpadded_mjx:
        raise ValueError(f"unpadded_range={a.unpadded_range!r} needs unpadded_mjx=true")
    tree = build_shared_tree(rs.robots)
    print(f"# {rs.name}: shared tree of {tree.num_slots} bodies (nv {6 + 2 * tree.num_limb_slots}) "
          f"for {len(rs)} robots of at most {max(m.num_nodes for m in rs.robots)} bodies")
    opts0 = SolverOptions(iterations=a.iterations, ls_iterations=a.ls_iterations, self_collision=a.self_collision)
    summary = self_pair_summary(rs.robots, fidelity.FLOOR_WORLD, opts0, tree)
    if summary is not None:
        print("# " + summary.line(), flush=True)
    budget = dataclasses.replace(_ENV, flat_contact_budget=a.flat_contact_budget).contact_cap(uses_hfield=False)
    settings = [(a.iterations, a.ls_iterations)]
    if a.mujoco_defaults and fidelity.MUJOCO_SOLVER not in settings:
        settings.append(fidelity.MUJOCO_SOLVER)
    bad = 0
    rows = []
    fl = "float64" if a.x64 else "float32"
    for it, ls in settings:
        opts = SolverOptions(iterations=it, ls_iterations=ls, self_collision=a.self_collision, contact_budget=budget)
        t0 = time.time()
        print(f"# comparing {len(rs)} robots with MuJoCo C (solver iterations {it}, line search {ls}; compiling "
              "the stacked model takes a while)...", flush=True)
        res = fidelity.compare(rs.robots, opts, steps=a.steps, seed=a.seed, tree=tree,
                               floor_contacts=a.floor_contacts, matmul_precision=a.matmul_precision,
                               unpadded_mjx=a.unpadded_mjx, x64=a.x64, alone=alone, c_gap=a.c_gap,
                               c_defaults=a.c_defaults, linalg=a.linalg)
        print(f"# {rs.name}: {len(res)} robots, solver iterations {it}, line search {ls}, "
              f"self-collision {'on' if a.self_collision else 'off'}, floor {a.floor_contacts}, "
              f"contact budget {budget or 'none'}, {a.steps} control steps, "
              f"matmul precision {a.matmul_precision}, Cholesky {_cholesky(a.linalg)}, "
              f"MJX in {fl} on {jax.devices()[0].platform}"
              f"{_reference(a)} ({time.time() - t0:.0f} s)")
        fields = list(PADDED + (ALONE if a.unpadded_mjx else ()))
        print(" ".join([f"{'robot':40s}"] + [f"{f[:9]:>9s}" for f in fields]) + "   (m; error = padded MJX vs "
              "alone in MuJoCo C, padding = padded vs alone both in MuJoCo C, mjx = padded MJX vs padded MuJoCo C, "
              f"sensitivity = alone vs alone started {fidelity.PERTURBATION:g} away"
              + (f", padding_mjx = padded MJX vs alone in MJX, both {fl}, "
                 "mjx_alone = alone in MJX vs alone in MuJoCo C, "
                 f"mjx_ulp = alone in MJX vs itself started one {fl} ulp away)" if a.unpadded_mjx else ")"))
        for r in res:
            flag = "" if r.error <= a.tolerance else (
                "   OVER TOLERANCE (as sensitive on its own)" if r.sensitivity >= 0.1 * r.error else "   OVER TOLERANCE")
            print(" ".join([f"{r.name:40s}"] + [f"{getattr(r, f):9.2e}" for f in fields]) + flag)
        rows += [[r.name, it, ls, *(f"{getattr(r, f):.3e}" for f in fields)] for r in res]
        for field in fields:
            print_summary(field, (getattr(r, field) for r in res))
        most = max(res, key=lambda r: r.contacts)
        print(f"# contacts touching at once, each robot alone in MuJoCo C: median "
              f"{np.median([r.contacts for r in res]):g}, max {most.contacts} ({most.name}); a flat_contact_budget "
              f"of at least {most.contacts} keeps every force of these runs")
        worst = max(res, key=lambda r: r.error)
        over = [r for r in res if r.error > a.tolerance]
        print(f"# worst {worst.error:.2e} m ({worst.name}); {len(over)} of {len(res)} over {a.tolerance:g} m")
        bad += len(over)
    if a.csv:
        write_rows(a.csv, ["robot", "iterations", "ls_iterations", *fields], rows)
    if bad:
        raise SystemExit(1)


def check_task(a: CheckSimConfig, rs) -> None:
    """The padded comparison of `task` (the padding's own share is the floor check's: it does not depend on the
    terrain)."""
    opts = SolverOptions(iterations=a.iterations, ls_iterations=a.ls_iterations, self_collision=a.self_collision)
    t0 = time.time()
    on_hfield = get_task(a.task).uses_hfield
    ground = "the same height-field patches" if on_hfield else "MetaMorph's slab"
    print(f"# comparing {len(rs)} robots on {a.task} with MuJoCo C on {ground}...", flush=True)
    traced = _traced(a.trace, rs)
    fl = "float64" if a.x64 else "float32"
    res = fidelity.compare_task(rs.robots, a.task, opts, steps=a.steps, seed=a.seed, trace=traced, x64=a.x64,
                                c_gap=a.c_gap, c_defaults=a.c_defaults,
                                hfield_contacts=a.hfield_contacts,
                                hfield_contacts_per_geom=a.hfield_contacts_per_geom,
                                hfield_candidates=a.hfield_candidates,
                                contact_budget=a.contact_budget, flat_contact_budget=a.flat_contact_budget,
                                linalg=a.linalg)
    rule_detail = (f" ({a.hfield_contacts_per_geom} per geom, {a.hfield_candidates or 'all'} candidate prisms per "
                   "group)" if a.hfield_contacts == "mujoco" else "")
    budget = dataclasses.replace(_ENV, contact_budget=a.contact_budget,
                                 flat_contact_budget=a.flat_contact_budget).contact_cap(on_hfield)
    hfield = (f", height-field contacts {a.hfield_contacts}{rule_detail}" if on_hfield
              else ", MetaMorph's slab in MuJoCo C") + f", contact budget {budget or 'none'}" + _reference(a)
    print(f"# {rs.name} on {a.task}: {len(res)} robots, solver iterations {a.iterations}, line search "
          f"{a.ls_iterations}, {a.steps} control steps{hfield} "
          f"({time.time() - t0:.0f} s); mjx = padded MJX in {fl} vs padded MuJoCo C (float64), max body-position "
          f"error (m); first step over 1e-5 m; ulp = the same MJX run against itself started one {fl} ulp away; step = "
          "MuJoCo C restarted from MJX's state before each control step, against MJX's next state")
    for r in res:
        first = int(np.argmax(r.steps > 1e-5)) if (r.steps > 1e-5).any() else -1
        flag = "" if r.mjx <= a.tolerance else (
            "   OVER TOLERANCE (as far from one ulp)" if r.mjx_ulp >= 0.1 * r.mjx else "   OVER TOLERANCE")
        print(f"{r.name:40s} {r.mjx:9.2e}   {first:3d}   ulp {r.mjx_ulp:9.2e}   step {r.mjx_step:9.2e}{flag}")
    s = fidelity.summary([r.mjx for r in res])
    over = [r for r in res if r.mjx > a.tolerance]
    print(f"# mjx      median {s['median']:.2e}  p99 {s['p99']:.2e}  max {s['max']:.2e} m; {len(over)} of {len(res)} "
          f"over {a.tolerance:g} m")
    s = fidelity.summary([r.mjx_step for r in res])
    print(f"# step     median {s['median']:.2e}  p99 {s['p99']:.2e}  max {s['max']:.2e} m")
    for r in res:
        if r.contacts is not None:
            print_trace(r)
    if over:
        raise SystemExit(1)


def _traced(names: List[str], rs) -> List[str]:
    """The set's robot names that `trace` names (a name or its beginning, one robot each)."""
    out = []
    for n in names:
        hits = [m for m in rs.names if m.startswith(n)]
        if len(hits) != 1:
            found = f"{len(hits)}: {', '.join(hits[:5])}" if hits else "none"
            raise ValueError(f"trace={n!r}: expected the name (or its beginning) of one robot of {rs.name}; found "
                             f"{found}")
        out.append(hits[0])
    return out


def print_trace(r) -> None:
    """One traced robot step by step (`trace=`): mjx, ulp and step errors and MuJoCo C's contacts per substep (its
    own run / restarted from MJX's state), then at the step of the largest step error each substep's contacts
    (distance, geoms), those one side has and the other not marked *."""
    print(f"# trace {r.name}: control step, mjx, ulp, step (m); MuJoCo C's contacts after each substep, run / "
          "restart")
    worst = int(np.argmax(r.step_steps))
    for t in range(len(r.steps)):
        run, restart = (",".join(str(int(n)) for n in r.ncon[t, i]) for i in (0, 1))
        mark = "   <- largest step error" if t == worst else ""
        print(f"  {t:3d}  {r.steps[t]:9.2e}  {r.ulp_steps[t]:9.2e}  {r.step_steps[t]:9.2e}   {run:>12s} / "
              f"{restart:<12s}{mark}")
    print(f"# trace {r.name}: MuJoCo C's contacts at control step {worst} (distance m, geom x geom; * = a pair only one "
          "side has, or has more of)")
    for k, (run, restart) in enumerate(zip(*r.contacts[worst])):
        for label, mine, other in (("run    ", run, restart), ("restart", restart, run)):
            mine_pairs, other_pairs = [c[1:] for c in mine], [c[1:] for c in other]
            cells = [f"{dist:.2e} {g1} x {g2}{'*' if mine_pairs.count((g1, g2)) > other_pairs.count((g1, g2)) else ''}"
                     for dist, g1, g2 in mine]
            print(f"  substep {k} {label} ({len(mine)}): {'; '.join(cells)}")


def main(argv=None) -> int:
    return cli.main(check, "check_sim_schema", CheckSimConfig, __doc__, argv, positional="set")


if __name__ == "__main__":
    sys.exit(main())
