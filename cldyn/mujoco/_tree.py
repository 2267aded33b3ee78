"""The kinematic structure of a compiled MuJoCo model: its plane of motion, its rigid groups of bodies
and the keypoints that carry them.

Everything here is read from the model in its reference configuration `qpos0`, in plain numpy.
"""

import dataclasses

import mujoco
import numpy as np

# Points closer than this (metres) are the same point; axes closer than this (radians) are parallel.
TOL = 1e-9

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)


class NotPlanarError(ValueError):
    """The model is not a planar mechanism of parallel hinges and in-plane slides."""


def name_of(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int, fallback: str) -> str:
    """An element's name, or `fallback<index>` for unnamed elements."""
    name = mujoco.mj_id2name(model, kind, index)
    return name if name else f"{fallback}{index}"


def joint_name(model: mujoco.MjModel, j: int) -> str:
    """The name of joint `j`."""
    return name_of(model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint")


def body_name(model: mujoco.MjModel, b: int) -> str:
    """The name of body `b`."""
    return name_of(model, mujoco.mjtObj.mjOBJ_BODY, b, "body")


def reference_data(model: mujoco.MjModel) -> mujoco.MjData:
    """Data with the kinematics of the reference configuration `qpos0` computed."""
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    mujoco.mj_kinematics(model, data)
    return data


@dataclasses.dataclass(frozen=True)
class Plane:
    """The plane of motion: world point `p` has planar coordinates `basis @ p`.

    `basis` holds the in-plane unit vectors `e1, e2` as rows, with `e2` pointing up (against the
    in-plane part of gravity) when gravity has one; `normal` is `e1 x e2`; `gravity` is the magnitude
    of the in-plane gravity, which points along `-e2`.
    """

    basis: np.ndarray
    normal: np.ndarray
    gravity: float

    def project(self, points: np.ndarray) -> np.ndarray:
        """Planar coordinates of world points, shape `(..., 3) -> (..., 2)`."""
        return np.asarray(points) @ self.basis.T


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _gravity(model: mujoco.MjModel) -> np.ndarray:
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        return np.zeros(3)
    return np.array(model.opt.gravity, dtype=float)


def find_plane(model: mujoco.MjModel, data: mujoco.MjData) -> Plane:
    """The plane of motion of a planar mechanism, or a `NotPlanarError` that names the element.

    The normal is the common hinge axis (or, without hinges, the normal of the slide axes); the
    in-plane basis is chosen so that world up maps to `+y` when gravity lies in the plane, and so
    that `e1` points along world `+x` where it can (dm_control's x-z scenes map `(x, z)` to `(x, y)`).
    """
    types = model.jnt_type
    for j in range(model.njnt):
        if types[j] in (_BALL, _FREE):
            kind = "ball" if types[j] == _BALL else "free"
            raise NotPlanarError(
                f"joint {joint_name(model, j)!r} is a {kind} joint; only hinge and slide joints "
                "move in a plane"
            )
    hinges = [j for j in range(model.njnt) if types[j] == _HINGE]
    slides = [j for j in range(model.njnt) if types[j] == _SLIDE]
    axes = {j: _unit(np.array(data.xaxis[j])) for j in hinges + slides}
    if hinges:
        normal = axes[hinges[0]]
        for j in hinges[1:]:
            if np.linalg.norm(np.cross(axes[j], normal)) > TOL:
                raise NotPlanarError(
                    f"hinge {joint_name(model, j)!r} has axis {np.round(axes[j], 6).tolist()}, not "
                    f"parallel to hinge {joint_name(model, hinges[0])!r} with axis "
                    f"{np.round(normal, 6).tolist()}: the mechanism is not planar"
                )
    elif slides:
        normal = None
        for j in slides[1:]:
            cross = np.cross(axes[slides[0]], axes[j])
            if np.linalg.norm(cross) > TOL:
                normal = _unit(cross)
                break
        if normal is None:  # motion along one line: any plane through it, preferably vertical
            cross = np.cross(axes[slides[0]], _gravity(model))
            if np.linalg.norm(cross) <= TOL:
                cross = np.cross(axes[slides[0]], np.eye(3)[np.argmin(np.abs(axes[slides[0]]))])
            normal = _unit(cross)
    else:
        raise NotPlanarError("the model has no hinge or slide joint: nothing moves")
    for j in slides:
        if abs(np.dot(axes[j], normal)) > TOL:
            raise NotPlanarError(
                f"slide {joint_name(model, j)!r} has axis {np.round(axes[j], 6).tolist()}, which leaves "
                f"the plane of motion (normal {np.round(normal, 6).tolist()})"
            )

    gravity = _gravity(model)
    in_plane = gravity - np.dot(gravity, normal) * normal
    magnitude = float(np.linalg.norm(in_plane))
    if magnitude > TOL * max(1.0, float(np.linalg.norm(gravity))):
        up = -in_plane / magnitude
    else:
        magnitude = 0.0
        for candidate in (np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]):
            up = candidate - np.dot(candidate, normal) * normal
            if np.linalg.norm(up) > 1e-6:
                break
        up = _unit(up)
    e1 = np.cross(up, normal)
    leading = e1[np.argmax(np.abs(e1) > 1e-9)]
    if leading < 0:
        normal, e1 = -normal, -e1
    return Plane(basis=np.stack([e1, up]), normal=normal, gravity=magnitude)


@dataclasses.dataclass(frozen=True)
class Tree:
    """Bodies welded together form rigid groups, named by their root body; group 0 is the world."""

    group: np.ndarray  # body -> group
    parent: dict  # group -> parent group
    joints: dict  # group -> joint ids, in order
    children: dict  # group -> child groups

    @property
    def moving(self) -> list[int]:
        """The moving groups, parents before children."""
        return sorted(self.parent)


def build_tree(model: mujoco.MjModel) -> Tree:
    """The rigid groups of bodies and how they hang together."""
    group = np.array(model.body_weldid, dtype=int)
    parent, joints, children = {}, {}, {0: []}
    for b in range(1, model.nbody):
        if group[b] != b:
            continue
        parent[b] = int(group[model.body_parentid[b]])
        joints[b] = [j for j in range(model.njnt) if model.jnt_bodyid[j] == b]
        children[b] = []
    for g, p in parent.items():
        children[p].append(g)
    return Tree(group=group, parent=parent, joints=joints, children=children)


def _axis_distance(point: np.ndarray, anchor: np.ndarray, axis: np.ndarray) -> float:
    return float(np.linalg.norm(np.cross(point - anchor, _unit(axis))))


def _pivots_about(model, data, tree: Tree, g: int, point: np.ndarray) -> bool:
    """Whether `point` lies on the rotation axis (or ball centre) of group `g`'s only joint."""
    joints = tree.joints.get(g, [])
    if len(joints) != 1:
        return False
    j = joints[0]
    if model.jnt_type[j] == _HINGE:
        return _axis_distance(point, data.xanchor[j], data.xaxis[j]) < TOL
    if model.jnt_type[j] == _BALL:
        return float(np.linalg.norm(point - data.xanchor[j])) < TOL
    return False


def fixed_in(model, data, tree: Tree, home: int, point: np.ndarray) -> frozenset[int]:
    """The groups in which a point of group `home` is fixed: a point on a hinge axis belongs to both
    sides of the hinge."""
    groups = {home}
    g = home
    while g != 0 and _pivots_about(model, data, tree, g, point):
        g = tree.parent[g]
        groups.add(g)
    stack = list(groups)
    while stack:
        g = stack.pop()
        for c in tree.children.get(g, []):
            if c not in groups and _pivots_about(model, data, tree, c, point):
                groups.add(c)
                stack.append(c)
    return frozenset(groups)


@dataclasses.dataclass(frozen=True)
class Keypoint:
    """A point fixed in a body: world position `xpos[body] + xmat[body] @ local`."""

    name: str
    body: int
    local: np.ndarray
    world: np.ndarray  # in the reference configuration
    groups: frozenset  # the rigid groups it is fixed in

    def position(self, data: mujoco.MjData) -> np.ndarray:
        """Its world position in `data`'s configuration."""
        return data.xpos[self.body] + data.xmat[self.body].reshape(3, 3) @ self.local


def _local(data, body: int, point: np.ndarray) -> np.ndarray:
    return data.xmat[body].reshape(3, 3).T @ (point - data.xpos[body])


def _distance(plane: Plane | None, a: np.ndarray, b: np.ndarray) -> float:
    if plane is not None:
        return float(np.linalg.norm(plane.project(a - b)))
    return float(np.linalg.norm(a - b))


def _far_end(model, data, tree: Tree, plane: Plane | None, g: int):
    """`(name, body, point)` of the far end of group `g`: its farthest site from its joint, or else
    the farthest end of its geoms; `None` if everything sits on the joint."""
    bodies = [b for b in range(model.nbody) if tree.group[b] == g]
    anchor = data.xanchor[tree.joints[g][0]]
    sites = [s for s in range(model.nsite) if model.site_bodyid[s] in bodies]
    candidates = []
    if sites:
        for s in sites:
            name = name_of(model, mujoco.mjtObj.mjOBJ_SITE, s, "site")
            candidates.append((name, int(model.site_bodyid[s]), np.array(data.site_xpos[s])))
    else:
        for geom in range(model.ngeom):
            b = int(model.geom_bodyid[geom])
            if b not in bodies:
                continue
            centre = np.array(data.geom_xpos[geom])
            points = [centre]
            if model.geom_type[geom] in (_CAPSULE, _CYLINDER):
                half = data.geom_xmat[geom].reshape(3, 3)[:, 2] * model.geom_size[geom, 1]
                points = [centre - half, centre + half]
            candidates += [(f"{body_name(model, g)}_end", b, p) for p in points]
    if not candidates:
        return None
    distances = [_distance(plane, p, anchor) for _, _, p in candidates]
    best = int(np.argmax(distances))
    if distances[best] < TOL:
        return None
    return candidates[best]


def _merge(keypoints: list[Keypoint], new: Keypoint, plane: Plane | None) -> None:
    for i, old in enumerate(keypoints):
        if _distance(plane, old.world, new.world) < TOL and old.groups & new.groups:
            keypoints[i] = dataclasses.replace(
                old, name=f"{old.name}+{new.name}", groups=old.groups | new.groups
            )
            return
    keypoints.append(new)


def _carried(model, data, tree: Tree, g: int, keypoints: list[Keypoint]) -> bool:
    """Whether group `g` has a keypoint that shows its motion (one off the axis, if it turns)."""
    on_group = [k for k in keypoints if g in k.groups]
    return any(not _pivots_about(model, data, tree, g, k.world) for k in on_group)


def default_keypoints(model, data, tree: Tree, plane: Plane | None) -> list[Keypoint]:
    """Every moving joint anchor, then the far end of every terminal group, then the far end of any
    group that still carries no keypoint off its joint axis; coincident points of a common body
    merged into one keypoint."""
    keypoints: list[Keypoint] = []
    for b in range(1, model.nbody):
        for j in range(model.njnt):
            if model.jnt_bodyid[j] != b:
                continue
            point = np.array(data.xanchor[j])
            groups = fixed_in(model, data, tree, int(tree.group[b]), point)
            if 0 in groups:
                continue
            keypoint = Keypoint(joint_name(model, j), b, _local(data, b, point), point, groups)
            _merge(keypoints, keypoint, plane)
    terminal = [g for g in tree.moving if not tree.children[g]]
    for g in terminal + [g for g in tree.moving if g not in terminal]:
        if g not in terminal and _carried(model, data, tree, g, keypoints):
            continue
        end = _far_end(model, data, tree, plane, g)
        if end is None:
            continue
        name, b, point = end
        groups = fixed_in(model, data, tree, g, point)
        _merge(keypoints, Keypoint(name, b, _local(data, b, point), point, groups), plane)
    return keypoints


def site_keypoints(model, data, tree: Tree, plane: Plane | None, names) -> list[Keypoint]:
    """Keypoints at the named sites, in that order."""
    if isinstance(names, str):
        names = [names]
    keypoints: list[Keypoint] = []
    for name in names:
        s = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
        if s < 0:
            available = [name_of(model, mujoco.mjtObj.mjOBJ_SITE, i, "site") for i in range(model.nsite)]
            raise ValueError(
                f"keypoints: the model has no site named {name!r}; its sites are "
                f"{available if available else 'none'}"
            )
        b = int(model.site_bodyid[s])
        point = np.array(data.site_xpos[s])
        groups = fixed_in(model, data, tree, int(tree.group[b]), point)
        for old in keypoints:
            if _distance(plane, old.world, point) < TOL and old.groups & groups:
                raise ValueError(
                    f"keypoints: sites {old.name!r} and {name!r} are the same point of the same body; "
                    "name one of them"
                )
        keypoints.append(Keypoint(name, b, np.array(model.site_pos[s]), point, groups))
    if not keypoints:
        raise ValueError("keypoints: name at least one site")
    return keypoints


def select_keypoints(model, data, tree: Tree, plane: Plane | None, names=None) -> list[Keypoint]:
    """The default keypoints, or those at the named sites."""
    if names is None:
        keypoints = default_keypoints(model, data, tree, plane)
        if not keypoints:
            raise ValueError("the model has no moving joint anchor or body end to use as a keypoint")
        return keypoints
    return site_keypoints(model, data, tree, plane, names)
