"""cldyn: constrained Lagrangian dynamics in Cartesian keypoint coordinates.

An implementation of the dynamics of KeyCLD (Daems et al., "Learning Constrained Lagrangian Dynamics
in Keypoint Coordinates from Images") in JAX and Equinox.
"""

import importlib.metadata

from . import systems as systems
from ._baselines import SecondOrderNeuralODE as SecondOrderNeuralODE
from ._batching import (
    AbstractBatching as AbstractBatching,
    Runs as Runs,
    Windows as Windows,
)
from ._checkpoint import CheckpointError as CheckpointError
from ._consistency import (
    ConstraintCheck as ConstraintCheck,
    ConstraintViolation as ConstraintViolation,
    check_constraints as check_constraints,
)
from ._constraint import (
    AbstractConstraint as AbstractConstraint,
    Anchor as Anchor,
    Distance as Distance,
    FixedCoordinate as FixedCoordinate,
    FromFunction as FromFunction,
    LinearConstraint as LinearConstraint,
    Stack as Stack,
)
from ._control import (
    AbstractControl as AbstractControl,
    AbstractDampingInjection as AbstractDampingInjection,
    ConstantControl as ConstantControl,
    EnergyShaping as EnergyShaping,
    FeedbackControl as FeedbackControl,
    KeypointDampingInjection as KeypointDampingInjection,
    OutputDampingInjection as OutputDampingInjection,
    TimeVaryingControl as TimeVaryingControl,
    ZeroOrderHold as ZeroOrderHold,
)
from ._coordinates import (
    AbstractCoordinate as AbstractCoordinate,
    HingeAngle as HingeAngle,
    JointMap as JointMap,
    SliderPosition as SliderPosition,
    wrap_angle as wrap_angle,
)
from ._data import (
    Sequences as Sequences,
    central_difference as central_difference,
)
from ._dissipation import (
    AbstractDissipation as AbstractDissipation,
    DissipationSum as DissipationSum,
    JointCoulomb as JointCoulomb,
    JointDamping as JointDamping,
    JointQuadraticDamping as JointQuadraticDamping,
    KeypointDrag as KeypointDrag,
)
from ._evaluate import (
    Evaluation as Evaluation,
    evaluate as evaluate,
    geometric_mean_relative_error as geometric_mean_relative_error,
    keypoint_error as keypoint_error,
    range_of_motion as range_of_motion,
    relative_error as relative_error,
    rollout as rollout,
    rollout_energy as rollout_energy,
    valid_prediction_time as valid_prediction_time,
)
from ._fit import (
    FitResult as FitResult,
    NonFiniteLossError as NonFiniteLossError,
    fit as fit,
    load_fit as load_fit,
)
from ._identify import (
    EFFECTS as EFFECTS,
    AbstractEffect as AbstractEffect,
    ActuatorGainEffect as ActuatorGainEffect,
    Adequacy as Adequacy,
    Candidate as Candidate,
    Criteria as Criteria,
    Detection as Detection,
    EnergyBalance as EnergyBalance,
    Errors as Errors,
    Identification as Identification,
    JointArmatureEffect as JointArmatureEffect,
    JointCoulombEffect as JointCoulombEffect,
    JointDampingEffect as JointDampingEffect,
    JointQuadraticDampingEffect as JointQuadraticDampingEffect,
    JointSpringEffect as JointSpringEffect,
    KeypointDragEffect as KeypointDragEffect,
    PointMassEffect as PointMassEffect,
    Smoothing as Smoothing,
    SmoothingChoice as SmoothingChoice,
    augment as augment,
    energy_balance as energy_balance,
    estimate_noise as estimate_noise,
    identify as identify,
)
from ._input import (
    AbstractInputMatrix as AbstractInputMatrix,
    ConstantInput as ConstantInput,
    JointInput as JointInput,
    MLPInput as MLPInput,
)
from ._integrate import (
    Trajectory as Trajectory,
    project_state as project_state,
    simulate as simulate,
)
from ._keycld import (
    KEYCLD_SCENES as KEYCLD_SCENES,
    keycld_constraint as keycld_constraint,
    keycld_joints as keycld_joints,
    keycld_model as keycld_model,
    model_from_spec as model_from_spec,
)
from ._loss import (
    AbstractLoss as AbstractLoss,
    Collocation as Collocation,
    InverseDynamics as InverseDynamics,
    LossSum as LossSum,
    MultipleShooting as MultipleShooting,
    Rollout as Rollout,
)
from ._mass import (
    AbstractMass as AbstractMass,
    ConstantMass as ConstantMass,
    CoupledMasses as CoupledMasses,
    JointArmature as JointArmature,
    PointMasses as PointMasses,
    pivot_body_gravity as pivot_body_gravity,
    pivot_body_mass as pivot_body_mass,
    rigid_body_gravity as rigid_body_gravity,
    rigid_body_mass as rigid_body_mass,
)
from ._potential import (
    AbstractPotential as AbstractPotential,
    Gravity as Gravity,
    JointSpring as JointSpring,
    MLPPotential as MLPPotential,
    Spring as Spring,
    Sum as Sum,
)
from ._progress import (
    AbstractProgressMeter as AbstractProgressMeter,
    NoProgressMeter as NoProgressMeter,
    TextProgressMeter as TextProgressMeter,
    TqdmProgressMeter as TqdmProgressMeter,
)
from ._solver import (
    RATTLE as RATTLE,
    RATTLE4 as RATTLE4,
    RK4 as RK4,
    DynamicsTerm as DynamicsTerm,
    ProjectedSolver as ProjectedSolver,
)
from ._stabilisation import (
    AbstractStabilisation as AbstractStabilisation,
    Baumgarte as Baumgarte,
    NoStabilisation as NoStabilisation,
    Projection as Projection,
)
from ._steps import (
    AbstractStepLoop as AbstractStepLoop,
    CompiledLoop as CompiledLoop,
    HostLoop as HostLoop,
)
from ._system import (
    AbstractDynamics as AbstractDynamics,
    ConstrainedLagrangian as ConstrainedLagrangian,
)

try:
    __version__ = importlib.metadata.version("cldyn")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
