"""What the command-line tools share: composing a config from `key=value` arguments, `--help`, the compile cache,
and one way to report a user's mistake (`error: ...` on one line, exit status 2, no traceback)."""
from __future__ import annotations

import sys
from typing import Any, Callable, Sequence

from omegaconf import OmegaConf

from mjx_morph.run import ConfigError, RunDirError, compose, use_compile_cache
from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.render import RenderUnavailable

#: exceptions that are the user's to fix: reported as one line, never as a traceback
USER_ERRORS = (ConfigError, RunDirError, RobotError, RenderUnavailable, ValueError, FileNotFoundError)


def fail(message: Any) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def guarded(fn: Callable[[], Any]) -> int:
    """Run `fn`; a user error becomes `error: ...` and status 2, Ctrl-C status 130."""
    try:
        fn()
    except USER_ERRORS as e:
        return fail(e)
    except KeyboardInterrupt:
        return 130
    return 0


def main(run: Callable[[Any], Any], config_name: str, schema: type, doc: str | None = None,
         argv: Sequence[str] | None = None, positional: str | None = None) -> int:
    """Compose `config_name` (a YAML file of experiments/conf or a registered schema) with `argv` as `key=value`
    overrides into a `schema` instance, turn on its compile cache if it has one, and call `run(cfg)`.
    `positional`: the key that a first argument without `=` sets (`check_sim unimal100/train`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if positional and argv and "=" not in argv[0] and not argv[0].startswith("-"):
        argv[0] = f"{positional}={argv[0]}"
    if argv and argv[0] in ("-h", "--help"):
        print((doc or "").strip() + "\n\nKeys and defaults (override with key=value):\n")
        print(OmegaConf.to_yaml(OmegaConf.structured(schema)))
        return 0

    def go():
        cfg = compose(config_name, argv, schema)
        if getattr(cfg, "compile_cache", None):
            use_compile_cache(cfg.compile_cache)
        run(cfg)
    return guarded(go)
