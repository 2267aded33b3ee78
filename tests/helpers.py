"""Shared test utilities: tolerances, tree comparison, and independent reference mechanics.

The reference mechanics here are written from scratch in generalised coordinates (link angles, cart
position), with kinetic energy from centre-of-mass velocities and rotational inertia. They share no
code with cldyn's mass blocks, constraints or joint maps.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import cldyn


def tree_allclose(a, b, *, rtol=1e-9, atol=1e-12) -> bool:
    """Whether two PyTrees have the same structure and allclose array leaves."""
    la, ta = jax.tree_util.tree_flatten(eqx.filter(a, eqx.is_array))
    lb, tb = jax.tree_util.tree_flatten(eqx.filter(b, eqx.is_array))
    if ta != tb:
        return False
    return all(np.allclose(x, y, rtol=rtol, atol=atol) for x, y in zip(la, lb))


def _dir(theta):
    return jnp.stack([jnp.sin(theta), -jnp.cos(theta)])


def _normal(theta):
    # the counter-clockwise perpendicular of _dir(theta)
    return jnp.stack([jnp.cos(theta), jnp.sin(theta)])


@dataclasses.dataclass(frozen=True)
class ChainReference:
    """A hanging chain of rigid links in generalised coordinates (relative joint angles)."""

    masses: tuple
    lengths: tuple
    coms: tuple
    offsets: tuple
    inertias: tuple
    gravity: float = 9.81
    gears: tuple = ()
    actuated: tuple = ()
    # rotor inertia on each relative joint angle: 1/2 a_j qd_j^2 (MuJoCo's armature)
    armatures: tuple = ()

    @property
    def n(self):
        return len(self.masses)

    def keypoints(self, q):
        theta = jnp.cumsum(q)
        joint, out = jnp.zeros(2), []
        for i in range(self.n):
            joint = joint + self.lengths[i] * _dir(theta[i])
            out.append(joint)
        return jnp.concatenate(out)

    def lagrangian(self, q, qd):
        def coms(q):
            theta = jnp.cumsum(q)
            joint, out = jnp.zeros(2), []
            for i in range(self.n):
                out.append(
                    joint + self.coms[i] * _dir(theta[i]) + self.offsets[i] * _normal(theta[i])
                )
                joint = joint + self.lengths[i] * _dir(theta[i])
            return jnp.stack(out)

        c, cd = jax.jvp(coms, (q,), (qd,))
        omega = jnp.cumsum(qd)
        m, inertia = jnp.array(self.masses), jnp.array(self.inertias)
        kinetic = 0.5 * jnp.sum(m * jnp.sum(cd**2, axis=1)) + 0.5 * jnp.sum(inertia * omega**2)
        for a, rate in zip(self.armatures, qd):
            kinetic = kinetic + 0.5 * a * rate**2
        potential = self.gravity * jnp.sum(m * c[:, 1])
        return kinetic - potential

    def generalized_force(self, q, u):
        force = jnp.zeros(self.n)
        for j, (joint, gear) in enumerate(zip(self.actuated, self.gears)):
            force = force.at[joint].add(gear * u[j])
        return force


@dataclasses.dataclass(frozen=True)
class CartpoleReference:
    """A cart on a rail with a hinged pole, in generalised coordinates `(s, theta)`."""

    cart_mass: float
    pole_mass: float
    length: float
    com: float
    offset: float
    inertia: float
    gravity: float = 9.81
    gears: tuple = ()
    actuated: tuple = ()

    def keypoints(self, q):
        cart = jnp.stack([q[0], 0.0])
        return jnp.concatenate([cart, cart + self.length * _dir(q[1])])

    def lagrangian(self, q, qd):
        def com(q):
            return jnp.stack([q[0], 0.0]) + self.com * _dir(q[1]) + self.offset * _normal(q[1])

        c, cd = jax.jvp(com, (q,), (qd,))
        kinetic = (
            0.5 * self.cart_mass * qd[0] ** 2
            + 0.5 * self.pole_mass * jnp.sum(cd**2)
            + 0.5 * self.inertia * qd[1] ** 2
        )
        return kinetic - self.gravity * self.pole_mass * c[1]

    def generalized_force(self, q, u):
        force = jnp.zeros(2)
        for j, (joint, gear) in enumerate(zip(self.actuated, self.gears)):
            force = force.at[joint].add(gear * u[j])
        return force


def euler_lagrange_acceleration(reference, q, qd, u, force=None):
    """`qdd` from `d/dt dL/dqd - dL/dq = Q`, by autodiff of the reference Lagrangian.

    `force(q, qd)`, if given, is an extra generalised force (damping, friction, drag on a joint),
    written in joint space independently of cldyn's Cartesian terms.
    """
    mass = jax.hessian(reference.lagrangian, argnums=1)(q, qd)
    mixed = jax.jacfwd(jax.grad(reference.lagrangian, argnums=1), argnums=0)(q, qd)
    rhs = (
        jax.grad(reference.lagrangian, argnums=0)(q, qd)
        - mixed @ qd
        + reference.generalized_force(q, u)
    )
    if force is not None:
        rhs = rhs + force(q, qd)
    return jnp.linalg.solve(mass, rhs)


def reference_energy(reference, q, qd):
    """The reference's energy `E = qd . dL/dqd - L` (its Hamiltonian)."""
    return jnp.dot(qd, jax.grad(reference.lagrangian, argnums=1)(q, qd)) - reference.lagrangian(q, qd)


def joint_acceleration(reference, q, qd, xdd):
    """The `qdd` whose keypoint acceleration `J qdd + Jd qd` is `xdd`, through the reference's `F(q)`."""
    jac = jax.jacfwd(reference.keypoints)(q)
    _, drift = jax.jvp(lambda q_: jax.jvp(reference.keypoints, (q_,), (qd,))[1], (q,), (qd,))
    return jnp.linalg.lstsq(jac, xdd - drift)[0]


def keypoint_state(reference, q, qd, qdd=None):
    """`(x, xd[, xdd])` from joint coordinates through the reference's own `x = F(q)`."""
    x, xd = jax.jvp(reference.keypoints, (q,), (qd,))
    if qdd is None:
        return x, xd
    _, xdd = jax.jvp(lambda q_: jax.jvp(reference.keypoints, (q_,), (qd,))[1], (q,), (qd,))
    return x, xd, xdd + jax.jacfwd(reference.keypoints)(q) @ qdd


def _chain_case(n, masses, lengths, coms, offsets, inertias, actuated, gears):
    system, joints = cldyn.systems.chain(
        n,
        masses=masses,
        lengths=lengths,
        coms=coms,
        com_offsets=offsets,
        inertias=inertias,
        actuators=actuated,
        gears=gears,
    )
    reference = ChainReference(
        tuple(masses), tuple(lengths), tuple(coms), tuple(offsets), tuple(inertias),
        gears=tuple(gears), actuated=tuple(actuated),
    )
    return system, joints, reference


def reference_systems():
    """`name -> (system, joints, reference)` with unequal, off-axis, non-trivial parameters."""
    cases = {
        "pendulum": _chain_case(1, [1.3], [0.7], [0.45], [0.08], [0.05], [0], [2.0]),
        "acrobot": _chain_case(
            2, [1.0, 0.6], [1.0, 0.8], [0.5, 0.35], [0.1, -0.05], [0.08, 0.03], [0, 1], [2.0, 1.0]
        ),
        "chain3": _chain_case(
            3,
            [1.0, 2.0, 0.7],
            [1.0, 0.5, 0.8],
            [0.3, 0.25, 0.5],
            [0.0, 0.1, -0.2],
            [0.1, 0.05, 0.02],
            [0, 2],
            [1.0, 3.0],
        ),
    }
    cart_system, cart_joints = cldyn.systems.cartpole(
        cart_mass=1.2, pole_mass=0.4, length=1.1, com=0.55, com_offset=0.04, pole_inertia=0.03,
        actuators=(0, 1), gears=(4.0, 1.0),
    )
    cases["cartpole"] = (
        cart_system,
        cart_joints,
        CartpoleReference(1.2, 0.4, 1.1, 0.55, 0.04, 0.03, gears=(4.0, 1.0), actuated=(0, 1)),
    )
    return cases


def simulate_reference(reference, q0, qd0, u, dt, samples, *, substeps=20, force=None):
    """Integrate a reference in its generalised coordinates (classic RK4, `substeps` steps per sample)
    with the control `u` `(samples, l)` held from each sample to the next, and map the samples to
    keypoints through the reference's own `x = F(q)`.

    `force(q, qd)` adds a generalised force (see `euler_lagrange_acceleration`). One run in, one out;
    `jax.vmap` over runs. Returns `(x, xd)`, each `(samples, k)`.
    """
    h = dt / substeps

    def rate(state, control):
        q, qd = state
        return qd, euler_lagrange_acceleration(reference, q, qd, control, force)

    def step(state, control):
        def substep(state, _):
            k1 = rate(state, control)
            k2 = rate(jax.tree.map(lambda s, k: s + 0.5 * h * k, state, k1), control)
            k3 = rate(jax.tree.map(lambda s, k: s + 0.5 * h * k, state, k2), control)
            k4 = rate(jax.tree.map(lambda s, k: s + h * k, state, k3), control)
            combine = lambda s, a, b, c, d: s + h / 6 * (a + 2 * b + 2 * c + d)
            new = jax.tree.map(combine, state, k1, k2, k3, k4)
            return new, None

        new, _ = jax.lax.scan(substep, state, None, length=substeps)
        return new, state

    _, (q, qd) = jax.lax.scan(step, (jnp.asarray(q0), jnp.asarray(qd0)), jnp.asarray(u)[:samples])
    return jax.jit(jax.vmap(lambda a, b: keypoint_state(reference, a, b)))(q, qd)
