"""Tests run in float64 so gradient checks against finite differences are meaningful.

Forward accuracy in float32 is tested explicitly where it matters (`dtype` arguments,
`jnp.float32`).

Most of the suite's time is XLA compilation, and many tests compile the same programs (the same
defocus or fit at the same shapes from separate closures, pytest-xdist workers, or the
subprocesses of the data_gen and sharding tests). JAX's persistent compilation cache lets them
share one compilation: it is keyed by the program, the JAX version and the compile options, so a
hit is the same executable. It is set through the environment too, so subprocesses use it. Set
`DOFJAX_TEST_JAX_CACHE` to a directory to choose where it lives, or to "" to turn it off.
"""

import getpass
import os
import tempfile

import jax

jax.config.update("jax_enable_x64", True)


def _user() -> str:
    """The login name for the cache directory's name (os.getuid does not exist on Windows)."""
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (some containers)
        return "user"


_CACHE = os.environ.get(
    "DOFJAX_TEST_JAX_CACHE",
    os.path.join(tempfile.gettempdir(), f"dofjax-test-jax-cache-{_user()}"))
if _CACHE:
    _settings = {"jax_compilation_cache_dir": _CACHE,
                 "jax_persistent_cache_min_compile_time_secs": 0.2,
                 "jax_persistent_cache_min_entry_size_bytes": 0}
    for name, value in _settings.items():
        jax.config.update(name, value)
        os.environ.setdefault(name.upper(), str(value))
