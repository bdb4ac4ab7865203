"""JAX's persistent compilation cache for dofjax's command-line tools.

Most of a command's first fit or render is XLA compilation. JAX can keep compiled programs on disk,
keyed by the program, the JAX version and the compile options, so a later process with the same
shapes and settings loads the same executable instead of compiling it again (what remains is
tracing; docs/performance.md, "The persistent compilation cache"). The library itself never changes
JAX's configuration; the command-line tools (`dofjax`, `python -m fit.*`, `python -m data_gen`)
call `use_compilation_cache` at start-up.
"""

from __future__ import annotations

import os
import sys
import warnings

ENV = "DOFJAX_JAX_CACHE"


def default_cache_dir() -> str:
    """`$XDG_CACHE_HOME/dofjax/jax`, or `~/.cache/dofjax/jax`."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "dofjax", "jax")


def use_compilation_cache(directory: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache for this process; return its directory.

    Args:
        directory: where compiled programs are kept. None: the `DOFJAX_JAX_CACHE` environment
            variable if set, else a cache directory JAX was already given (e.g. by
            `JAX_COMPILATION_CACHE_DIR`), else `default_cache_dir()`. An empty string (as
            argument or in `DOFJAX_JAX_CACHE`) turns the cache off and returns None.

    Only programs that took at least a second to compile are written (JAX's default), so the
    cache holds the renders, defocus passes and fits, a few MB each.

    Raises:
        OSError: a directory that was asked for (argument or environment) cannot be created;
            when the default one cannot (a read-only home), a warning says so and the cache
            stays off.
    """
    import jax

    asked = directory is not None or os.environ.get(ENV) is not None
    if directory is None:
        directory = os.environ.get(ENV)
    if directory is None:
        directory = jax.config.jax_compilation_cache_dir or default_cache_dir()
    if not directory:
        return None
    directory = os.path.abspath(os.path.expanduser(directory))
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as exc:
        message = (f"JAX compilation cache: cannot create directory {directory!r}: "
                   f"{exc.strerror or exc}")
        if asked:
            raise OSError(message) from exc
        warnings.warn(message + "; compiling without it", RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", directory)
    return directory


def use_in_script(prog: str, directory: str | None) -> str | None:
    """`use_compilation_cache` for a script: a directory that cannot be created ends it with a
    one-line message naming `prog` on stderr (instead of a traceback) and exit status 2."""
    try:
        return use_compilation_cache(directory)
    except OSError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def add_argument(parser) -> None:
    """The `--jax-cache DIR` option every command-line tool shares."""
    parser.add_argument(
        "--jax-cache", default=None, metavar="DIR",
        help=f"JAX persistent compilation cache: later runs load compiled programs instead of "
        f"compiling them again (default: ${ENV}, else $JAX_COMPILATION_CACHE_DIR, else "
        f"{default_cache_dir()}; '' turns it off)")
