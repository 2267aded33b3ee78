"""The joint-space residual of a model and the candidates' features, in the weak form.

The measured motion obeys `M xdd = f(x, xd, u) + DPhi^T lambda + F`, with `F` whatever the model
lacks. In the joint-space basis `G = dx/dq`, `G^T DPhi^T = 0`, so `r = G^T (M xdd - f) = G^T F`: one
generalised force per joint, free of the unknown multipliers. Every column here has the form
`L(x) xdd + c(x, xd, u)`, and the weak form integrates it against test functions without
accelerations (see `weak_pieces`).
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._coordinates import JointMap
from .._system import ConstrainedLagrangian
from .base import Candidate, Context, Point


def basis(model: ConstrainedLagrangian, joints, x):
    """`G = dx/dq` `(k, m)`. From the joint map when `joints` is a `JointMap`; when it is the joint
    coordinates themselves, the `G` they and the constraints determine: `[dq/dx; DPhi] G = [I; 0]`
    (the joint velocities `qd = dq/dx xd` and `DPhi xd = 0` fix `xd = G qd`). Smooth in `x`, as the
    weak form's derivative of `G^T M` along the motion needs."""
    if isinstance(joints, JointMap):
        return jax.jacfwd(joints.keypoints)(joints.joints(x))
    rows = jnp.concatenate([jnp.stack([c.gradient(x) for c in joints]), model.constraint.jacobian(x)])
    m = len(joints)
    return jnp.linalg.solve(rows, jnp.eye(rows.shape[0], m, dtype=rows.dtype))


def weak_pieces(joint_forces: Callable, x, xd, u, q):
    """The pieces of the weak form of `joint_forces(x, xd, xdd, u, q)`, without accelerations.

    Every column is `L(x) xdd + c(x, xd, u)`. With a test function `psi` that vanishes at both ends,
    integration by parts gives `int psi (L xdd + c) dt = int [-psi' (L xd) - psi (DL(x)[xd] xd) +
    psi c] dt`, so only positions and velocities are needed. Returns `(L xd, DL[xd] xd, c)`.
    """
    zero = jnp.zeros_like(xd)
    inertial = lambda y: joint_forces(y, xd, xd, u, q) - joint_forces(y, xd, zero, u, q)
    momentum, rate = jax.jvp(inertial, (x,), (xd,))
    return momentum, rate, joint_forces(x, xd, zero, u, q)


class Residual(eqx.Module):
    """The joint-space residual `G^T (M xdd - f)` and inertial force `G^T M xdd`, shape `(m, 2)`."""

    model: ConstrainedLagrangian
    joints: "JointMap | tuple"  # or the joint coordinates (see `basis`)

    def joint_forces(self, x, xd, xdd, u, q):
        g = basis(self.model, self.joints, x)
        residual = g.T @ self.model.inverse_dynamics(x, xd, xdd, u)
        return jnp.stack([residual, g.T @ self.model.mass.matvec(xdd)], axis=1)

    def __call__(self, x, xd, u, q):
        return weak_pieces(self.joint_forces, x, xd, u, q)


class Features(eqx.Module):
    """The joint-space force of every candidate column per unit parameter, shape `(m, C)`."""

    context: Context
    joints: "JointMap | tuple"  # or the joint coordinates (see `basis`)
    candidates: tuple[Candidate, ...] = eqx.field(static=True)

    def joint_forces(self, x, xd, xdd, u, q):
        point = Point(x, xd, xdd, u, q)
        columns = [c.effect.force(c, self.context, point) for c in self.candidates]
        forces = jnp.concatenate(columns, axis=1) if columns else jnp.zeros((x.shape[0], 0), x.dtype)
        return basis(self.context.model, self.joints, x).T @ forces

    def __call__(self, x, xd, u, q):
        return weak_pieces(self.joint_forces, x, xd, u, q)


@eqx.filter_jit
def evaluate(pieces: Residual | Features, x, xd, u, q):
    """`pieces` at every sample of every run: arrays `(runs, T, ...)`."""
    # one batch of all samples: a second level of batching costs tracing and compilation
    batch = x.shape[:2]
    flat = jax.vmap(pieces)(*(a.reshape((-1,) + a.shape[2:]) for a in (x, xd, u, q)))
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), flat)
