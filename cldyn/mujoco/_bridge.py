"""`from_mjcf`: a planar MuJoCo model as a cldyn `ConstrainedLagrangian` in keypoint coordinates.

Every rigid group of bodies (a body and the bodies welded to it) gets a *frame*: its origin `O(x)` and
its orientation as a unit complex number `z(x)`, both affine in the keypoints `x`, so that a point of
the group with reference position `y0` sits at `O(x) + z(x) (y0 - O0)` (complex product). A group hinged
to its parent has its origin at the hinge and its orientation from one of its keypoints; a group on a
slide takes its origin at one of its keypoints and its parent's orientation. Being affine in `x`, a
frame gives the group's centre-of-mass velocity and its angular velocity (`|zdot| = |omega|`) as
constant linear maps of `xd`, hence an exact constant mass block `m C^T C + I Z^T Z`.
"""

import dataclasses
import os
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from .._constraint import (
    AbstractConstraint,
    Anchor,
    BilinearConstraint,
    Distance,
    FixedCoordinate,
    LinearConstraint,
    NormConstraint,
    Stack,
)
from .._coordinates import AbstractCoordinate, HingeAngle, JointMap, SliderPosition
from .._dissipation import JointDamping
from .._input import JointInput
from .._mass import ConstantMass, JointArmature
from .._potential import AbstractPotential, Gravity, JointSpring
from .._system import ConstrainedLagrangian
from ._checks import actuator_name, check_include, check_supported
from ._frames import (
    Affine,
    ForwardKinematics,
    FrameAngle,
    FrameSlide,
    InverseKinematics,
    cmat,
)
from ._scenes import load_model
from ._tree import (
    _HINGE,
    TOL,
    Keypoint,
    Plane,
    Tree,
    body_name,
    build_tree,
    find_plane,
    joint_name,
    reference_data,
    select_keypoints,
)


def _conj(c: np.ndarray) -> np.ndarray:
    return np.array([c[0], -c[1]])


@dataclasses.dataclass(frozen=True)
class _Segment:
    """A direction fixed in a group, from keypoint `tail` (or the fixed `pivot`) to keypoint `head`."""

    tail: int | None
    head: int
    pivot: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class _Frame:
    """A rigid group's pose, affine in the keypoints (see the module docstring)."""

    origin: Affine
    origin0: np.ndarray
    rotation: Affine
    # How HingeAngle can read the orientation: "fixed" for a group that never rotates, a segment,
    # or None when only the general frame can.
    segment: "_Segment | str | None"

    def point(self, y0: np.ndarray) -> Affine:
        """The current position of the group's point with reference position `y0`."""
        return self.origin + self.rotation.left(cmat(y0 - self.origin0))

    @property
    def rotates(self) -> bool:
        return not self.rotation.is_constant


class MujocoModel(eqx.Module):
    """A planar MuJoCo model in cldyn's terms, as built by `from_mjcf`.

    **Fields:**

    - `system`: the `ConstrainedLagrangian` in keypoint coordinates.
    - `joints`: a `cldyn.JointMap` between MuJoCo's `qpos` (all joints, in MuJoCo's order) and the
      keypoints: `joints.to_keypoints(qpos, qvel)` gives `(x, xd)`, `joints.to_joints(x, xd)` gives
      `(qpos, qvel)` back, with hinge angles wrapped into `[-pi, pi)`.
    - `keypoint_names`: one name per keypoint (a site's name, a joint's name for its anchor,
      `<body>_end` for the far end of a body; merged points join their names with `+`).
    - `joint_names`: MuJoCo's joint names, in `qpos` order.
    - `joint_coordinates`: for each of those joints, the cldyn coordinate `q(x)` that equals its
      `qpos` (`HingeAngle`, `SliderPosition`, or a general frame coordinate).
    - `actuator_names`: MuJoCo's actuator names, one per control column of `system.input_matrix`.
    - `actuator_joints`: the joint each actuator drives.
    - `basis`: the plane of motion, rows `e1, e2` in world coordinates: world point `p` has planar
      coordinates `basis @ p`.
    - `include`: the passive effects included (see `from_mjcf`).
    - `joint_limits`: per joint (in `joint_names`' order), `(low, high)` where MuJoCo limits it
      (`limited`, `range`, less the limit's `margin`) with limits and constraints enabled, else `None`.
      The cldyn model has no limits: `identify_recording` leaves out the samples at a limit.
    """

    system: ConstrainedLagrangian
    joints: JointMap
    keypoint_names: tuple[str, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    joint_coordinates: tuple[AbstractCoordinate, ...]
    actuator_names: tuple[str, ...] = eqx.field(static=True)
    actuator_joints: tuple[str, ...] = eqx.field(static=True)
    basis: tuple[tuple[float, float, float], tuple[float, float, float]] = eqx.field(static=True)
    include: tuple[str, ...] = eqx.field(static=True)
    joint_limits: tuple[tuple[float, float] | None, ...] = eqx.field(static=True, default=())

    def limits(self) -> dict[str, tuple[float, float]]:
        """`{joint name: (low, high)}` for the joints MuJoCo limits."""
        return {n: r for n, r in zip(self.joint_names, self.joint_limits) if r is not None}

    def project(self, points) -> np.ndarray:
        """Planar coordinates of world points: shape `(..., 3) -> (..., 2)`."""
        return np.asarray(points) @ np.asarray(self.basis).T

    def coordinate(self, joint: str) -> AbstractCoordinate:
        """The cldyn coordinate of the MuJoCo joint named `joint`."""
        if joint not in self.joint_names:
            raise KeyError(f"no joint named {joint!r}; the joints are {list(self.joint_names)}")
        return self.joint_coordinates[self.joint_names.index(joint)]


# -- the build -------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Build:
    model: mujoco.MjModel
    data: mujoco.MjData
    tree: Tree
    plane: Plane
    keypoints: list[Keypoint]

    def __post_init__(self):
        self.size = 2 * len(self.keypoints)
        self.x0 = np.array([self.plane.project(k.world) for k in self.keypoints]).reshape(-1, 2)
        self.introduced = [min(k.groups) for k in self.keypoints]
        self.frames: dict[int, _Frame] = {
            0: _Frame(self.constant(np.zeros(2)), np.zeros(2), self.constant(np.array([1.0, 0.0])), "fixed")
        }
        self.constraints: list[AbstractConstraint] = []
        self.linear_rows: list[np.ndarray] = []
        self.coordinates: dict[int, AbstractCoordinate] = {}
        self.mass = np.zeros((self.size, self.size))
        self.weights = np.zeros(self.size)

    def constant(self, value: np.ndarray) -> Affine:
        return Affine(np.zeros((2, self.size)), np.asarray(value, dtype=float))

    def select(self, i: int) -> Affine:
        matrix = np.zeros((2, self.size))
        matrix[:, 2 * i : 2 * i + 2] = np.eye(2)
        return Affine(matrix, np.zeros(2))

    def name(self, i: int) -> str:
        return self.keypoints[i].name

    # -- one rigid group at a time, parents first --

    def add_group(self, g: int) -> None:
        model, tree = self.model, self.tree
        j = tree.joints[g][0]
        parent = self.frames[tree.parent[g]]
        on_group = [i for i in range(len(self.keypoints)) if g in self.keypoints[i].groups]
        new = [i for i in on_group if self.introduced[i] == g]
        anchor = self.plane.project(self.data.xanchor[j])
        if model.jnt_type[j] == _HINGE:
            frame, frames = self._hinge(g, j, parent, on_group, new, anchor)
        else:
            frame, frames = self._slide(g, j, parent, on_group, new, anchor)
        self.frames[g] = frame
        self._mass(g, frame, frames)

    def _hinge(self, g, j, parent: _Frame, on_group, new, anchor):
        model = self.model
        at_anchor = [i for i in on_group if np.linalg.norm(self.x0[i] - anchor) < TOL]
        if at_anchor:
            origin_index = at_anchor[0]
            origin = self.select(origin_index)
        else:
            origin_index = None
            origin = parent.point(anchor)
        distances = {i: float(np.linalg.norm(self.x0[i] - anchor)) for i in on_group}
        candidates = [i for i in on_group if distances[i] > TOL]
        if not candidates:
            raise ValueError(
                f"body {body_name(model, g)!r} turns about hinge {joint_name(model, j)!r} but carries no "
                "keypoint away from the hinge axis; name a site on it (keypoints=...) or give it a geom "
                "away from the joint"
            )

        def frame_for(k):
            w0 = self.x0[k] - anchor
            rotation = (self.select(k) - origin).left(cmat(_conj(w0) / np.dot(w0, w0)))
            segment = None
            if origin_index is not None:
                segment = _Segment(origin_index, k, None)
            elif origin.is_constant:
                segment = _Segment(None, k, origin.const)
            return _Frame(origin, anchor, rotation, segment)

        head = max(candidates, key=lambda i: distances[i])
        frame = frame_for(head)
        if origin_index is not None:
            self.constraints.append(Distance(origin_index, head))
        elif origin.is_constant:
            self.constraints.append(Anchor(head, origin.const))
        else:
            self.constraints.append(NormConstraint((self.select(head) - origin).map()))
        self._attach(frame, [i for i in new if i not in (head, origin_index)])

        sign = float(np.sign(np.dot(self.data.xaxis[j], self.plane.normal)))
        qpos0 = float(model.qpos0[model.jnt_qposadr[j]])
        self.coordinates[j] = self._hinge_coordinate(frame, parent, sign, qpos0)
        return frame, [frame_for(k) for k in candidates]

    def _hinge_coordinate(self, frame: _Frame, parent: _Frame, sign: float, qpos0: float):
        child = frame.segment
        if isinstance(child, _Segment) and parent.segment == "fixed":
            c0 = self.x0[child.head] - frame.origin0
            return HingeAngle(
                child=(child.tail, child.head),
                pivot=(0.0, 0.0) if child.pivot is None else child.pivot,
                reference=c0 / np.linalg.norm(c0),
                sign=sign,
                offset=-qpos0,
            )
        if isinstance(child, _Segment) and isinstance(parent.segment, _Segment):
            par = parent.segment
            pivots = [p for p in (child.pivot, par.pivot) if p is not None]
            if not pivots or all(np.allclose(p, pivots[0], atol=TOL) for p in pivots):
                c0 = self.x0[child.head] - (self.x0[child.tail] if child.tail is not None else child.pivot)
                r0 = self.x0[par.head] - (self.x0[par.tail] if par.tail is not None else par.pivot)
                phi0 = np.arctan2(r0[0] * c0[1] - r0[1] * c0[0], np.dot(r0, c0))
                return HingeAngle(
                    child=(child.tail, child.head),
                    parent=(par.tail, par.head),
                    pivot=pivots[0] if pivots else (0.0, 0.0),
                    sign=sign,
                    offset=float(sign * phi0 - qpos0),
                )
        return FrameAngle(frame.rotation.map(), parent.rotation.map(), sign, jnp.asarray(-qpos0))

    def _slide(self, g, j, parent: _Frame, on_group, new, anchor):
        model = self.model
        if not on_group:
            raise ValueError(
                f"body {body_name(model, g)!r} slides on {joint_name(model, j)!r} but carries no keypoint; "
                "name a site on it (keypoints=...)"
            )
        at_anchor = [i for i in on_group if np.linalg.norm(self.x0[i] - anchor) < TOL]
        k = at_anchor[0] if at_anchor else on_group[0]

        def frame_for(i):
            return _Frame(self.select(i), self.x0[i], parent.rotation, parent.segment)

        frame = frame_for(k)
        axis = self.plane.project(self.data.xaxis[j])
        axis = axis / np.linalg.norm(axis)
        normal = np.array([-axis[1], axis[0]])
        displacement = self.select(k) - parent.point(self.x0[k])
        if not parent.rotates:
            row = normal @ displacement.matrix
            aligned = np.flatnonzero(np.abs(normal) > 1 - 1e-12)
            if _on_world(self.tree, g) and aligned.size:
                self.constraints.append(FixedCoordinate(k, axis=int(aligned[0])))
            else:
                self.linear_rows.append(row[None, :])
        else:
            self.constraints.append(
                BilinearConstraint(displacement.map(), parent.rotation.left(cmat(normal)).map())
            )
        self._attach(frame, [i for i in new if i != k])

        qpos0 = float(model.qpos0[model.jnt_qposadr[j]])
        if _on_world(self.tree, g):
            self.coordinates[j] = SliderPosition(k, axis=axis, origin=self.x0[k], offset=-qpos0)
        else:
            self.coordinates[j] = FrameSlide(
                displacement.map(), parent.rotation.left(cmat(axis)).map(), jnp.asarray(-qpos0)
            )
        return frame, [frame_for(i) for i in on_group]

    def _attach(self, frame: _Frame, indices) -> None:
        """Tie further keypoints of a group rigidly to its frame: two linear constraints each."""
        for i in indices:
            self.linear_rows.append((self.select(i) - frame.point(self.x0[i])).matrix)

    def _mass(self, g: int, frame: _Frame, frames: list[_Frame]) -> None:
        model, data, plane = self.model, self.data, self.plane
        bodies = [b for b in range(model.nbody) if self.tree.group[b] == g]
        masses = np.array([model.body_mass[b] for b in bodies])
        total = float(masses.sum())
        coms = plane.project(np.array([data.xipos[b] for b in bodies]))
        com = masses @ coms / total if total > 0 else frame.origin0
        inertia = 0.0
        for b, m, c in zip(bodies, masses, coms):
            rot = data.ximat[b].reshape(3, 3)
            axis = rot.T @ plane.normal
            inertia += float(axis @ (model.body_inertia[b] * axis)) + m * float(np.sum((c - com) ** 2))
        block = np.zeros_like(self.mass)
        for f in frames:
            velocity = f.point(com).matrix
            spin = f.rotation.matrix
            block += total * velocity.T @ velocity + inertia * spin.T @ spin
        self.mass += block / len(frames)
        self.weights += total * frame.point(com).matrix[1]

    # -- assembly --

    def constraint(self) -> AbstractConstraint | None:
        constraints = list(self.constraints)
        if self.linear_rows:
            rows = np.concatenate(self.linear_rows, axis=0)
            constraints.append(LinearConstraint(jnp.asarray(rows, dtype=float)))
        if not constraints:
            return None
        return Stack(constraints)

    def check_mass(self) -> None:
        eigenvalues, vectors = np.linalg.eigh(0.5 * (self.mass + self.mass.T))
        scale = max(float(np.abs(eigenvalues).max()), np.finfo(float).tiny)
        if eigenvalues[0] > 1e-10 * scale:
            return
        weights = np.linalg.norm(vectors[:, 0].reshape(-1, 2), axis=1)
        culprit = int(np.argmax(weights))
        raise ValueError(
            f"keypoint {self.name(culprit)!r} carries no mass: the mass matrix is singular "
            f"(smallest eigenvalue {eigenvalues[0]:.3g}). The bodies it is fixed in have no mass or "
            "inertia that moves with it; choose keypoints where the mass is (keypoints=...)"
        )


def _on_world(tree: Tree, g: int) -> bool:
    return tree.parent[g] == 0


def _forward_map(build: _Build) -> ForwardKinematics:
    """`qpos -> x`: planar forward kinematics of the tree, from the reference configuration."""
    model, tree, plane, data = build.model, build.tree, build.plane, build.data
    index = {0: -1} | {g: i for i, g in enumerate(tree.moving)}
    joints = [tree.joints[g][0] for g in tree.moving]
    axes = [plane.project(data.xaxis[j]) for j in joints]
    return ForwardKinematics(
        parents=tuple(index[tree.parent[g]] for g in tree.moving),
        hinges=tuple(bool(model.jnt_type[j] == _HINGE) for j in joints),
        addresses=tuple(int(model.jnt_qposadr[j]) for j in joints),
        homes=tuple(index[g] for g in build.introduced),
        anchors=_array([plane.project(data.xanchor[j]) for j in joints], (len(joints), 2)),
        axes=_array([a / max(np.linalg.norm(a), TOL) for a in axes], (len(joints), 2)),
        signs=_array([np.sign(np.dot(data.xaxis[j], plane.normal)) for j in joints], (len(joints),)),
        qpos0=_array([model.qpos0[model.jnt_qposadr[j]] for j in joints], (len(joints),)),
        reference=_array(build.x0, (len(build.keypoints), 2)),
    )


def _array(values, shape) -> jnp.ndarray:
    return jnp.asarray(np.asarray(values, dtype=float).reshape(shape))


def _check_rank(constraint: AbstractConstraint | None, x0: np.ndarray, dof: int, model, keypoints) -> None:
    n = 0 if constraint is None else constraint.num_constraints
    if x0.size - n != dof:  # by construction; a mismatch is a bug, not a user error
        raise RuntimeError(f"from_mjcf built {n} constraints on {x0.size} coordinates for {dof} joints")
    if constraint is None:
        return
    jac = np.asarray(jax.jacfwd(constraint)(jnp.asarray(x0)))
    singular = np.linalg.svd(jac, compute_uv=False)
    if singular.min() < 1e-6 * max(singular.max(), 1.0):
        raise ValueError(
            "the keypoints do not determine the mechanism's configuration (the constraint Jacobian is "
            f"rank-deficient at the reference pose); keypoints: {[k.name for k in keypoints]}"
        )


def from_mjcf(
    mjcf: "str | os.PathLike",
    *,
    keypoints: Sequence[str] | None = None,
    include: Sequence[str] = (),
) -> MujocoModel:
    """A planar MuJoCo model as a `ConstrainedLagrangian` in keypoint coordinates, exactly.

    For planar kinematic trees of hinge and slide joints: all hinge axes parallel (the normal of the
    plane of motion), slide axes in the plane, one joint per body. MuJoCo's world is mapped to the
    plane by `MujocoModel.basis`: for dm_control's scenes (motion in the world x-z plane, hinges about
    `y`), world `(x, z)` becomes planar `(x, y)`; in general world up maps to `+y` when gravity lies in
    the plane.

    The masses and inertias are MuJoCo's compiled ones (`body_mass`, `body_inertia` with `body_iquat`,
    `body_ipos`; the centre of mass may lie off the line between keypoints), combined into an exact
    constant mass matrix; gravity comes from the model options; `<motor>` actuators on hinges and
    slides become a `JointInput` with gear `gear * gainprm[0]`. Joint coordinates equal MuJoCo's
    `qpos` (`qpos0` and joint `ref` included; hinge angles wrapped into `[-pi, pi)`).

    Not modelled: joint limits (their ranges are in `joint_limits`), control and force clamping
    (`ctrllimited`, `forcelimited`: `record` stores the controls as applied), contacts with the world,
    `frictionloss`. Outside the class, with an error that names the element: ball and
    free joints, non-parallel hinges, slides out of the plane, several joints in one body, tendons,
    equality constraints, contacts between moving bodies, non-motor actuators, gravity compensation,
    fluid forces.

    **Arguments:**

    - `mjcf`: a path, an XML string, a dm_control suite name or `"keycld/<name>"` (see `scene_xml`).
    - `keypoints`: names of sites to use as keypoints, in order; by default every moving joint anchor
      and the far end of every terminal body (a site there if it has one), coincident points of one
      body merged.
    - `include`: passive effects that the XML declares, added as cldyn terms: `"damping"`
      (`JointDamping`), `"stiffness"` (`JointSpring` about `springref`), `"armature"`
      (`JointArmature`). Left out by default: the nominal model.

    **Returns:** a `MujocoModel` with the `system`, the `joints` map and the names of keypoints,
    joints and actuators. Its arrays are float64 when it is built in JAX's 64-bit mode. Every number
    of the scene (lengths, anchors, masses, gears) is an array of the model and only its structure is
    static, so the same scene built twice, or two scenes that differ only in such numbers, run through
    one compiled program of an `eqx.filter_jit` function that takes the model.

    !!! example

        ```python
        bridge = cldyn.mujoco.from_mjcf("keycld/acrobot")
        x, xd = bridge.joints.to_keypoints(jnp.array([0.3, -0.2]), jnp.zeros(2))
        xdd = bridge.system.acceleration(x, xd, jnp.array([0.5, 0.0]))
        ```
    """
    include = check_include(include)
    model, _, _ = load_model(mjcf)
    data = reference_data(model)
    plane = find_plane(model, data)
    tree = build_tree(model)
    check_supported(model, tree)
    chosen = select_keypoints(model, data, tree, plane, keypoints)
    for k in chosen:
        if 0 in k.groups:
            raise ValueError(f"keypoint {k.name!r} is fixed in the world: it does not move; drop it")

    build = _Build(model, data, tree, plane, chosen)
    for g in tree.moving:
        build.add_group(g)
    build.check_mass()
    constraint = build.constraint()
    _check_rank(constraint, build.x0.reshape(-1), model.nv, model, chosen)

    joint_ids = list(range(model.njnt))
    coordinates = tuple(build.coordinates[j] for j in joint_ids)
    joint_names = tuple(joint_name(model, j) for j in joint_ids)

    actuated = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
    input_matrix = None
    if model.nu:
        gears = model.actuator_gear[:, 0] * model.actuator_gainprm[:, 0]
        input_matrix = JointInput([coordinates[j] for j in actuated], gears)

    potential: AbstractPotential | None = None
    if plane.gravity > 0:
        potential = Gravity(jnp.asarray(build.weights), plane.gravity)
    dissipation, armature = None, None
    flags = model.opt.disableflags
    if "stiffness" in include and not flags & mujoco.mjtDisableBit.mjDSBL_SPRING:
        for j in joint_ids:
            stiffness = float(model.jnt_stiffness[j])
            if stiffness > 0:
                spring = JointSpring(
                    coordinates[j],
                    stiffness=stiffness,
                    rest=float(model.qpos_spring[model.jnt_qposadr[j]]),
                    periodic=bool(model.jnt_type[j] == _HINGE),
                )
                potential = spring if potential is None else potential + spring
    dofs = [int(model.jnt_dofadr[j]) for j in joint_ids]
    if "damping" in include and not flags & mujoco.mjtDisableBit.mjDSBL_DAMPER:
        damped = [j for j, d in zip(joint_ids, dofs) if model.dof_damping[d] > 0]
        if damped:
            dissipation = JointDamping(
                [coordinates[j] for j in damped], [float(model.dof_damping[dofs[j]]) for j in damped]
            )
    if "armature" in include:
        geared = [j for j, d in zip(joint_ids, dofs) if model.dof_armature[d] > 0]
        if geared:
            armature = JointArmature(
                [coordinates[j] for j in geared], [float(model.dof_armature[dofs[j]]) for j in geared]
            )
    frictional = [joint_name(model, j) for j, d in zip(joint_ids, dofs) if model.dof_frictionloss[d] > 0]
    if frictional and not flags & (
        mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    ):
        warnings.warn(
            f"joints {frictional} have frictionloss (dry friction, a constraint in MuJoCo); the cldyn "
            "model leaves it out",
            stacklevel=2,
        )

    limits_on = not flags & (mujoco.mjtDisableBit.mjDSBL_LIMIT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    joint_limits = tuple(
        (
            float(model.jnt_range[j, 0] + model.jnt_margin[j]),
            float(model.jnt_range[j, 1] - model.jnt_margin[j]),
        )
        if limits_on and model.jnt_limited[j]
        else None
        for j in joint_ids
    )
    system = ConstrainedLagrangian(
        mass=ConstantMass(jnp.asarray(build.mass)),
        potential=potential,
        constraint=constraint,
        input_matrix=input_matrix,
        dissipation=dissipation,
        armature=armature,
    )
    return MujocoModel(
        system=system,
        joints=JointMap(_forward_map(build), InverseKinematics(coordinates), joint_names),
        keypoint_names=tuple(k.name for k in chosen),
        joint_names=joint_names,
        joint_coordinates=coordinates,
        actuator_names=tuple(actuator_name(model, a) for a in range(model.nu)),
        actuator_joints=tuple(joint_names[j] for j in actuated),
        basis=tuple(tuple(float(v) + 0.0 for v in row) for row in plane.basis),
        include=include,
        joint_limits=joint_limits,
    )
