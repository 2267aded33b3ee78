"""The geometry of a planar MuJoCo scene as keyvision renders it: the plane of motion, the keypoints
(moving points of the bodies, or named sites) and the camera's homography from that plane to pixels."""

import dataclasses
import math
import os
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from cldyn._misc import optional_import

if TYPE_CHECKING:
    from ._render import RenderProtocol

_TOL = 1e-9  # metres: points closer than this coincide; axes closer than this (radians) are parallel
_HINGE, _SLIDE = 3, 2  # mujoco.mjtJoint values
_JOINT_TYPES = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}


def _mujoco():
    """MuJoCo, to render offscreen: it chooses its OpenGL backend from `MUJOCO_GL` when it is first
    imported, and on Linux keyvision asks for EGL (headless, as its rendering workers do) unless the
    environment names a backend; a MuJoCo imported earlier keeps the backend it chose."""
    if "mujoco" not in sys.modules and sys.platform.startswith("linux"):
        os.environ.setdefault("MUJOCO_GL", "egl")
    return optional_import("mujoco", purpose="keyvision.render")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _name(mujoco, model, kind, index: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"{fallback}{index}"


def _plane(model, data) -> tuple[np.ndarray, np.ndarray]:
    """`(basis (2, 3), normal (3,))` of the plane of motion, with cldyn's orientation convention:
    the second basis vector points up (against gravity) and the first along world +x where it can."""
    types = model.jnt_type
    for j in range(model.njnt):
        if types[j] not in (_HINGE, _SLIDE):
            raise ValueError(
                f"joint {j} is a {_JOINT_TYPES[int(types[j])]} joint: keyvision renders planar mechanisms "
                "of hinges and slides"
            )
    hinges = [j for j in range(model.njnt) if types[j] == _HINGE]
    slides = [j for j in range(model.njnt) if types[j] == _SLIDE]
    axes = {j: _unit(np.array(data.xaxis[j])) for j in hinges + slides}
    gravity = np.array(model.opt.gravity, dtype=float)
    if hinges:
        normal = axes[hinges[0]]
    elif slides:
        crosses = [np.cross(axes[slides[0]], axes[j]) for j in slides[1:]]
        crosses = [c for c in crosses if np.linalg.norm(c) > _TOL] or [np.cross(axes[slides[0]], gravity)]
        if np.linalg.norm(crosses[0]) <= _TOL:
            crosses = [np.cross(axes[slides[0]], np.eye(3)[np.argmin(np.abs(axes[slides[0]]))])]
        normal = _unit(crosses[0])
    else:
        raise ValueError("the scene has no hinge or slide joint: nothing moves")
    for j in hinges + slides:
        parallel = np.linalg.norm(np.cross(axes[j], normal)) <= _TOL
        if (types[j] == _HINGE and not parallel) or (types[j] == _SLIDE and abs(axes[j] @ normal) > _TOL):
            raise ValueError(f"joint {j} moves out of the plane with normal {np.round(normal, 6).tolist()}")
    up = -(gravity - (gravity @ normal) * normal)
    if np.linalg.norm(up) <= _TOL:
        for candidate in np.eye(3)[::-1]:
            up = candidate - (candidate @ normal) * normal
            if np.linalg.norm(up) > 1e-6:
                break
    up = _unit(up)
    e1 = np.cross(up, normal)
    if e1[np.argmax(np.abs(e1) > 1e-9)] < 0:
        normal, e1 = -normal, -e1
    return np.stack([e1, up]), normal


@dataclasses.dataclass(frozen=True)
class _Point:
    """A point fixed in a body: world position `xpos[body] + xmat[body] @ local`."""

    name: str
    body: int
    local: np.ndarray

    def world(self, data) -> np.ndarray:
        return data.xpos[self.body] + data.xmat[self.body].reshape(3, 3) @ self.local


def _local(data, body: int, point: np.ndarray) -> np.ndarray:
    return data.xmat[body].reshape(3, 3).T @ (point - data.xpos[body])


def _default_keypoints(mujoco, model, data, basis) -> list[_Point]:
    """The anchors of the joints that move (a hinge on a moving body, every slide), then the far end
    (its site or geom end farthest from its joint, in the plane) of every terminal moving body and of
    every body that turns and carries no hinge of another body (an arm along which a bead slides: a
    turning body needs a point of its own, as `cldyn.mujoco.from_mjcf` places one); points that
    coincide in the reference configuration are kept once. For KeyCLD's scenes these are the
    paper's keypoints: the pendulum's tip; the cart and the pole's tip; the elbow and the tip."""
    weld = np.array(model.body_weldid)
    moving = sorted({int(weld[model.jnt_bodyid[j]]) for j in range(model.njnt)})
    parent_group = {g: int(weld[model.body_parentid[g]]) for g in moving}
    candidates: list[tuple[str, int, np.ndarray]] = []
    for j in range(model.njnt):
        group = int(weld[model.jnt_bodyid[j]])
        if model.jnt_type[j] == _HINGE and parent_group[group] == 0:
            continue  # a hinge on the world: its anchor never moves
        body = int(model.jnt_bodyid[j])
        candidates.append(
            (_name(mujoco, model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint"), body, data.xanchor[j])
        )
    has_moving_child = {parent_group[g] for g in moving}
    hinged = [int(weld[model.jnt_bodyid[j]]) for j in range(model.njnt) if model.jnt_type[j] == _HINGE]
    carries_a_hinge = {parent_group[g] for g in hinged}
    for g in moving:
        if g in has_moving_child and (g not in hinged or g in carries_a_hinge):
            continue  # its joints' anchors and its children's hinges place it
        anchor = data.xanchor[next(j for j in range(model.njnt) if weld[model.jnt_bodyid[j]] == g)]
        ends = []
        for s in range(model.nsite):
            if weld[model.site_bodyid[s]] == g:
                name = _name(mujoco, model, mujoco.mjtObj.mjOBJ_SITE, s, "site")
                ends.append((name, int(model.site_bodyid[s]), np.array(data.site_xpos[s])))
        for geom in range(model.ngeom):
            body = int(model.geom_bodyid[geom])
            if weld[body] != g:
                continue
            centre = np.array(data.geom_xpos[geom])
            points = [centre]
            if int(model.geom_type[geom]) in (
                int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                int(mujoco.mjtGeom.mjGEOM_CYLINDER),
            ):
                half = data.geom_xmat[geom].reshape(3, 3)[:, 2] * model.geom_size[geom, 1]
                points = [centre - half, centre + half]
            body_label = _name(mujoco, model, mujoco.mjtObj.mjOBJ_BODY, g, "body")
            ends += [(f"{body_label}_end", body, p) for p in points]
        distances = [np.linalg.norm(basis @ (p - anchor)) for _, _, p in ends]
        if ends and max(distances) > _TOL:
            candidates.append(ends[int(np.argmax(distances))])
    points: list[_Point] = []
    seen: list[np.ndarray] = []
    for name, body, world in candidates:
        if any(np.linalg.norm(basis @ (world - other)) < _TOL for other in seen):
            continue
        seen.append(world)
        points.append(_Point(name, body, _local(data, body, world)))
    return points


def _site_keypoints(mujoco, model, data, names: Sequence[str]) -> list[_Point]:
    points = []
    for name in names:
        s = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
        if s < 0:
            sites = [_name(mujoco, model, mujoco.mjtObj.mjOBJ_SITE, i, "site") for i in range(model.nsite)]
            raise ValueError(f"keypoints: the scene has no site {name!r}; its sites are {sites or 'none'}")
        points.append(_Point(name, int(model.site_bodyid[s]), np.array(model.site_pos[s], dtype=float)))
    return points


def _camera(mujoco, model, camera: str | int) -> int:
    if isinstance(camera, str):
        index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if index < 0:
            names = [_name(mujoco, model, mujoco.mjtObj.mjOBJ_CAMERA, i, "camera") for i in range(model.ncam)]
            raise ValueError(f"camera: the scene has no camera {camera!r}; its cameras are {names or 'none'}")
    else:
        index = int(camera)
        if not 0 <= index < model.ncam:
            raise ValueError(f"camera: index {index} out of range; the scene has {model.ncam} cameras")
    label = _name(mujoco, model, mujoco.mjtObj.mjOBJ_CAMERA, index, "camera")
    if (
        int(model.cam_mode[index]) != int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED)
        or model.body_weldid[model.cam_bodyid[index]]
    ):
        raise ValueError(
            f"camera {label!r} moves with the scene; keyvision needs a camera fixed in the world"
        )
    if model.cam_projection[index] != 0 or np.any(model.cam_sensorsize[index] > 0):
        raise ValueError(f"camera {label!r}: only perspective cameras given by fovy are supported")
    return index


def _homography(model, data, camera: int, basis, normal, offset: float, aspect: float) -> np.ndarray:
    """The map from the image frame to planar coordinates: the pixel's viewing ray meets the plane
    `normal . p = offset` at `p`, whose planar coordinates are `basis @ p`."""
    tan_half = math.tan(math.radians(float(model.cam_fovy[camera])) / 2)
    rotation = np.array(data.cam_xmat[camera]).reshape(3, 3)  # columns: camera x, y, z in the world
    origin = np.array(data.cam_xpos[camera])
    # The ray through image point (u, v): direction rays @ (u, v, 1); the camera looks along -z.
    rays = rotation @ np.diag([aspect * tan_half, tan_half, -1.0])
    facing = normal @ rays
    if np.any(np.abs(facing[2]) < 1e-6):
        raise ValueError("the camera looks along the plane of motion: it cannot see the mechanism")
    top = np.outer(basis @ origin, facing) + (offset - normal @ origin) * (basis @ rays)
    return np.vstack([top, facing])


@dataclasses.dataclass(frozen=True)
class _Scene:
    """A compiled scene, set up for rendering."""

    model: Any
    camera: int
    basis: np.ndarray
    normal: np.ndarray
    keypoints: tuple[_Point, ...]
    homography: np.ndarray


class _Camera:
    """The scene's camera as `protocol` says: frames of `image_size` pixels, each the mean of
    `supersample` x `supersample` samples of MuJoCo's render at that many times the size, rounded
    to 8 bits (`supersample=1`: MuJoCo's render itself)."""

    def __init__(self, mujoco, scene: _Scene, protocol: "RenderProtocol"):
        self.size, self.supersample, self.camera = protocol.image_size, protocol.supersample, scene.camera
        side = self.size * self.supersample
        self._renderer = mujoco.Renderer(scene.model, side, side)

    def render(self, data) -> np.ndarray:
        """The frame `(size, size, 3)` uint8 of `data` (after `mj_forward`), a new array."""
        self._renderer.update_scene(data, camera=self.camera)
        image = self._renderer.render()
        if self.supersample == 1:
            return image.copy()
        blocks = image.reshape(self.size, self.supersample, self.size, self.supersample, 3)
        return np.round(blocks.mean(axis=(1, 3))).astype(np.uint8)

    def close(self) -> None:
        self._renderer.close()


def default_keypoint_names(xml: str) -> list[str]:
    """The names of the scene's default keypoints (`_default_keypoints`), without a camera or a render."""
    mujoco = _mujoco()
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    basis, _ = _plane(model, data)
    return [point.name for point in _default_keypoints(mujoco, model, data, basis)]


def _scene(xml: str, protocol: "RenderProtocol", camera: str | int, keypoints) -> _Scene:
    mujoco = _mujoco()
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as error:
        raise ValueError(f"MuJoCo could not compile the scene: {error}") from error
    if protocol.shadow_size is not None:
        model.vis.quality.shadowsize = protocol.shadow_size
    size = protocol.image_size * protocol.supersample
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), size)
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), size)
    index = _camera(mujoco, model, camera)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    basis, normal = _plane(model, data)
    points = (
        _default_keypoints(mujoco, model, data, basis)
        if keypoints is None
        else _site_keypoints(mujoco, model, data, keypoints)
    )
    if not points:
        raise ValueError("the scene has no moving point to use as a keypoint; name sites with keypoints=")
    offset = float(normal @ data.xanchor[0])
    homography = _homography(model, data, index, basis, normal, offset, aspect=1.0)
    return _Scene(model, index, basis, normal, tuple(points), homography)
