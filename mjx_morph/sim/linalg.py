"""Which Cholesky factorisation and solve MJX uses (`EnvConfig.linalg`), and the one place MJX is given them.

MJX factors and solves with `jax.scipy.linalg.cho_factor` / `cho_solve`, looked up through the `jax` name of three
of its modules (smooth: the mass matrix, solver: the Newton Hessian, forward: the implicit integrator). `install()`,
called once when `mjx_morph.sim` is imported, gives those three modules a view of `jax` that is `jax` itself except
for these two functions, which pick, each time MJX calls them (that is, while a step is traced), the
implementation of the innermost `use(name)` block being traced:
    "auto"    the default, also outside any block: "pallas" where the default backend is a GPU, "jax" elsewhere
              (`resolve`; on a CPU the kernels would run interpreted, far slower than the loops). Measured on an
              H200 (docs/benchmarks.md, sessions 61-62): pallas is 15% faster on the 64- and 256-env rollouts, a
              tie at 1,024, MuJoCo C agrees as closely (check_sim), and an R-MoMo seed trained on it learned no worse
              than the two on jax (docs/results-log.md, session 62). At 2,048 and 4,096 matrices a call they are 10%
              and 6% slower (bench_cholesky, session 63; the variants sweep runs chunks of 4,800); kept there too:
              the choice is made per trace, where MJX's vmap hides the batch, and the Cholesky is part of a step;
    "jax"     JAX's own functions (cuSOLVER / cuBLAS on a GPU); on a CPU with jaxlib < 0.11 the pure-JAX loops of
              cpu_linalg.py instead (a deadlock of those jaxlibs' batched LAPACK calls under MJX);
    "pallas"  gpu_linalg.py: one fused Pallas kernel per factorisation and one per solve (Triton on a GPU, the
              same kernels interpreted as plain JAX on a CPU, which is how the tests check them).
An env traces all its MJX calls inside `UnimalEnv.physics()`, which enters `use(config.linalg)`, so two envs of
one process with different settings each trace their own (as the floor-contact rules, contact.py). The choice is
made while tracing, not when a compiled program runs: a function jitted once and called again inside another
block reuses the program it compiled first (JAX's jit cache does not see the block), which no env does (each env
jits its own methods). Everything else in MJX and in the process sees `jax` unchanged.
"""
from __future__ import annotations

import contextlib
import contextvars
import types
from typing import Callable, Iterator, Tuple

import jax

from . import cpu_linalg

CHOICES = ("auto", "jax", "pallas")
DEFAULT = "auto"
_CHOICE = contextvars.ContextVar("mjx_morph_linalg", default=DEFAULT)
#: MJX's modules that factor or solve with Cholesky (mujoco-mjx 3.17.0)
MJX_MODULES = ("forward", "smooth", "solver")
_INSTALLED = False


def check(name: str) -> str:
    """`name` if it is a known choice (and, where it means "pallas", Pallas imports); a ValueError naming the key
    otherwise."""
    if name not in CHOICES:
        raise ValueError(f"env.linalg={name!r}: expected one of {', '.join(CHOICES)} (MJX's Cholesky factor and "
                         "solve: auto, the kernels on a GPU and JAX's own elsewhere; JAX's own; or the fused Pallas "
                         "kernels of mjx_morph/sim/gpu_linalg.py)")
    if resolve(name) == "pallas":
        from . import gpu_linalg  # noqa: F401  (fails here, at the env's build, where Pallas does not import)
    return name


def resolve(name: str) -> str:
    """The implementation `name` stands for now: "auto" is "pallas" where JAX's default backend is a GPU, else
    "jax"; the others stand for themselves. Called while tracing, as `functions` is."""
    if name == "auto":
        return "pallas" if jax.default_backend() == "gpu" else "jax"
    return name


@contextlib.contextmanager
def use(name: str) -> Iterator[None]:
    """Trace the MJX calls inside this block with the Cholesky of `name` (one of CHOICES)."""
    token = _CHOICE.set(check(name))
    try:
        yield
    finally:
        _CHOICE.reset(token)


def current() -> str:
    """The choice of the innermost `use` block (DEFAULT outside any), as given: `resolve` it for the
    implementation."""
    return _CHOICE.get()


def functions(name: str | None = None) -> Tuple[Callable, Callable]:
    """(cho_factor, cho_solve) that MJX gets for `name` (default: the current block's), decided now: call it while
    tracing, since "auto" and "jax" look at the default backend."""
    name = resolve(check(current() if name is None else name))
    if name == "pallas":
        from . import gpu_linalg
        return gpu_linalg.cho_factor, gpu_linalg.cho_solve
    return cpu_linalg.default_functions()


def _cho_factor(a, lower=False, overwrite_a=False, check_finite=True):
    return functions()[0](a, lower=lower, overwrite_a=overwrite_a, check_finite=check_finite)


def _cho_solve(c_and_lower, b, overwrite_b=False, check_finite=True):
    return functions()[1](c_and_lower, b, overwrite_b=overwrite_b, check_finite=check_finite)


class _View(types.ModuleType):
    """A module `base` with some attributes replaced; every other attribute is looked up in `base`."""

    def __init__(self, base, **replaced):
        super().__init__(base.__name__)
        self.__dict__.update(replaced)
        self.__dict__["_base"] = base

    def __getattr__(self, name):            # only for names not replaced
        return getattr(self.__dict__["_base"], name)


def view() -> types.ModuleType:
    """`jax` as MJX's Cholesky users see it after `install()`."""
    linalg = _View(jax.scipy.linalg, cho_factor=_cho_factor, cho_solve=_cho_solve)
    return _View(jax, scipy=_View(jax.scipy, linalg=linalg))


def install() -> None:
    """Give MJX's Cholesky users the view (idempotent; done at import of mjx_morph.sim)."""
    global _INSTALLED
    if _INSTALLED:
        return
    import importlib
    v = view()
    for name in MJX_MODULES:
        importlib.import_module(f"mujoco.mjx._src.{name}").jax = v
    _INSTALLED = True
