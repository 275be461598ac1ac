"""Which Cholesky factorisation and solve MJX uses (`EnvConfig.linalg`), and the one place MJX is given them.

MJX factors and solves with `jax.scipy.linalg.cho_factor` / `cho_solve`, looked up through the `jax` name of three
of its modules (smooth: the mass matrix, solver: the Newton Hessian, forward: the implicit integrator). `install()`,
called once when `mjx_morph.sim` is imported, gives those three modules a view of `jax` that is `jax` itself except
for these two functions, which pick, each time MJX calls them (that is, while a step is traced), the
implementation of the innermost `use(name)` block being traced:
    "jax"     JAX's own functions (the default, also outside any block); on a CPU with jaxlib < 0.11 the pure-JAX
              loops of cpu_linalg.py instead (a deadlock of those jaxlibs' batched LAPACK calls under MJX);
    "pallas"  gpu_linalg.py: one fused Pallas kernel per factorisation and one per solve (Triton on a GPU, the
              same kernels interpreted as plain JAX on a CPU). Not yet measured on a GPU: opt in.
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

CHOICES = ("jax", "pallas")
_CHOICE = contextvars.ContextVar("mjx_morph_linalg", default="jax")
#: MJX's modules that factor or solve with Cholesky (mujoco-mjx 3.17.0)
MJX_MODULES = ("forward", "smooth", "solver")
_INSTALLED = False


def check(name: str) -> str:
    """`name` if it is a known choice (and, for "pallas", Pallas imports); a ValueError naming the key otherwise."""
    if name not in CHOICES:
        raise ValueError(f"env.linalg={name!r}: expected one of {', '.join(CHOICES)} (MJX's Cholesky factor and "
                         "solve: JAX's own, or the fused Pallas kernels of mjx_morph/sim/gpu_linalg.py)")
    if name == "pallas":
        from . import gpu_linalg  # noqa: F401  (fails here, at the env's build, where Pallas does not import)
    return name


@contextlib.contextmanager
def use(name: str) -> Iterator[None]:
    """Trace the MJX calls inside this block with the Cholesky of `name` ("jax" or "pallas")."""
    token = _CHOICE.set(check(name))
    try:
        yield
    finally:
        _CHOICE.reset(token)


def current() -> str:
    """The choice of the innermost `use` block ("jax" outside any)."""
    return _CHOICE.get()


def functions(name: str | None = None) -> Tuple[Callable, Callable]:
    """(cho_factor, cho_solve) that MJX gets for `name` (default: the current block's), decided now: call it while
    tracing, since the "jax" choice looks at the default backend."""
    name = check(current() if name is None else name)
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
