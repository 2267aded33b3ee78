"""The joints of a planar chain of keypoints: read from a KeyCLD model's constraints
(`joint_structure`), or from the scene its frames were rendered from (`scene_joints`).

A KeyCLD model of a planar chain knows its joints only through its constraints: `Anchor(i)` hinges
keypoint `i` about a fixed point, `Distance(i, j)` hinges `j` about `i`, `FixedCoordinate(i, axis=1)`
slides `i` along a horizontal rail (a one-row `LinearConstraint`, along a rail at an angle).
`joint_structure` reads those into joint coordinates and the map from joints to keypoints, with the
link lengths measured on the data (the constraints' values along the runs: only their Jacobians enter
the dynamics, so a learnt model carries no lengths of its own). The other forms a scene's constraints
take in the image (keypoints tied to a body, a slide on a turning body, a hinge whose anchor is no
keypoint) fix their geometry, and `scene_joints` reads the joints from the scene itself.
"""

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

import cldyn
from cldyn._constraint import Anchor, Distance, FixedCoordinate, LinearConstraint, NormConstraint, Stack

_LENGTH_TOL = 0.25  # relative: a hinge's distance from an anchor off the keypoints, against the scene's
_COLLAPSED = 0.1  # a distance the keypoints keep below this fraction of the scene's: collapsed


@dataclasses.dataclass(frozen=True)
class _Joint:
    kind: str  # "hinge" or "slide"
    keypoint: int  # the keypoint this joint places
    parent: int | None  # the keypoint it hangs from (None: a fixed point)
    relative: bool  # a hinge measured from its parent link's direction (else from straight down)
    level: float  # link length (hinge) or the rail's offset along its normal (slide)
    pivot: tuple[float, float] = (0.0, 0.0)
    axis: tuple[float, float] = (1.0, 0.0)
    normal: tuple[float, float] = (0.0, 1.0)  # a slide's rail normal: x = q axis + level normal
    free: bool = False  # one of the two slides of an unconstrained keypoint


def _leaves(constraint) -> list:
    if constraint is None:
        return []
    if isinstance(constraint, Stack):
        return [leaf for part in constraint.constraints for leaf in _leaves(part)]
    return [constraint]


def _rail(leaf: LinearConstraint, count: int) -> tuple[int, tuple[float, float]] | None:
    """`(keypoint, unit normal)` of a linear constraint that is one rail: one row on one keypoint."""
    rows = np.asarray(leaf.rows, dtype=float)
    if rows.shape != (1, 2 * count):
        return None
    used = np.flatnonzero(rows[0])
    if len(used) == 0 or used[0] // 2 != used[-1] // 2:
        return None
    i = int(used[0] // 2)
    normal = rows[0, 2 * i : 2 * i + 2] / np.linalg.norm(rows[0, 2 * i : 2 * i + 2])
    return i, (float(normal[0]), float(normal[1]))


def _chain(constraint, x: np.ndarray) -> list[_Joint]:
    """The joints of a planar chain of keypoints, in the order that places them, from its constraints."""
    count = x.shape[-1] // 2
    points = x.reshape(-1, count, 2)
    placed_by: dict[int, object] = {}
    normals: dict[int, tuple[float, float]] = {}  # the rails' normals, by the keypoint on each
    for leaf in _leaves(constraint):
        rail = _rail(leaf, count) if isinstance(leaf, LinearConstraint) else None
        if isinstance(leaf, Anchor):
            child = leaf.keypoint
        elif isinstance(leaf, Distance):
            child = leaf.second
        elif isinstance(leaf, FixedCoordinate) and leaf.dim == 2:
            child = leaf.keypoint
        elif rail is not None:
            child, normals[rail[0]] = rail
        else:
            raise ValueError(
                f"joints from keypoints: constraint {type(leaf).__name__} is not one of a planar chain "
                "(Anchor, Distance, FixedCoordinate, or a LinearConstraint of one row on one keypoint)"
            )
        if child in placed_by:
            raise ValueError(f"joints from keypoints: keypoint {child} is constrained twice (a closed loop)")
        placed_by[child] = leaf
    joints: list[_Joint] = []
    hinged: set[int] = set()  # keypoints placed by a hinge: a child's angle is measured from their link

    def place(i: int, visiting: tuple[int, ...] = ()) -> None:
        if any(j.keypoint == i for j in joints):
            return
        if i in visiting:
            raise ValueError(f"joints from keypoints: the constraints form a loop through keypoint {i}")
        leaf = placed_by.get(i)
        if leaf is None:  # a free keypoint: two slides
            for axis in ((1.0, 0.0), (0.0, 1.0)):
                joints.append(_Joint("slide", i, None, False, 0.0, axis=axis, free=True))
            return
        if isinstance(leaf, Anchor):
            pivot = tuple(float(v) for v in leaf.point)
            length = float(np.median(np.linalg.norm(points[:, i] - np.asarray(pivot), axis=-1)))
            joints.append(_Joint("hinge", i, None, False, length, pivot=pivot))
            hinged.add(i)
        elif isinstance(leaf, Distance):
            parent = leaf.first
            place(parent, (*visiting, i))
            length = float(np.median(np.linalg.norm(points[:, i] - points[:, parent], axis=-1)))
            joints.append(_Joint("hinge", i, parent, parent in hinged, length))
            hinged.add(i)
        elif isinstance(leaf, FixedCoordinate):  # the other coordinate slides
            axis, normal = ((1.0, 0.0), (0.0, 1.0)) if leaf.axis == 1 else ((0.0, 1.0), (1.0, 0.0))
            level = float(np.median(points[:, i, leaf.axis]))
            joints.append(_Joint("slide", i, None, False, level, axis=axis, normal=normal))
        else:  # a rail at an angle: along it, positive to the right (or up, for a vertical rail)
            normal = normals[i]
            along = np.array([normal[1], -normal[0]])
            if along[0] < -1e-12 or (abs(along[0]) <= 1e-12 and along[1] < 0):
                along = -along
            axis = (float(along[0]), float(along[1]))
            level = float(np.median(points[:, i] @ np.asarray(normal)))
            joints.append(_Joint("slide", i, None, False, level, axis=axis, normal=normal))

    for i in range(count):
        place(i)
    return joints


def _coordinate(joint: _Joint, parents: dict[int, int | None]) -> cldyn.AbstractCoordinate:
    if joint.kind == "slide":
        return cldyn.SliderPosition(joint.keypoint, axis=joint.axis)
    if joint.parent is None:
        return cldyn.HingeAngle(child=(None, joint.keypoint), pivot=joint.pivot)
    if joint.relative:  # from the direction of the parent's own link
        grandparent = parents.get(joint.parent)
        return cldyn.HingeAngle(child=(joint.parent, joint.keypoint), parent=(grandparent, joint.parent))
    return cldyn.HingeAngle(child=(joint.parent, joint.keypoint))


class _Forward(eqx.Module):
    """`x = F(q)` of a planar chain: hinges measured from straight down or from their parent link."""

    joints: tuple[_Joint, ...] = eqx.field(static=True)
    count: int = eqx.field(static=True)

    def __call__(self, q):
        positions: dict[int, jax.Array] = {}
        angles: dict[int, jax.Array] = {}
        free: dict[int, list] = {}
        for index, joint in enumerate(self.joints):
            if joint.kind == "slide":
                if joint.free:  # an unconstrained keypoint: its two coordinates
                    free.setdefault(joint.keypoint, []).append(q[index])
                    if len(free[joint.keypoint]) == 2:
                        positions[joint.keypoint] = jnp.stack(free[joint.keypoint])
                    continue
                along = q[index] * jnp.asarray(joint.axis, dtype=q.dtype)
                across = joint.level * jnp.asarray(joint.normal, dtype=q.dtype)
                positions[joint.keypoint] = along + across
                continue
            angle = q[index] + (angles[joint.parent] if joint.relative else 0.0)
            if joint.parent is None:
                base = jnp.asarray(joint.pivot, dtype=q.dtype)
            else:
                base = positions[joint.parent]
            positions[joint.keypoint] = base + joint.level * jnp.stack([jnp.sin(angle), -jnp.cos(angle)])
            angles[joint.keypoint] = angle
        return jnp.concatenate([positions[i] for i in range(self.count)])


class _Inverse(eqx.Module):
    coordinates: tuple[cldyn.AbstractCoordinate, ...]

    def __call__(self, x):
        return jnp.stack([c(x) for c in self.coordinates])


@dataclasses.dataclass(frozen=True)
class JointStructure:
    """The joints of a planar chain of keypoints, read from a KeyCLD model's constraints.

    **Fields:**

    - `names`: one name per joint (MuJoCo's joint names where given).
    - `kinds`: `"hinge"` or `"slide"` per joint.
    - `coordinates`: name -> `cldyn.AbstractCoordinate` (`HingeAngle`, `SliderPosition`), what
      `cldyn.identify`'s `joint_coordinates` takes.
    - `joint_map`: the `cldyn.JointMap` between joints and keypoints, with link lengths measured on the
      data.
    - `levels`: the measured link lengths (hinges) and rail heights (slides), in keypoint units
      (`joint_structure`); empty where the geometry is the scene's (`scene_joints`).
    """

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    coordinates: dict[str, cldyn.AbstractCoordinate]
    joint_map: cldyn.JointMap
    levels: tuple[float, ...]


def joint_structure(
    constraint: cldyn.AbstractConstraint | None,
    x: Float[ArrayLike, "*batch k"],
    names: Sequence[str] | None = None,
) -> JointStructure:
    """The joints of a planar chain of keypoints, from the constraints that tie them.

    `Anchor(i)` is a hinge about a fixed point, `Distance(i, j)` a hinge of `j` about `i` (measured
    from the direction of the link before it when `i` is itself hinged, as MuJoCo's hinges are), and
    `FixedCoordinate(i, axis)` a slide along the other axis and a one-row `LinearConstraint` on one
    keypoint a slide along its rail (rightwards, or upwards for a vertical rail); a keypoint without a
    constraint is two slides. Hinge angles are counter-clockwise from straight down (or from the parent link).

    **Arguments:**

    - `constraint`: the model's constraint (`model.constraint`).
    - `x`: keypoints `(..., k)` on which the link lengths and rail heights are measured (medians).
    - `names`: a name per joint in the order of the keypoints they place (e.g. MuJoCo's joint names
      of the scene); `joint_0`, `joint_1`, ... by default.

    **Returns:** a `keyvision.JointStructure`. Constraints that are not a planar chain (a keypoint
    constrained twice, a loop, other kinds of constraint) raise a `ValueError` that says which.

    !!! example

        ```python
        structure = keyvision.joint_structure(cldyn.keycld_constraint("acrobot"), keypoints,
                                              names=["shoulder", "elbow"])
        ```
    """
    x = np.asarray(x, dtype=float)
    if x.ndim < 1 or x.shape[-1] % 2:
        raise ValueError(f"joint_structure: keypoints must be (..., k) with k even, got {x.shape}")
    joints = _chain(constraint, x)
    if names is None:
        names = [f"joint_{i}" for i in range(len(joints))]
    names = tuple(str(n) for n in names)
    if len(names) != len(joints):
        raise ValueError(f"joint_structure: {len(names)} names for the chain's {len(joints)} joints")
    parents = {j.keypoint: j.parent for j in joints if j.kind == "hinge"}
    coordinates = tuple(_coordinate(j, parents) for j in joints)
    joint_map = cldyn.JointMap(
        forward=_Forward(tuple(joints), x.shape[-1] // 2), inverse=_Inverse(coordinates), names=names
    )
    return JointStructure(
        names=names,
        kinds=tuple(j.kind for j in joints),
        coordinates=dict(zip(names, coordinates)),
        joint_map=joint_map,
        levels=tuple(j.level for j in joints),
    )


# the joint kind of each coordinate from_mjcf reads a joint by
_KINDS = {"HingeAngle": "hinge", "FrameAngle": "hinge", "SliderPosition": "slide", "FrameSlide": "slide"}


class _Through(cldyn.AbstractCoordinate):
    """A coordinate of the scene's planar keypoints read on image keypoints, `q(M x + t) / s`: `M`, `t`
    the camera's map (and any move of the keypoints before it), `s` metres per image unit for a slide."""

    coordinate: cldyn.AbstractCoordinate
    matrix: Float[jax.Array, "k k"]
    shift: Float[jax.Array, " k"]
    scale: float = eqx.field(static=True)

    def __call__(self, x):
        matrix, shift = jax.lax.stop_gradient((self.matrix.astype(x.dtype), self.shift.astype(x.dtype)))
        return self.coordinate(matrix @ x + shift) / self.scale


class _ThroughForward(eqx.Module):
    """`x = M^-1 (F(s q) - t)`: slides from image units to metres, the scene's forward kinematics, then
    back through the map of `_Through`."""

    forward: eqx.Module
    matrix: Float[jax.Array, "k k"]
    shift: Float[jax.Array, " k"]
    scales: tuple[float, ...] = eqx.field(static=True)

    def __call__(self, q):
        matrix, shift = jax.lax.stop_gradient((self.matrix.astype(q.dtype), self.shift.astype(q.dtype)))
        return jnp.linalg.solve(matrix, self.forward(q * jnp.asarray(self.scales, dtype=q.dtype)) - shift)


@dataclasses.dataclass(frozen=True)
class _Scene:
    """The scene's joints in its plane (`cldyn.mujoco.from_mjcf`) and the camera's map to them,
    `plane = M x + t` on the stacked keypoints."""

    bridge: object
    kinds: tuple[str, ...]
    scales: tuple[float, ...]
    matrix: np.ndarray
    shift: np.ndarray

    def structure(self, matrix: np.ndarray, shift: np.ndarray) -> JointStructure:
        """The joints on keypoints `x` that `M x + t` maps to the image's."""
        matrix, shift = jnp.asarray(self.matrix @ matrix), jnp.asarray(self.matrix @ shift + self.shift)
        bridge, names = self.bridge, tuple(self.bridge.joint_names)
        coordinates = tuple(
            _Through(c, matrix, shift, s) for c, s in zip(bridge.joint_coordinates, self.scales)
        )
        forward = _ThroughForward(bridge.joints.forward, matrix, shift, self.scales)
        joint_map = cldyn.JointMap(forward=forward, inverse=_Inverse(coordinates), names=names)
        return JointStructure(names, self.kinds, dict(zip(names, coordinates)), joint_map, levels=())


def _scene(frames) -> _Scene:
    from ._structure import scene_bridge

    bridge, linear, offset, _ = scene_bridge(frames, "scene_joints")
    metres = float(np.sqrt(abs(np.linalg.det(linear))))  # per image unit: the map is a similarity
    kinds = []
    for name, coordinate in zip(bridge.joint_names, bridge.joint_coordinates):
        kind = type(coordinate).__name__
        if kind not in _KINDS:
            raise ValueError(f"scene_joints: joint {name!r} is read by a {kind}, neither a hinge nor a slide")
        kinds.append(_KINDS[kind])
    scales = tuple(metres if kind == "slide" else 1.0 for kind in kinds)
    count = len(bridge.keypoint_names)
    return _Scene(bridge, tuple(kinds), scales, np.kron(np.eye(count), linear), np.tile(offset, count))


def scene_joints(frames) -> JointStructure:
    """The joints of the frames' scene, on its keypoints in the image frame.

    Where `joint_structure` reads the joints of a planar chain from a model's constraints, this reads
    them from the MuJoCo scene the frames were rendered from (`frames.info["mjcf_xml"]`, through
    `cldyn.mujoco.from_mjcf` on the frames' keypoints), and carries them through the camera's map:
    every tree of hinges and slides that `from_mjcf` reads, including those whose constraints in the
    image `joint_structure` cannot read (keypoints tied to a body that does not turn, a slide on a
    turning body, a hinge whose anchor is no keypoint). The coordinates are MuJoCo's `qpos` (its
    joint names, its zero; hinge angles in radians wrapped into `[-pi, pi)`), its slides in image
    units as `joint_structure`'s (MuJoCo's metres over the camera's metres per image unit);
    the geometry (link lengths, anchors, rails) is the scene's, as `keyvision.scene_constraint` gives
    the model trained on these frames, not measured on keypoints.

    **Arguments:**

    - `frames`: rendered frames (`keyvision.render`), with their MJCF and camera.

    **Returns:** a `keyvision.JointStructure` whose `levels` are empty (nothing measured). A camera
    that is not a similarity, or keypoints that cannot carry the scene's turning bodies, raise a
    `ValueError` that says which.

    !!! example

        ```python
        structure = keyvision.scene_joints(frames)      # a bead on a swinging arm: hinge, slide
        q = structure.joint_map.joints(x)   # MuJoCo's qpos from image keypoints x (slides in image units)
        ```
    """
    scene = _scene(frames)
    count = scene.shift.size
    return scene.structure(np.eye(count), np.zeros(count))


def _placed(leaf: NormConstraint, linear: np.ndarray) -> int | None:
    """The keypoint `k` that `|d(x)|` places, `d = x_k - o(x)` in the scene's plane with `o` affine in
    the other keypoints: the one whose block of `d`'s matrix is the camera's map to the plane,
    `linear` (the identity on the plane's coordinates); None where there is no such one keypoint."""
    matrix = np.asarray(leaf.difference.matrix, dtype=float)
    blocks = matrix.reshape(2, -1, 2).transpose(1, 0, 2) @ np.linalg.inv(linear)
    found = [k for k, block in enumerate(blocks) if np.allclose(block, np.eye(2), atol=1e-9)]
    return found[0] if len(found) == 1 else None


def _is_chain(constraint, count: int) -> bool:
    """Whether `joint_structure` reads every constraint: Anchor, Distance, a planar FixedCoordinate,
    a one-row LinearConstraint on one keypoint."""
    for leaf in _leaves(constraint):
        if isinstance(leaf, Anchor | Distance) or (isinstance(leaf, FixedCoordinate) and leaf.dim == 2):
            continue
        if not (isinstance(leaf, LinearConstraint) and _rail(leaf, count) is not None):
            return False
    return True


def model_joints(constraint, x: np.ndarray, frames, names: Sequence[str] | None) -> JointStructure:
    """The joints of a model's keypoints: `joint_structure` where its constraints are a planar chain
    that it reads, the scene's (`scene_joints`) where they are forms whose geometry only the scene
    gives."""
    if _is_chain(constraint, x.shape[-1] // 2):
        return joint_structure(constraint, x, names)
    scene = _scene(frames)
    if (seen := scene.shift.size) != x.shape[-1]:
        raise ValueError(
            f"identify: the model has {x.shape[-1] // 2} keypoints, its frames' scene {seen // 2}: "
            "the frames are not of the scene the model was trained on"
        )
    return scene.structure(*_to_scene_lengths(constraint, x.reshape(-1, x.shape[-1]), scene))


def _to_scene_lengths(constraint, x: np.ndarray, scene: _Scene) -> tuple[np.ndarray, np.ndarray]:
    """`(M, t)`, the model's keypoints moved to the scene's lengths, `x_scene = M x + t`: the scene's
    joints on keypoints that keep the model's constraints at their own.

    `Anchor` and `Distance` keep a distance at whatever value the estimator gives it, and a keypoint
    may sit anywhere along its link (the shipped pendulum's at a third of the pole). Each keypoint
    they place is moved along its ray from the pivot, or from its (moved) parent, by the ratio of the
    scene's distance to its median along the data: `x_scene = M x + t`, affine, and the scene's
    joints read `q(M x + t)`, its keypoints `M^-1 (F(q) - t)`. A hinge whose anchor is no keypoint,
    `|d(x)|` with `d = x_k - o(x)` for an affine anchor `o` of the other keypoints (a pole on a cart
    seen at its two ends), moves `x_k` along `d` from its (moved) anchor the same way. A distance kept
    below `_COLLAPSED` of the scene's (a keypoint drawn onto its pivot) carries no joint and is
    refused, as is a `|d(x)|` that places no one keypoint kept more than `_LENGTH_TOL` off the
    scene's."""
    count = x.shape[-1] // 2
    linear = scene.matrix[:2, :2]  # the camera's map from the image to the plane, per keypoint
    seen = scene.structure(np.eye(2 * count), np.zeros(2 * count)).joint_map
    at_rest = jnp.asarray(seen.keypoints(jnp.zeros(seen.num_joints)))  # the scene's keypoints, in the image
    blocks = {i: (np.eye(2 * count)[2 * i : 2 * i + 2], np.zeros(2)) for i in range(count)}
    pending, placed_by = [], {}  # placed_by: a NormConstraint's index -> the keypoint it places
    for index, leaf in enumerate(_leaves(constraint)):
        if not isinstance(leaf, Anchor | Distance | NormConstraint):
            continue
        found = float(np.median(np.asarray(jax.vmap(leaf)(jnp.asarray(x)))))
        target = float(np.asarray(leaf(at_rest))[0])
        placed = placed_by[index] = _placed(leaf, linear) if isinstance(leaf, NormConstraint) else None
        too_far = isinstance(leaf, NormConstraint) and abs(found - target) > _LENGTH_TOL * abs(target)
        if (too_far and placed is None) or found < _COLLAPSED * abs(target):
            # |d(x)| measures in the scene's plane, the rods in the image
            units = "m of the scene's plane" if isinstance(leaf, NormConstraint) else "image units"
            raise ValueError(
                f"identify: the model's keypoints keep constraint {index} ({type(leaf).__name__}) at "
                f"{found:.4g} {units}, the scene at {target:.4g}: its estimator does not place the "
                "keypoints where the scene's are, and the scene's joints (keyvision.scene_joints) cannot "
                "be read from them (keyvision train --candidates N picks, of N initialisations, the "
                "one whose keypoints best keep the constraints)"
            )
        if not isinstance(leaf, NormConstraint) or placed is not None:
            pending.append((index, leaf, target / found))

    def rows(k):  # keypoint k's two coordinates picked from x
        return np.eye(2 * count)[2 * k : 2 * k + 2]

    def moves(index, leaf) -> int:  # the keypoint a constraint moves
        if isinstance(leaf, Anchor):
            return leaf.keypoint
        return leaf.second if isinstance(leaf, Distance) else placed_by[index]

    def after(index, leaf) -> set:  # the keypoints whose moved places it needs first
        if isinstance(leaf, Anchor):
            return set()
        if isinstance(leaf, Distance):
            return {leaf.first}
        anchor = np.abs(np.asarray(leaf.difference.matrix)).reshape(2, count, 2).sum(axis=(0, 2)) > 0
        return set(np.flatnonzero(anchor)) - {moves(index, leaf)}

    while pending:  # a rod's child after its parent
        waiting = {moves(index, leaf) for index, leaf, _ in pending}
        ready = [item for item in pending if not after(*item[:2]) & waiting]
        if not ready:
            raise ValueError("identify: the constraints' rods form a loop")
        for index, leaf, ratio in ready:
            if isinstance(leaf, Anchor):
                k, point = leaf.keypoint, np.asarray(leaf.point, dtype=float)
                blocks[k] = (ratio * rows(k), (1 - ratio) * point)
            elif isinstance(leaf, Distance):  # x'_j = x'_i + ratio (x_j - x_i)
                (a, b), i, j = blocks[leaf.first], leaf.first, leaf.second
                blocks[j] = (a + ratio * (rows(j) - rows(i)), b)
            else:  # d(x) = L (x_k - o(x)), L the map to the plane: x'_k = o(x') + ratio L^-1 d(x)
                k, matrix = placed_by[index], np.asarray(leaf.difference.matrix, dtype=float)
                const, inverse = np.asarray(leaf.difference.const, dtype=float), np.linalg.inv(linear)
                others = matrix - linear @ rows(k)  # o(x) = -L^-1 (others x + const): zero on x_k
                moved = np.concatenate([blocks[i][0] for i in range(count)])
                shift = np.concatenate([blocks[i][1] for i in range(count)])
                blocks[k] = (
                    inverse @ (ratio * matrix - others @ moved),
                    inverse @ ((ratio - 1) * const - others @ shift),
                )
        done = {index for index, _, _ in ready}
        pending = [item for item in pending if item[0] not in done]
    matrix = np.concatenate([blocks[i][0] for i in range(count)])
    return matrix, np.concatenate([blocks[i][1] for i in range(count)])
