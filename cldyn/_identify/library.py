"""The effect library: the effects `identify` considers by default, in the order of preference
(where the data cannot tell candidates apart, the earliest represents them)."""

from collections.abc import Sequence

from .actuator_gain import ActuatorGainEffect
from .base import AbstractEffect
from .joint_armature import JointArmatureEffect
from .joint_coulomb import JointCoulombEffect
from .joint_damping import JointDampingEffect
from .joint_quadratic_damping import JointQuadraticDampingEffect
from .joint_spring import JointSpringEffect
from .keypoint_drag import KeypointDragEffect
from .point_mass import PointMassEffect

EFFECTS: tuple[AbstractEffect, ...] = (
    JointDampingEffect(),
    JointCoulombEffect(),
    JointSpringEffect(),
    JointArmatureEffect(),
    ActuatorGainEffect(),
    JointQuadraticDampingEffect(),
    KeypointDragEffect(),
    PointMassEffect(),
)
"""The effect library, in order of preference; `effect.name` is the name in reports."""


def resolve(effects: Sequence["AbstractEffect | str"]) -> tuple[AbstractEffect, ...]:
    """Effects given as objects or by the names of the library's effects, checked for duplicates."""
    library = {e.name: e for e in EFFECTS}
    out = []
    for effect in effects:
        if isinstance(effect, str):
            if effect not in library:
                raise ValueError(f"unknown effect {effect!r}; the library has {list(library)}")
            effect = library[effect]
        elif not isinstance(effect, AbstractEffect):
            raise TypeError(f"effects must be AbstractEffects or their names, got {type(effect).__name__}")
        out.append(effect)
    names = [e.name for e in out]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"effects named more than once: {repeated}")
    return tuple(out)
