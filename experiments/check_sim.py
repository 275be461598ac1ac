"""Fidelity check of the padded, stacked MJX simulation against each robot alone in MuJoCo C.

    python -m experiments.check_sim unimal100/train                 # default solver settings (5 / 8)
    python -m experiments.check_sim unimal100/test --defaults       # MuJoCo's defaults (100 / 50) too
    python -m experiments.check_sim gen/train --iterations 100 --ls-iterations 50 --steps 25

Prints the worst body-position error (m) per robot over `--steps` control steps (same start state and actions in
both, see mjx_morph/sim/fidelity.py) and exits 1 when any robot is over the tolerance (1e-3 m by default).
"""
from __future__ import annotations

import argparse
import sys
import time

from mjx_morph.sim import fidelity
from mjx_morph.sim.padding import SolverOptions
from mjx_morph.sim.supertree import build_shared_tree
from mjx_morph.unimal.sets import load_set


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("set", help="robot set name or path (unimal100/train, gen/train, a folder, ...)")
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--ls-iterations", type=int, default=8)
    p.add_argument("--defaults", action="store_true", help="also check at MuJoCo's defaults (100 / 50)")
    p.add_argument("--self-collision", action="store_true")
    p.add_argument("--steps", type=int, default=25)
    p.add_argument("--tolerance", type=float, default=fidelity.TOLERANCE)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    rs = load_set(a.set)
    tree = build_shared_tree(rs.robots)
    print(f"# {rs.name}: shared tree of {tree.num_slots} bodies (nv {6 + 2 * tree.num_limb_slots}) "
          f"for {len(rs)} robots of at most {max(m.num_nodes for m in rs.robots)} bodies")
    settings = [(a.iterations, a.ls_iterations)]
    if a.defaults and (100, 50) not in settings:
        settings.append((100, 50))
    bad = 0
    for it, ls in settings:
        opts = SolverOptions(iterations=it, ls_iterations=ls, self_collision=a.self_collision)
        t0 = time.time()
        res = fidelity.compare(rs.robots, opts, steps=a.steps, seed=a.seed, tree=tree)
        print(f"# {rs.name}: {len(res)} robots, solver iterations {it}, line search {ls}, "
              f"self-collision {'on' if a.self_collision else 'off'}, {a.steps} control steps "
              f"({time.time() - t0:.0f} s)")
        for r in res:
            flag = "" if r.error <= a.tolerance else "   OVER TOLERANCE"
            print(f"{r.name:40s} {r.error:.2e}{flag}")
        worst = max(res, key=lambda r: r.error)
        over = [r for r in res if r.error > a.tolerance]
        print(f"# worst {worst.error:.2e} m ({worst.name}); {len(over)} over {a.tolerance:g} m")
        bad += len(over)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
