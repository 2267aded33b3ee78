"""Controls: what `simulate`, the losses, the metrics and `identify` apply to a system.

Every control is a final Equinox module with the one signature `u = control(t, x, xd)`, shape `(l,)`:

- `ConstantControl`: one value for all time (KeyCLD's data hold one action per run);
- `TimeVaryingControl`: a function of time `u(t)`;
- `FeedbackControl`: a policy `u(t, x, xd)`;
- `ZeroOrderHold`: sampled controls, each held until the next sample (recorded data);
- `EnergyShaping`: the passivity-based controller of eq. 32, with its damping injection chosen by
  `KeypointDampingInjection` or `OutputDampingInjection`.
"""

import abc
import inspect
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._custom_types import ArrayInput, Control, Vector
from ._linalg import SmallDense
from ._system import ConstrainedLagrangian, check_array


class AbstractControl(eqx.Module):
    """A control law `u(t, x, xd)`: the inputs applied at time `t` in state `(x, xd)`.

    Subclasses implement `__call__` and say whether the control reads the state (`depends_on_state`),
    which lets solvers such as `RATTLE` skip the fixed-point iteration that a feedback needs.
    """

    depends_on_state: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def __call__(self, t: Float[ArrayLike, ""], x: Vector, xd: Vector) -> Control:
        """The controls at time `t` in state `(x, xd)`, shape `(l,)`."""

    def over_step(self, t0: Float[ArrayLike, ""], t1: Float[ArrayLike, ""]) -> "AbstractControl":
        """The control as one solver step from `t0` to `t1` applies it; the control itself unless it
        jumps. A held control (`ZeroOrderHold`) holds the sample of the step's interior over the whole
        step, so that a last stage evaluated at `t1` does not read the next sample."""
        del t0, t1
        return self

    def breakpoints(self) -> np.ndarray | None:
        """The times at which the control jumps, which no solver step should straddle (`None`: the
        control does not jump)."""
        return None


class ConstantControl(AbstractControl):
    """A control that does not change: $u(t) = u_0$.

    **Arguments:**

    - `value`: the controls, shape `(l,)`.

    !!! example

        ```python
        traj = cldyn.simulate(system, x0, xd0, ts, control=cldyn.ConstantControl(jnp.array([0.5])))
        ```
    """

    value: Float[Array, " l"]
    depends_on_state = False

    def __init__(self, value: ArrayInput):
        value = jnp.asarray(value)
        if value.ndim != 1:
            raise ValueError(f"ConstantControl: value must have shape (l,), got {value.shape}")
        self.value = value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(float)

    def __call__(self, t, x, xd) -> Control:
        del t, x, xd
        return self.value


class TimeVaryingControl(AbstractControl):
    """A control given as a function of time, $u = f(t)$ (open loop).

    **Arguments:**

    - `fn`: `fn(t) -> (l,)`; an Equinox module (whose arrays are then parameters) or a function.
    """

    fn: Callable
    depends_on_state = False

    def __call__(self, t, x, xd) -> Control:
        del x, xd
        return jnp.asarray(self.fn(t))


class FeedbackControl(AbstractControl):
    """A state-feedback policy, $u = \\pi(t, x, \\dot x)$.

    **Arguments:**

    - `fn`: `fn(t, x, xd) -> (l,)`; an Equinox module or a function.
    """

    fn: Callable
    depends_on_state = True

    def __call__(self, t, x, xd) -> Control:
        return jnp.asarray(self.fn(t, x, xd))


class ZeroOrderHold(AbstractControl):
    """Sampled controls, each held from its sample to the next: $u(t) = u_i$ for
    $t_0 + i h \\le t < t_0 + (i + 1) h$.

    How recorded data are applied: MuJoCo holds `ctrl` constant between samples, and the KeyCLD data
    hold one action per run. Times before `t0` take the first value and times after the last sample
    the last value.

    **Arguments:**

    - `values`: the controls at the samples, shape `(T, l)`.
    - `dt`: the sampling interval `h`.
    - `t0`: the time of the first sample.

    !!! example

        ```python
        control = cldyn.ZeroOrderHold(data.u[0], dt=data.dt)
        traj = cldyn.simulate(system, x0, xd0, data.ts, control=control, solver=cldyn.RK4())
        ```
    """

    values: Float[Array, "T l"]
    dt: float = eqx.field(static=True)
    t0: float = eqx.field(static=True, default=0.0)
    depends_on_state = False

    def __check_init__(self):
        if jnp.ndim(self.values) != 2:
            raise ValueError(f"ZeroOrderHold: values must have shape (T, l), got {jnp.shape(self.values)}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"ZeroOrderHold: dt must be a positive interval, got {self.dt}")

    def __call__(self, t, x, xd) -> Control:
        del x, xd
        # a relative margin: a step that lands on a sample time (up to rounding) takes that sample
        position = (t - self.t0) / self.dt
        index = jnp.floor(position + 1e-6 * jnp.maximum(1.0, jnp.abs(position))).astype(int)
        return self.values[jnp.clip(index, 0, self.values.shape[0] - 1)]

    def over_step(self, t0, t1) -> AbstractControl:
        # the sample held at the middle of the step, for every stage of it (MuJoCo holds `ctrl` over
        # the whole step); steps end on the sample times (`breakpoints`), so none straddles two
        middle = 0.5 * (t0 + t1)
        return ConstantControl(self(middle, None, None))

    def breakpoints(self) -> np.ndarray:
        return self.t0 + self.dt * np.arange(1, self.values.shape[0])


def as_control(control, num_inputs: int) -> AbstractControl | None:
    """Normalise what users pass as `control=`: `None`, an `AbstractControl`, a constant `(l,)`
    array, a function of time `u(t)` or a feedback policy `u(t, x, xd)` (told apart by the number of
    required positional arguments)."""
    if control is None or isinstance(control, AbstractControl):
        return control
    if callable(control):
        try:
            parameters = inspect.signature(control).parameters.values()
        except (TypeError, ValueError):
            parameters = ()
        positional = [
            p
            for p in parameters
            if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty
        ]
        if len(positional) == 1:
            return TimeVaryingControl(control)
        if len(positional) == 3:
            return FeedbackControl(control)
        raise ValueError(
            "control must be a function of time u(t) or a feedback policy u(t, x, xd); "
            f"got a callable with {len(positional)} required positional arguments"
        )
    return ConstantControl(check_array("control", control, (num_inputs,)))


def check_control_shape(control: AbstractControl | None, num_inputs: int, t, x, xd) -> None:
    """Raise a `ValueError` unless `control(t, x, xd)` has shape `(num_inputs,)` (checked by tracing)."""
    if control is None:
        return
    shape = jax.eval_shape(control, t, x, xd).shape
    if shape != (num_inputs,):
        raise ValueError(f"control must return shape ({num_inputs},), got {shape}")


class AbstractDampingInjection(eqx.Module):
    """How `EnergyShaping` injects damping: the part of eq. 32 that removes energy."""

    @abc.abstractmethod
    def __call__(
        self,
        match: Callable[[Vector], Control],
        force: Vector,
        g: Float[Array, "k l"],
        xd: Vector,
        kd: Float[Array, ""],
    ) -> Control:
        """The controls from the shaped keypoint force `force`, with damping of gain `kd` injected.

        `match(f)` gives the controls whose input force best matches a keypoint force `f`, $(g^T
        g)^{-1} g^T f$; `g` is the input matrix at the state and `xd` the velocity.
        """


class KeypointDampingInjection(AbstractDampingInjection):
    """Damping matched as a keypoint force: $u = (g^T g)^{-1} g^T [f - k_d \\dot x]$.

    The keypoint damping force `-k_d xd` goes through the same match as the shaped force, so `k_d` is
    a damping coefficient in N s/m whatever the scale of `g` (a gear, or a learned `g`'s arbitrary
    scale). Passive. The default of `EnergyShaping`.

    !!! example

        ```python
        controller = cldyn.EnergyShaping(system, upright, kp=5.0, kd=2.0,
                                         damping=cldyn.KeypointDampingInjection())
        ```
    """

    def __call__(self, match, force, g, xd, kd) -> Control:
        del g
        return match(force - kd * xd)


class OutputDampingInjection(AbstractDampingInjection):
    """Damping on the passive output as eq. 32 prints it: $u = (g^T g)^{-1} g^T f - k_d g^T \\dot x$.

    Passive, but the damping grows with the square of the actuators' gears (and of a learned `g`'s
    scale): with MuJoCo's KeyCLD scenes (gear 2) the paper's `k_d = 2` makes the swing-up so
    overdamped that it takes far longer than 10 s.

    !!! example

        ```python
        controller = cldyn.EnergyShaping(system, upright, kp=5.0, kd=2.0,
                                         damping=cldyn.OutputDampingInjection())
        ```
    """

    def __call__(self, match, force, g, xd, kd) -> Control:
        return match(force) - kd * (g.T @ xd)


# the shorthands `EnergyShaping(damping=...)` accepts
_DAMPING_INJECTIONS = {"keypoint": KeypointDampingInjection(), "output": OutputDampingInjection()}


class EnergyShaping(AbstractControl):
    """Passivity-based energy-shaping controller (eq. 32).

    $u = (g^T g)^{-1} g^T [\\nabla_x V(x) - k_p (x - x^*)] - k_d\\, g^T \\dot x$

    The first term replaces the system's potential `V` by the shaped potential
    $V_d = \\tfrac12 k_p |x - x^*|^2$ with its minimum at the target; the second injects damping through
    the passive output $g^T \\dot x$. For a fully actuated system (`l` equal to the degrees of freedom)
    the matching condition of eq. 30 holds and the target is asymptotically stable. `(g^T g)^-1` is
    applied by a linear solve. Works with analytic and learned systems alike: only `V(x)` and `g(x)`
    are used.

    **Arguments:**

    - `system`: a `ConstrainedLagrangian` with a potential and an input matrix.
    - `x_target`: the target keypoints `x*`, shape `(k,)`.
    - `kp`: the stiffness of the shaped potential (the paper uses 5).
    - `kd`: the damping injection gain (the paper uses 2).
    - `limit`: optional bound on `|u|` per input (actuator saturation).
    - `project`: match in the constraint tangent space (see above); `False` for the literal eq. 32.
    - `damping`: how damping is injected: `KeypointDampingInjection()` (default) matches the keypoint
      damping force `-k_d xd` through the same `(g^T g)^-1 g^T` as the shaped force, so that `k_d` is a
      damping coefficient in N s/m whatever the scale of `g`; `OutputDampingInjection()` injects
      `-k_d g^T xd` on the passive output as eq. 32 prints it. The strings `"keypoint"` and `"output"`
      are shorthands for them.
    - `metric`: the metric of the shaped potential and of keypoint damping. `"euclidean"` (default)
      is eq. 32: $V_d = \\tfrac12 k_p |x - x^*|^2$ and damping force $-k_d \\dot x$. `"mass"` weighs both
      by the constant mass matrix $M$: $V_d = \\tfrac12 k_p (x - x^*)^T M (x - x^*)$ and $-k_d M \\dot x$,
      so that near the target every mode obeys $\\ddot e + k_d \\dot e + k_p e = 0$ (fully actuated,
      exact potential): the gains are rates (`kp` in 1/s², `kd` in 1/s) whatever the masses. A
      Lagrangian learnt from images is only defined up to a factor (`M`, `V` and `g` scaled together
      give the same motion), and eq. 32's gains act differently at each factor; with `"mass"` the
      controls do not depend on it. Needs `damping="keypoint"`.
    - `trim`: subtract the command at the target at rest, `u(x*, 0)`, from every command (not part of
      eq. 32). Where the target is an equilibrium of the uncontrolled system (a pendulum upright or
      hanging) that command is zero for an exact potential, and what a learnt one commands there is
      its error. Without the trim the loop rests where the shaped spring balances that error, about
      the gravity rate over `kp` times the learnt upright's offset; with it the rest is the target to
      first order. A constant control, so exact for an input matrix that does not change near the
      target (joint motors). Wrong for a target that is not an equilibrium.

    Call it as a feedback policy `u = controller(t, x, xd)`, e.g. `cldyn.simulate(...,
    control=controller)`.

    !!! example

        ```python
        system, joints = cldyn.systems.pendulum()
        upright = joints.keypoints(jnp.array([jnp.pi]))
        controller = cldyn.EnergyShaping(system, upright, kp=5.0, kd=2.0)
        traj = cldyn.simulate(system, x0, xd0, ts, control=controller)
        ```
    """

    system: ConstrainedLagrangian
    x_target: Float[Array, " k"]
    kp: Float[Array, ""]
    kd: Float[Array, ""]
    limit: float | None = eqx.field(static=True)
    project: bool = eqx.field(static=True)
    damping: AbstractDampingInjection
    metric: str = eqx.field(static=True)
    trim: bool = eqx.field(static=True)
    depends_on_state = True

    def __init__(
        self,
        system: ConstrainedLagrangian,
        x_target: ArrayInput,
        kp: float = 5.0,
        kd: float = 2.0,
        *,
        limit: float | None = None,
        project: bool = True,
        damping: AbstractDampingInjection | str = KeypointDampingInjection(),
        metric: str = "euclidean",
        trim: bool = False,
    ):
        if not isinstance(system, ConstrainedLagrangian):
            raise TypeError(f"system must be a ConstrainedLagrangian, got {type(system).__name__}")
        if system.input_matrix is None or system.num_inputs == 0:
            raise ValueError("energy shaping needs a system with inputs (an input_matrix)")
        self.system = system
        # the controller computes in the system's precision (a float32 model under 64-bit mode too)
        dtype = system.mass.matrix().dtype
        self.x_target = check_array("x_target", x_target, (system.size,)).astype(dtype)
        self.kp = jnp.asarray(kp, dtype=dtype)
        self.kd = jnp.asarray(kd, dtype=dtype)
        if limit is not None and not limit > 0:
            raise ValueError(f"limit must be positive, got {limit}")
        self.limit = limit
        self.project = project
        if isinstance(damping, str):
            if damping not in _DAMPING_INJECTIONS:
                raise ValueError(f"damping must be 'output' or 'keypoint', got {damping!r}")
            damping = _DAMPING_INJECTIONS[damping]
        if not isinstance(damping, AbstractDampingInjection):
            raise TypeError(f"damping must be an AbstractDampingInjection, got {type(damping).__name__}")
        self.damping = damping
        if metric not in ("euclidean", "mass"):
            raise ValueError(f"metric must be 'euclidean' or 'mass', got {metric!r}")
        if metric == "mass" and not isinstance(damping, KeypointDampingInjection):
            raise ValueError(
                "metric='mass' weighs the keypoint damping force by the mass matrix: it needs "
                f"damping='keypoint', got {type(damping).__name__}"
            )
        self.metric = metric
        self.trim = bool(trim)

    def _weigh(self, v: Vector) -> Vector:
        """`v` in the metric: `M v` for `"mass"`, `v` itself for `"euclidean"`."""
        return self.system.mass.matrix() @ v if self.metric == "mass" else v

    def shaped_potential(self, x: Vector) -> Float[Array, ""]:
        """The desired potential $V_d(x) = \\tfrac12 k_p (x - x^*)^T W (x - x^*)$ (eq. 31), `W` the
        identity or, with `metric="mass"`, the mass matrix."""
        e = x - self.x_target
        return 0.5 * self.kp * jnp.dot(e, self._weigh(e))

    def __call__(self, t, x: Vector, xd: Vector) -> Control:
        """The control `u(t, x, xd)`, shape `(l,)`."""
        del t
        u = self._shaping(x, xd)
        if self.trim:
            u = u - self._shaping(self.x_target, jnp.zeros_like(self.x_target))
        if self.limit is not None:
            u = jnp.clip(u, -self.limit, self.limit)
        return u

    def _shaping(self, x: Vector, xd: Vector) -> Control:
        """Eq. 32's command, before the trim and the limit."""
        g = self.system.input_matrix(x)
        if self.project and self.system.num_constraints > 0:
            jac = self.system.constraint.jacobian(x)
            normal = lx.MatrixLinearOperator(jac @ jac.T, lx.positive_semidefinite_tag)
            g = g - jac.T @ jnp.stack(
                [lx.linear_solve(normal, jac @ g[:, j], SmallDense()).value for j in range(g.shape[1])],
                axis=1,
            )
        grad_v = self.system.potential.gradient(x) if self.system.potential is not None else jnp.zeros_like(x)
        force = grad_v - self.kp * self._weigh(x - self.x_target)
        gram = lx.MatrixLinearOperator(g.T @ g, lx.positive_semidefinite_tag)
        match = lambda f: lx.linear_solve(gram, g.T @ f, SmallDense()).value  # noqa: E731
        # keypoint damping is `match(force - kd * xd)`: in the mass metric, `xd` weighed
        return self.damping(match, force, g, self._weigh(xd), self.kd)


def hinge_extremes(count: int, height: Callable[[np.ndarray], float]) -> tuple[np.ndarray, np.ndarray]:
    """The angles in `{0, pi}^count` (one per hinge) at which `height(angles)` is lowest and highest
    (the first in order among equals): a mechanism's hanging and upright postures, found from its
    geometry rather than from a joint convention."""
    corners = np.array(np.meshgrid(*([[0.0, np.pi]] * count), indexing="ij")).reshape(count, -1).T
    heights = [height(corner) for corner in corners]
    return corners[int(np.argmin(heights))], corners[int(np.argmax(heights))]
