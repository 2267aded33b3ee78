"""Find the physics a model is missing: residual, attribution, augmentation, report.

The measured motion `x(t)` of a constrained mechanism obeys `M xdd = f(x, xd, u) + DPhi^T lambda + F`,
where `F` is whatever the model does not contain. Along the constraint manifold, in the joint-space
basis `G = dx/dq`, `r = G^T (M xdd - f) = G^T F`: a generalised force per joint that the data
determine. Every candidate effect (one `AbstractEffect` per file here) is a force linear in its
parameters, so attribution is a sparse, sign-constrained linear regression of `r` on the candidates'
features, with a bootstrap over whole runs for the uncertainty. Detected effects are added to the model
as cldyn terms, the model is refitted, and the loop repeats until nothing passes.

Layout: `base` (the effect interface), one module per effect, `library` (the default effects),
`smoothing` and `choice` (its settings, chosen from the data), `residual` (the weak form), `adequacy`
(what the data can support), `limits` (samples at joint limits), `regression`, `refit`, `errors`
(before/after), `identify` (the loop), `result` and `report`;
`balance` (the energy balance, a check beside the loop that conservative model errors cannot fake).
"""

from .actuator_gain import ActuatorGainEffect as ActuatorGainEffect
from .balance import EnergyBalance as EnergyBalance, energy_balance as energy_balance
from .base import AbstractEffect as AbstractEffect, Candidate as Candidate, Context as Context
from .choice import estimate_noise as estimate_noise
from .identify import identify as identify
from .joint_armature import JointArmatureEffect as JointArmatureEffect
from .joint_coulomb import JointCoulombEffect as JointCoulombEffect
from .joint_damping import JointDampingEffect as JointDampingEffect
from .joint_quadratic_damping import JointQuadraticDampingEffect as JointQuadraticDampingEffect
from .joint_spring import JointSpringEffect as JointSpringEffect
from .keypoint_drag import KeypointDragEffect as KeypointDragEffect
from .library import EFFECTS as EFFECTS
from .point_mass import PointMassEffect as PointMassEffect
from .refit import augment as augment
from .regression import Criteria as Criteria
from .result import (
    Adequacy as Adequacy,
    Detection as Detection,
    Errors as Errors,
    Identification as Identification,
)
from .smoothing import Smoothing as Smoothing, SmoothingChoice as SmoothingChoice
