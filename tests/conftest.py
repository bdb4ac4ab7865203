"""Tests run in float64 so gradient checks against finite differences are meaningful.

Forward accuracy in float32 is tested explicitly where it matters (`dtype` arguments,
`jnp.float32`).

JAX's persistent compilation cache is off by default: on the CPU backend of the pinned jaxlib,
writing or reading one of its entries from two pytest-xdist workers at once has aborted a worker
(SIGABRT in `put_executable_and_time`, SIGSEGV in `get_executable_and_time`). Set
`DOFJAX_TEST_JAX_CACHE` to a directory to use one anyway (subprocesses inherit it).
"""

import os

import jax

jax.config.update("jax_enable_x64", True)


_CACHE = os.environ.get("DOFJAX_TEST_JAX_CACHE", "")
# the command-line tools the tests run (in this process or as subprocesses) use the same setting
# instead of their default cache directory
os.environ["DOFJAX_JAX_CACHE"] = _CACHE
if _CACHE:
    _settings = {"jax_compilation_cache_dir": _CACHE,
                 "jax_persistent_cache_min_compile_time_secs": 0.2,
                 "jax_persistent_cache_min_entry_size_bytes": 0}
    for name, value in _settings.items():
        jax.config.update(name, value)
        os.environ.setdefault(name.upper(), str(value))
