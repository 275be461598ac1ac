"""JAX's persistent compilation cache for the command-line tools (`compile_cache=` of run / evaluate / study)."""
from __future__ import annotations

from pathlib import Path

import jax

#: where compiled programs are kept unless a config says otherwise: $MJX_MORPH_XLA_CACHE, else ~/.cache/mjx_morph/xla
DEFAULT_COMPILE_CACHE = "${oc.env:MJX_MORPH_XLA_CACHE,'~/.cache/mjx_morph/xla'}"


def use_compile_cache(path: str | Path | None, min_compile_s: float = 2.0) -> Path | None:
    """Keep compiled XLA programs in `path` across processes, so a resumed run or a second evaluation skips most
    compilation (docs/benchmarks.md has the measured gain). Must run before the first compilation of the process;
    None or "" leaves the cache off."""
    if not path:
        return None
    p = Path(path).expanduser()
    p.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(p))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    return p
