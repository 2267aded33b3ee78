"""The MuJoCo bridge: record trajectories from MJCF scenes, turn planar MJCF models into cldyn systems,
KeyCLD's scene variants, and validation of the one against the other.

Needs the `mujoco` extra (`pip install 'cldyn[mujoco]'`); `import cldyn` never imports it.
"""

from . import _extra as _extra
from ._bridge import MujocoModel as MujocoModel, from_mjcf as from_mjcf
from ._control import closed_loop as closed_loop, plot_swing_up as plot_swing_up, swing_up as swing_up
from ._datasets import (
    keycld_dataset as keycld_dataset,
    keycld_origin as keycld_origin,
    keycld_recording as keycld_recording,
)
from ._identify import identify_recording as identify_recording, modify_scene as modify_scene
from ._record import record as record
from ._scenes import keycld_scene as keycld_scene, scene_xml as scene_xml
from ._validate import validate as validate
