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

from .._constraint import AbstractConstraint, Anchor, Distance, FixedCoordinate, FromFunction, Stack
from .._coordinates import AbstractCoordinate, HingeAngle, JointMap, SliderPosition, wrap_angle
from .._dissipation import JointDamping
from .._input import JointInput
from .._mass import ConstantMass, JointArmature
from .._potential import AbstractPotential, Gravity, JointSpring
from .._system import ConstrainedLagrangian
from ._scenes import load_model, scene_xml
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
    name_of,
    reference_data,
    select_keypoints,
)

INCLUDABLE = ("damping", "stiffness", "armature")


def _cmat(c: np.ndarray) -> np.ndarray:
    """Left multiplication by the complex number `c` as a 2x2 matrix."""
    return np.array([[c[0], -c[1]], [c[1], c[0]]])


def _conj(c: np.ndarray) -> np.ndarray:
    return np.array([c[0], -c[1]])


@dataclasses.dataclass(frozen=True)
class _Affine:
    """`y(x) = matrix @ x + const`, planar: `matrix` `(2, k)`, `const` `(2,)`."""

    matrix: np.ndarray
    const: np.ndarray

    def left(self, a: np.ndarray) -> "_Affine":
        """`a @ y(x)` for a `(2, 2)` matrix `a`."""
        return _Affine(a @ self.matrix, a @ self.const)

    def __add__(self, other: "_Affine") -> "_Affine":
        return _Affine(self.matrix + other.matrix, self.const + other.const)

    def __sub__(self, other: "_Affine") -> "_Affine":
        return _Affine(self.matrix - other.matrix, self.const - other.const)

    @property
    def is_constant(self) -> bool:
        return not np.any(self.matrix)

    def static(self) -> tuple:
        return (
            tuple(tuple(float(v) for v in row) for row in self.matrix),
            tuple(float(v) for v in self.const),
        )


def _evaluate(affine: tuple, x):
    matrix, const = affine
    return jnp.asarray(matrix, dtype=x.dtype) @ x + jnp.asarray(const, dtype=x.dtype)


@dataclasses.dataclass(frozen=True)
class _Segment:
    """A direction fixed in a group, from keypoint `tail` (or the fixed `pivot`) to keypoint `head`."""

    tail: int | None
    head: int
    pivot: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class _Frame:
    """A rigid group's pose, affine in the keypoints (see the module docstring)."""

    origin: _Affine
    origin0: np.ndarray
    rotation: _Affine
    # How HingeAngle can read the orientation: "fixed" for a group that never rotates, a segment,
    # or None when only the general frame can.
    segment: "_Segment | str | None"

    def point(self, y0: np.ndarray) -> _Affine:
        """The current position of the group's point with reference position `y0`."""
        return self.origin + self.rotation.left(_cmat(y0 - self.origin0))

    @property
    def rotates(self) -> bool:
        return not self.rotation.is_constant


class _FrameAngle(AbstractCoordinate):
    """A hinge angle read from two rigid groups' frames: `wrap(s * arg(z_child conj(z_parent)) - q0)`.

    Used where `HingeAngle` cannot express the hinge (its anchor is no keypoint).
    """

    child: tuple = eqx.field(static=True)
    parent: tuple = eqx.field(static=True)
    sign: float = eqx.field(static=True)
    offset: float = eqx.field(static=True)

    def __call__(self, x):
        zc, zp = _evaluate(self.child, x), _evaluate(self.parent, x)
        cross = zp[0] * zc[1] - zp[1] * zc[0]
        dot = zp[0] * zc[0] + zp[1] * zc[1]
        return wrap_angle(self.sign * jnp.arctan2(cross, dot) - self.offset)


class _FrameSlide(AbstractCoordinate):
    """A slide position read from frames: `q(x) = d(x) . u(x) - q0`, with `d` the displacement of the
    sliding keypoint from its reference point in the parent and `u` the slide axis, both affine.

    Used where `SliderPosition` cannot express the slide (a slide on a moving parent).
    """

    displacement: tuple = eqx.field(static=True)
    axis: tuple = eqx.field(static=True)
    offset: float = eqx.field(static=True)

    def __call__(self, x):
        return jnp.dot(_evaluate(self.displacement, x), _evaluate(self.axis, x)) - self.offset


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

    def project(self, points) -> np.ndarray:
        """Planar coordinates of world points: shape `(..., 3) -> (..., 2)`."""
        return np.asarray(points) @ np.asarray(self.basis).T

    def coordinate(self, joint: str) -> AbstractCoordinate:
        """The cldyn coordinate of the MuJoCo joint named `joint`."""
        if joint not in self.joint_names:
            raise KeyError(f"no joint named {joint!r}; the joints are {list(self.joint_names)}")
        return self.joint_coordinates[self.joint_names.index(joint)]


# -- checks: the class of models this bridge is exact for ------------------------------------------


def _check_supported(model: mujoco.MjModel, tree: Tree) -> None:
    if model.ntendon:
        name = name_of(model, mujoco.mjtObj.mjOBJ_TENDON, 0, "tendon")
        raise ValueError(f"tendon {name!r}: tendons are not supported by from_mjcf")
    if model.neq and not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EQUALITY:
        name = name_of(model, mujoco.mjtObj.mjOBJ_EQUALITY, 0, "equality")
        raise ValueError(f"equality constraint {name!r}: equality constraints are not supported by from_mjcf")
    if getattr(model, "nflex", 0):
        raise ValueError("flex elements (deformable bodies) are not supported by from_mjcf")
    for g in tree.moving:
        joints = tree.joints[g]
        if len(joints) > 1:
            names = [joint_name(model, j) for j in joints]
            raise ValueError(
                f"body {body_name(model, g)!r} has {len(joints)} joints {names}; from_mjcf supports one "
                "hinge or slide per body (nest bodies to chain joints)"
            )
    for b in range(1, model.nbody):
        if model.body_gravcomp[b] != 0:
            raise ValueError(f"body {body_name(model, b)!r} has gravcomp, which from_mjcf does not model")
    if model.opt.density > 0 or model.opt.viscosity > 0:
        raise ValueError("fluid forces (option density/viscosity) are not modelled by from_mjcf")
    _check_contacts(model, tree)
    _check_actuators(model)


def _check_contacts(model: mujoco.MjModel, tree: Tree) -> None:
    flags = model.opt.disableflags
    if flags & (mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT):
        return
    filter_parent = not flags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    excluded = set(int(s) for s in model.exclude_signature)

    def collide(g1, g2, b1, b2):
        if g1 == g2 or g1 == 0 or g2 == 0:
            return False
        if filter_parent and (tree.parent[g1] == g2 or tree.parent[g2] == g1):
            return False
        return ((min(b1, b2) << 16) + max(b1, b2)) not in excluded

    for i in range(model.npair):
        a, b = int(model.pair_geom1[i]), int(model.pair_geom2[i])
        ba, bb = int(model.geom_bodyid[a]), int(model.geom_bodyid[b])
        if tree.group[ba] and tree.group[bb] and tree.group[ba] != tree.group[bb]:
            raise ValueError(
                f"contact pair {_geom(model, a)!r}-{_geom(model, b)!r} between moving bodies "
                "is not supported by from_mjcf"
            )
    geoms = range(model.ngeom)
    for a in geoms:
        for b in range(a + 1, model.ngeom):
            ba, bb = int(model.geom_bodyid[a]), int(model.geom_bodyid[b])
            if not collide(int(tree.group[ba]), int(tree.group[bb]), ba, bb):
                continue
            if (model.geom_contype[a] & model.geom_conaffinity[b]) or (
                model.geom_contype[b] & model.geom_conaffinity[a]
            ):
                raise ValueError(
                    f"geoms {_geom(model, a)!r} and {_geom(model, b)!r} on moving bodies "
                    f"{body_name(model, ba)!r} and {body_name(model, bb)!r} can collide; from_mjcf does "
                    "not model contacts (disable contact, or set contype/conaffinity)"
                )


def _geom(model, g: int) -> str:
    return name_of(model, mujoco.mjtObj.mjOBJ_GEOM, g, "geom")


def _actuator(model, a: int) -> str:
    return name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator")


def _check_actuators(model: mujoco.MjModel) -> None:
    for a in range(model.nu):
        trn = mujoco.mjtTrn(int(model.actuator_trntype[a]))
        if trn != mujoco.mjtTrn.mjTRN_JOINT:
            raise ValueError(
                f"actuator {_actuator(model, a)!r} uses a {trn.name} transmission; from_mjcf supports "
                "motors on hinge and slide joints"
            )
        plain = (
            model.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
            and model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
            and model.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
        )
        if not plain:
            raise ValueError(
                f"actuator {_actuator(model, a)!r} is not a motor (its force depends on state or "
                "activation); from_mjcf supports <motor> actuators"
            )


def _check_include(include) -> tuple[str, ...]:
    if isinstance(include, str):
        include = (include,)
    include = tuple(include)
    for name in include:
        if name == "frictionloss":
            raise ValueError(
                "include: frictionloss is dry friction, a constraint in MuJoCo, not a smooth force, so "
                "it cannot be included exactly; cldyn.JointCoulomb approximates it. Allowed: "
                f"{', '.join(INCLUDABLE)}"
            )
        if name not in INCLUDABLE:
            raise ValueError(f"include: unknown effect {name!r}; allowed: {', '.join(INCLUDABLE)}")
    return include


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

    def constant(self, value: np.ndarray) -> _Affine:
        return _Affine(np.zeros((2, self.size)), np.asarray(value, dtype=float))

    def select(self, i: int) -> _Affine:
        matrix = np.zeros((2, self.size))
        matrix[:, 2 * i : 2 * i + 2] = np.eye(2)
        return _Affine(matrix, np.zeros(2))

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
            rotation = (self.select(k) - origin).left(_cmat(_conj(w0) / np.dot(w0, w0)))
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
            self.constraints.append(_norm_constraint(self.select(head) - origin))
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
        return _FrameAngle(frame.rotation.static(), parent.rotation.static(), sign, -qpos0)

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
            self.constraints.append(_bilinear_constraint(displacement, parent.rotation.left(_cmat(normal))))
        self._attach(frame, [i for i in new if i != k])

        qpos0 = float(model.qpos0[model.jnt_qposadr[j]])
        if _on_world(self.tree, g):
            self.coordinates[j] = SliderPosition(k, axis=axis, origin=self.x0[k], offset=-qpos0)
        else:
            self.coordinates[j] = _FrameSlide(
                displacement.static(), parent.rotation.left(_cmat(axis)).static(), -qpos0
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
            constraints.append(_linear_constraint(rows))
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


def _linear_constraint(rows: np.ndarray) -> FromFunction:
    """Linear constraints `rows @ x = const`: points attached to a frame, slides on a fixed line."""

    def phi(x):
        return jnp.asarray(rows, dtype=x.dtype) @ x

    return FromFunction(phi, rows.shape[0])


def _norm_constraint(difference: _Affine) -> FromFunction:
    """`|d(x)| = const` for an affine `d`: a keypoint at a fixed distance from a hinge anchor that is
    no keypoint itself."""
    static = difference.static()

    def phi(x):
        d = _evaluate(static, x)
        return jnp.sqrt(jnp.sum(d**2))[None]

    return FromFunction(phi, 1)


def _bilinear_constraint(displacement: _Affine, normal: _Affine) -> FromFunction:
    """`d(x) . n(x) = const`: a keypoint slides along a line fixed in a rotating parent."""
    d, n = displacement.static(), normal.static()

    def phi(x):
        return jnp.dot(_evaluate(d, x), _evaluate(n, x))[None]

    return FromFunction(phi, 1)


def _forward_map(build: _Build):
    """`qpos -> x`: planar forward kinematics of the tree, from the reference configuration."""
    model, tree, plane, data = build.model, build.tree, build.plane, build.data
    steps = []
    for g in tree.moving:
        j = tree.joints[g][0]
        hinge = model.jnt_type[j] == _HINGE
        anchor = plane.project(data.xanchor[j])
        axis = plane.project(data.xaxis[j])
        sign = float(np.sign(np.dot(data.xaxis[j], plane.normal)))
        steps.append(
            (
                g,
                tree.parent[g],
                hinge,
                anchor,
                axis / max(np.linalg.norm(axis), TOL),
                sign,
                int(model.jnt_qposadr[j]),
                float(model.qpos0[model.jnt_qposadr[j]]),
            )
        )
    x0 = build.x0
    homes = list(build.introduced)

    def rotation(angle):
        c, s = jnp.cos(angle), jnp.sin(angle)
        return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])

    def forward(qpos):
        angle = {0: jnp.zeros((), dtype=qpos.dtype)}
        shift = {0: jnp.zeros(2, dtype=qpos.dtype)}
        for g, p, hinge, anchor, axis, sign, adr, q0 in steps:
            dq = qpos[adr] - q0
            parent_rotation = rotation(angle[p])
            if hinge:
                phi = sign * dq
                angle[g] = angle[p] + phi
                shift[g] = parent_rotation @ (anchor - rotation(phi) @ anchor) + shift[p]
            else:
                angle[g] = angle[p]
                shift[g] = parent_rotation @ (axis * dq) + shift[p]
        points = [rotation(angle[h]) @ x0[i] + shift[h] for i, h in enumerate(homes)]
        return jnp.concatenate(points)

    return forward


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

    Not modelled: joint limits, control and force clamping (`ctrllimited`, `forcelimited`), contacts
    with the world, `frictionloss`. Outside the class, with an error that names the element: ball and
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
    joints and actuators. Build it after `jax.config.update("jax_enable_x64", True)` for float64.

    !!! example

        ```python
        bridge = cldyn.mujoco.from_mjcf("keycld/acrobot")
        x, xd = bridge.joints.to_keypoints(jnp.array([0.3, -0.2]), jnp.zeros(2))
        xdd = bridge.system.acceleration(x, xd, jnp.array([0.5, 0.0]))
        ```
    """
    key = (
        scene_xml(mjcf),
        None if keypoints is None else tuple(keypoints),
        tuple(include),
        bool(jax.config.jax_enable_x64),
    )
    if key not in _BUILT:
        if len(_BUILT) >= _BUILT_MAX:
            _BUILT.pop(next(iter(_BUILT)))
        _BUILT[key] = _from_mjcf(mjcf, keypoints=keypoints, include=include)
    return _BUILT[key]


# Built models are immutable; handing out the same object for the same scene lets every jitted function
# that takes it hit JAX's compilation cache (the joint maps are static functions, new at every build).
_BUILT: dict = {}
_BUILT_MAX = 32


def _from_mjcf(mjcf, *, keypoints, include) -> "MujocoModel":
    include = _check_include(include)
    model, _, _ = load_model(mjcf)
    data = reference_data(model)
    plane = find_plane(model, data)
    tree = build_tree(model)
    _check_supported(model, tree)
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

    system = ConstrainedLagrangian(
        mass=ConstantMass(jnp.asarray(build.mass)),
        potential=potential,
        constraint=constraint,
        input_matrix=input_matrix,
        dissipation=dissipation,
        armature=armature,
    )
    inverse_coordinates = coordinates

    def inverse(x):
        return jnp.stack([c(x) for c in inverse_coordinates])

    return MujocoModel(
        system=system,
        joints=JointMap(_forward_map(build), inverse, joint_names),
        keypoint_names=tuple(k.name for k in chosen),
        joint_names=joint_names,
        joint_coordinates=coordinates,
        actuator_names=tuple(_actuator(model, a) for a in range(model.nu)),
        actuator_joints=tuple(joint_names[j] for j in actuated),
        basis=tuple(tuple(float(v) + 0.0 for v in row) for row in plane.basis),
        include=include,
    )
