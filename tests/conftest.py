"""Tests run in float64 so gradient checks against finite differences are meaningful.

Forward accuracy in float32 is tested explicitly where it matters (`dtype` arguments, `jnp.float32`).
"""

import jax

jax.config.update("jax_enable_x64", True)
