import os
import tempfile

os.environ.setdefault("MUJOCO_GL", "egl")

import jax

# Physics tests compare against independent derivations to 1e-9 and better: float64 throughout.
# Tests that exercise float32 training cast explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# Compiled programs are shared between the pytest-xdist workers (and later runs) through JAX's
# persistent cache; compilation is most of the suite's time on two cores.
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), "cldyn-jax-cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
