"""`cldyn.mujoco` needs the `[mujoco]` extra: imported first, so that without it the error names the
extra to install rather than a bare `No module named 'mujoco'` from whichever submodule came first."""

from .._misc import optional_import

optional_import("mujoco", purpose="cldyn.mujoco")
