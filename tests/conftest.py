import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax

# Physics tests compare against independent derivations to 1e-9 and better: float64 throughout.
# Tests that exercise float32 training cast explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
