"""Robot sets on the command line.

    python -m experiments.robots info SET_OR_PATH          table of the robots and totals
    python -m experiments.robots validate PATH             one line per problem, non-zero exit if any
    python -m experiments.robots validate PATH --allow-outside-design-space   ... values beyond the design space
                                                           are warnings (exit 0)
    python -m experiments.robots generate --out DIR --num N --seed S
    python -m experiments.robots variants SET --out DIR    the 24 dynamics/kinematics variants per robot
    python -m experiments.robots export PATH --out FILE    the project's MJCF for one robot
    python -m experiments.robots gallery SET --out FILE.png

SET is a named set (unimal100/train, unimal100/test, unimal100/val, unimal100/test70, gen/train, gen/test,
<set>/variants) or a path (MetaMorph folder, folder of XML files, one XML file); see mjx_morph.unimal.sets.
User errors (bad files, unknown sets, no OpenGL backend) print one message and exit with status 2, without a
traceback. Robots with values far beyond the UNIMAL design space (a 50 m limb, a gear of 1e6: the bounds of
mjx_morph.unimal.design_space) are refused by every command, and reported by `validate`, unless the command is
given --allow-outside-design-space.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.mjcf import save_set, to_mjcf
from mjx_morph.unimal.render import RenderUnavailable, check_gl, render_robots
from mjx_morph.unimal.sets import load_set
from mjx_morph.unimal.validate import validate_path

from .cli import fail


def cmd_info(args) -> int:
    rs = load_set(args.set, args.root, allow_outside_design_space=args.allow_outside_design_space)
    rows = [(m.name, m.num_limbs, m.dof, m.total_mass, m.tree_depth, m.height) for m in rs.robots]
    width = max(len("robot"), *(len(r[0]) for r in rows))
    print(f"{'robot':<{width}}  limbs  joints  mass(kg)  depth  height(m)")
    for name, limbs, dof, mass, depth, height in rows:
        print(f"{name:<{width}}  {limbs:>5}  {dof:>6}  {mass:>8.2f}  {depth:>5}  {height:>9.2f}")
    a = np.array([r[1:] for r in rows], dtype=float)
    print(f"{len(rows)} robots from {rs.source}")
    for col, label in enumerate(("limbs", "joints", "mass (kg)", "depth", "height (m)")):
        print(f"  {label:<10} min {a[:, col].min():7.2f}  mean {a[:, col].mean():7.2f}  max {a[:, col].max():7.2f}"
              f"  total {a[:, col].sum():9.2f}")
    return 0


def cmd_validate(args) -> int:
    problems, warnings, outside = validate_path(args.path,
                                                allow_outside_design_space=args.allow_outside_design_space)
    for p in problems:
        print(p)
    for w in warnings:
        print(f"warning: {w}")
    if problems:
        hint = ("; values outside the UNIMAL design space are accepted with --allow-outside-design-space"
                if outside and not warnings else "")
        print(f"{len(problems)} problem(s){hint}", file=sys.stderr)
        return 1
    print(f"{args.path}: ok" + (f" ({len(warnings)} warning(s))" if warnings else ""))
    return 0


def cmd_generate(args) -> int:
    from mjx_morph.unimal.generator import generate_set
    robots = generate_set(args.num, args.seed)
    save_set(robots, args.out)
    print(f"wrote {len(robots)} robots to {args.out} (seed {args.seed})")
    return 0


def cmd_variants(args) -> int:
    from mjx_morph.unimal.variants import CHANGE_TYPES, make_variants
    rs = load_set(args.set, args.root, allow_outside_design_space=args.allow_outside_design_space)
    types = tuple(args.types.split(",")) if args.types else CHANGE_TYPES
    bad = [t for t in types if t not in CHANGE_TYPES]
    if bad:
        raise RobotError("--types", "", f"unknown change type(s) {bad}; expected some of {', '.join(CHANGE_TYPES)}")
    robots = make_variants(rs.robots, per_type=args.per_type, seed=args.seed, types=types)
    save_set(robots, args.out)
    print(f"wrote {len(robots)} variants of {len(rs)} robots to {args.out}")
    return 0


def cmd_export(args) -> int:
    rs = load_set(args.path, args.root, allow_outside_design_space=args.allow_outside_design_space)
    if len(rs) != 1:
        raise RobotError(args.path, "", f"export takes one robot; this is a set of {len(rs)}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(to_mjcf(rs.robots[0], floor=args.floor))
    print(f"wrote {out}")
    return 0


def cmd_gallery(args) -> int:
    check_gl()                                # no OpenGL backend: say so before reading anything
    rs = load_set(args.set, args.root, allow_outside_design_space=args.allow_outside_design_space)
    robots = rs.robots[: args.max]
    images = render_robots(robots, size=args.size)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = min(args.cols, len(images))
    rows = math.ceil(len(images) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.4 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, img, m in zip(axes.flat, images, robots):
        ax.imshow(img)
        ax.set_title(f"{m.name}\n{m.num_limbs} limbs, {m.dof} dof", fontsize=6)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    print(f"wrote {out} ({len(images)} robots)")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.robots", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default=None, help="folder of the original unimals_100 robots "
                   "(default: $MJX_MORPH_UNIMALS, else ../shared/unimals_100)")
    sub = p.add_subparsers(dest="cmd", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--allow-outside-design-space", action="store_true",
                        help="accept robots with values far beyond the UNIMAL design space (validate: report them "
                             "as warnings and exit 0); see mjx_morph.unimal.design_space for the bounds")
    s = sub.add_parser("info", help="table of the robots of a set", parents=[common])
    s.add_argument("set")
    s.set_defaults(fn=cmd_info)
    s = sub.add_parser("validate", help="check every robot file of a folder (or one file)",
                       parents=[common])
    s.add_argument("path")
    s.set_defaults(fn=cmd_validate)
    s = sub.add_parser("generate", help="write a new set of generated robots in MetaMorph format")
    s.add_argument("--out", required=True)
    s.add_argument("--num", type=int, default=100)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(fn=cmd_generate)
    s = sub.add_parser("variants", help="write dynamics/kinematics variants of a set", parents=[common])
    s.add_argument("set")
    s.add_argument("--out", required=True)
    s.add_argument("--per-type", type=int, default=4)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--types", default=None, help="comma-separated change types (default: all six)")
    s.set_defaults(fn=cmd_variants)
    s = sub.add_parser("export", help="write the project's MJCF for one robot", parents=[common])
    s.add_argument("path")
    s.add_argument("--out", required=True)
    s.add_argument("--floor", action="store_true", help="add a ground plane at z = 0")
    s.set_defaults(fn=cmd_export)
    s = sub.add_parser("gallery", help="a grid of rendered robots (needs an OpenGL backend)",
                       parents=[common])
    s.add_argument("set")
    s.add_argument("--out", required=True)
    s.add_argument("--max", type=int, default=100, help="at most this many robots")
    s.add_argument("--cols", type=int, default=10)
    s.add_argument("--size", type=int, default=240, help="pixels per image")
    s.set_defaults(fn=cmd_gallery)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.fn(args)
    except (RobotError, RenderUnavailable, OSError) as e:
        return fail(e)


if __name__ == "__main__":
    sys.exit(main())
