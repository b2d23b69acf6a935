"""Headless MuJoCo renderer with an exact pinhole camera (any K), exact depth and instance masks.

Frames and units: the MuJoCo world frame IS the OpenCV camera frame (x right, y down, z forward),
in millimetres; an object at pose (R, t) is a mocap body at position t with orientation R.
The camera is a fixed MJCF camera at the origin rotated 180 degrees about x (MuJoCo cameras look
along -z with y up). The projection is set per call by overriding the scene camera frustum
after ``mjv_updateScene`` so that pixel (u, v) (OpenCV: integer = pixel centre) is the ray
((u - cx)/fx, (v - cy)/fy, 1). Depth is exact: no multisampling (``offsamples=0``) and the
reversed-Z buffer is converted with z = f n / (n + d (f - n)) in float64.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import cv2
import mujoco
import numpy as np
import trimesh

from sc6d_jax.render._mesh import bake_mesh, prepare_mesh

_HIDDEN = np.array([0.0, 0.0, -1.0e7])  # behind the camera: clipped away
#: Geom group of the bodies not placed in the current call; the renderer's MjvOption hides it,
#: so mjv_updateScene leaves those geoms out of the scene.  Each geom in the scene costs a
#: draw call even when clipped: with the 30 slots of the training stream's renderer that was
#: 0.54 ms per mjr_render against 0.07 ms with only the placed object (llvmpipe, 128x128).
_HIDE_GROUP = 5
_EYE3 = np.eye(3)
PRIMITIVE_SHAPES = ("box", "sphere", "cylinder", "capsule", "ellipsoid")
_PRIM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "ellipsoid": mujoco.mjtGeom.mjGEOM_ELLIPSOID,
}


@dataclass(frozen=True)
class Primitive:
    """A distractor shape (not annotated): ``shape`` in PRIMITIVE_SHAPES, MuJoCo ``size`` (3,)
    in mm (half extents / radius, half length), ``rgb`` in [0, 1], pose (R, t mm)."""

    shape: str
    size: Sequence[float]
    rgb: Sequence[float]
    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class Light:
    """A directional light shining along ``direction`` (camera frame), colours in [0, 1].

    ``castshadow``: the light casts shadows of the rendered geometry (objects, occluders,
    distractor shapes) onto that geometry (not onto a composited 2D background); needs a renderer
    made with ``shadow_size > 0`` and a ``shadow_region`` in :meth:`Renderer.set_lights`."""

    direction: Sequence[float]
    diffuse: float | Sequence[float] = 0.6
    specular: float | Sequence[float] = 0.2
    ambient: float | Sequence[float] = 0.0
    castshadow: bool = False


@dataclass
class RenderOutput:
    """One rendered image.

    rgb: uint8 (H, W, 3). depth: float32 (H, W) mm along the optical axis, 0 where empty
    (None when not requested). instance: int32 (H, W), -1 background, i for ``objects[i]``,
    len(objects) + j for distractor j (None when masks were not requested).
    mask_visib: bool (N, H, W) visible mask per object. mask_full: bool (N, H, W) unoccluded
    silhouette per object (None unless requested).
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    instance: np.ndarray | None
    mask_visib: np.ndarray | None
    mask_full: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


def _gl_context_class():
    """The GL context class for the current ``MUJOCO_GL`` (default egl), chosen at call time so
    that importing mujoco before this module does not silently select GLFW."""
    backend = os.environ.get("MUJOCO_GL", "egl").lower().strip() or "egl"
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        from mujoco.rendering.classic.gl_context import GLContext
    return GLContext


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def _validate_pose(R: np.ndarray, t: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"{what}: R must be (3,3) and t (3,), got {R.shape} and {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError(f"{what}: pose has non-finite values")
    # BOP ground truth is stored with few digits (LM-O: |R R^T - I| up to 0.01): accept small
    # deviations and render the nearest rotation.  (Scalar arithmetic: this runs per object
    # per training crop.)
    dev = float(np.abs(R @ R.T - _EYE3).max())
    a, b, c, d, e, f, g, h, i = R.ravel().tolist()
    if dev > 0.02 or a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
        raise ValueError(f"{what}: R is not a rotation matrix")
    if dev > 1e-9:
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
    return R, t


def validate_intrinsics(K: np.ndarray) -> np.ndarray:
    """Return K as float64 (3,3) or raise ValueError naming the problem."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3,3), got {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError("K has non-finite values")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    if K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0, 0, 1)):
        raise ValueError("K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew)")
    return K


class Renderer:
    """MuJoCo renderer of several objects (each at its own pose) with one reusable GL context.

    Args:
        meshes: obj_id -> mesh in mm (e.g. from ``load_mesh``); colours from face colours.
        width, height: image size in pixels (render at exactly the needed resolution).
        max_instances: instances of the same object allowed in one image.
        n_primitives: number of distractor primitive slots.
        n_lights: number of directional light slots (unused ones are switched off).
        near, far: clipping distances in mm.
        shadow_size: side in texels of the shadow map of lights that cast shadows (0: no
            shadows, and no shadow map is made). The map covers the ``shadow_region`` given to
            :meth:`set_lights`, so 512 texels over twice an object's diameter resolve 1/256 of
            it.

    One renderer is not thread-safe; use one per process (``LP_NUM_THREADS=1`` helps when
    running several processes on few cores).
    """

    def __init__(
        self,
        meshes: Mapping[int, trimesh.Trimesh],
        width: int,
        height: int,
        *,
        max_instances: int = 1,
        n_primitives: int = 0,
        n_lights: int = 3,
        near: float = 10.0,
        far: float = 20_000.0,
        shadow_size: int = 0,
    ) -> None:
        if not meshes:
            raise ValueError("Renderer needs at least one mesh")
        if int(width) <= 0 or int(height) <= 0 or int(width) > 8192 or int(height) > 8192:
            raise ValueError(f"image size must be in 1..8192, got {width}x{height}")
        if not (0 < near < far):
            raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
        if max_instances < 1 or n_primitives < 0 or n_lights < 0:
            raise ValueError("max_instances >= 1, n_primitives >= 0, n_lights >= 0 required")
        if not 0 <= int(shadow_size) <= 8192:
            raise ValueError(f"shadow_size must be in 0..8192 texels, got {shadow_size}")
        self.width, self.height = int(width), int(height)
        self.near, self.far = float(near), float(far)
        self.obj_ids = [int(k) for k in meshes]
        self.max_instances = int(max_instances)
        self.n_primitives = int(n_primitives)
        self.n_lights = int(n_lights)
        self.shadow_size = int(shadow_size)
        self._lock = threading.Lock()

        spec = mujoco.MjSpec()
        spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
        spec.visual.quality.offsamples = 0
        spec.visual.quality.shadowsize = self.shadow_size  # 0: MuJoCo makes no shadow map
        spec.visual.global_.offwidth = self.width
        spec.visual.global_.offheight = self.height
        spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
        spec.visual.headlight.diffuse = [0.4, 0.4, 0.4]
        spec.visual.headlight.specular = [0.1, 0.1, 0.1]
        spec.visual.rgba.haze = [0, 0, 0, 1]
        spec.worldbody.add_camera(name="cam", pos=[0, 0, 0], quat=[0, 1, 0, 0])
        for li in range(self.n_lights):
            spec.worldbody.add_light(
                name=f"light{li}", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                pos=[0, 0, 0], dir=[0, 0, 1], diffuse=[0.5] * 3, castshadow=False,
            )
        body_names: list[tuple[str, int, int]] = []  # (name, obj_id, instance)
        for obj_id, mesh in meshes.items():
            if not isinstance(mesh, trimesh.Trimesh) or not hasattr(mesh.visual, "face_colors"):
                raise ValueError(f"mesh of object {obj_id} is not a trimesh.Trimesh")
            if mesh.visual.kind != "face":
                mesh = prepare_mesh(mesh, name=f"object {obj_id}")
            baked = bake_mesh(mesh)
            m = spec.add_mesh(name=f"mesh{obj_id}")
            m.uservert = baked.vertices.ravel().tolist()
            m.userface = baked.faces.ravel().tolist()
            if baked.normals is not None:
                m.usernormal = baked.normals.ravel().tolist()
            mat = spec.add_material(name=f"mat{obj_id}", rgba=list(baked.rgba))
            mat.specular = 0.3
            mat.shininess = 0.3
            if baked.texture is not None:
                th, tw = baked.texture.shape[:2]
                tex = spec.add_texture(
                    name=f"tex{obj_id}", type=mujoco.mjtTexture.mjTEXTURE_2D,
                    width=tw, height=th, nchannel=3,
                )
                tex.data = baked.texture.tobytes()
                roles = [""] * int(mujoco.mjtTextureRole.mjNTEXROLE)
                roles[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] = f"tex{obj_id}"
                mat.textures = roles
                m.usertexcoord = baked.texcoords.ravel().tolist()
                m.userfacetexcoord = np.repeat(np.arange(len(baked.faces)), 3).tolist()
            for j in range(self.max_instances):
                name = f"obj{obj_id}_{j}"
                b = spec.worldbody.add_body(name=name, mocap=True, pos=_HIDDEN.tolist())
                b.add_geom(
                    type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"mesh{obj_id}",
                    material=f"mat{obj_id}", contype=0, conaffinity=0,
                )
                body_names.append((name, int(obj_id), j))
        for j in range(self.n_primitives):
            b = spec.worldbody.add_body(name=f"prim{j}", mocap=True, pos=_HIDDEN.tolist())
            b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[10, 10, 10], contype=0,
                       conaffinity=0, rgba=[0.5, 0.5, 0.5, 1], name=f"primgeom{j}")
        try:
            self.model = spec.compile()
        except Exception as exc:
            raise ValueError(f"MuJoCo could not compile the scene: {exc}") from exc
        self.data = mujoco.MjData(self.model)
        model = self.model
        self._mocap = {}
        for name, obj_id, j in body_names:
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            self._mocap[(obj_id, j)] = int(model.body_mocapid[bid])
        self._prim_mocap = []
        self._prim_geom = []
        for j in range(self.n_primitives):
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"prim{j}")
            self._prim_mocap.append(int(model.body_mocapid[bid]))
            self._prim_geom.append(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"primgeom{j}"))
        # slot index of every body: objects by mocap id (filled per call), -1 otherwise
        self._geom_mocap = np.full(model.ngeom, -1, np.int64)
        for g in range(model.ngeom):
            self._geom_mocap[g] = model.body_mocapid[model.geom_bodyid[g]]
        self._geom_group0 = model.geom_group.copy()
        self.data.mocap_pos[:] = _HIDDEN
        self._cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "cam")

        self._gl = _gl_context_class()(self.width, self.height)
        self._gl.make_current()
        self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=model.ngeom + 8)
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[_HIDE_GROUP] = 0
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = self._cam_id
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._rgb = np.empty((self.height, self.width, 3), np.uint8)
        self._seg = np.empty((self.height, self.width, 3), np.uint8)
        self._depth = np.empty((self.height, self.width), np.float32)
        self._segmap = np.zeros(1, np.int64)
        self._closed = False
        self._force_segmentation = False  # tests: always use the segmentation pass
        self.set_lights(None)

    # ------------------------------------------------------------------ scene set-up
    def set_lights(
        self,
        lights: Sequence[Light] | None,
        headlight: Sequence[float] | None = None,
        shadow_region: tuple[Sequence[float], float] | None = None,
    ) -> None:
        """Set the directional lights (None: one light from the upper left) and the headlight
        (ambient, diffuse) intensities.

        ``shadow_region`` (centre (3,) mm, radius mm): the ball whose geometry casts and
        receives the shadows of lights with ``castshadow`` (each such light's orthographic shadow
        map is centred there, ``radius`` to each side); required when a light casts shadows.
        Geometry outside it is lit as if unshadowed."""
        model = self.model
        if lights is None:
            lights = [Light(direction=(0.4, 0.6, 1.0), diffuse=0.5, specular=0.2)] if self.n_lights else []
        if len(lights) > self.n_lights:
            raise ValueError(f"{len(lights)} lights requested, renderer has {self.n_lights} slots")
        shadows = any(L.castshadow for L in lights)
        if shadows:
            if self.shadow_size == 0:
                raise ValueError("a light casts shadows but the renderer was made with shadow_size=0")
            if shadow_region is None:
                raise ValueError("a light casts shadows: give shadow_region=(centre_mm, radius_mm)")
            centre = np.asarray(shadow_region[0], np.float64).reshape(-1)
            radius = float(shadow_region[1])
            if centre.shape != (3,) or not np.isfinite(centre).all() or not (np.isfinite(radius) and radius > 0):
                raise ValueError(f"shadow_region must be (centre (3,) mm, radius > 0 mm), got {shadow_region}")
            self._con.shadowClip = radius  # the map's half width (MuJoCo, directional lights)
        for i in range(self.n_lights):
            if i < len(lights):
                L = lights[i]
                d = np.asarray(L.direction, np.float64)
                n = np.linalg.norm(d)
                if d.shape != (3,) or not np.isfinite(n) or n == 0:
                    raise ValueError(f"light {i}: direction must be a non-zero 3-vector")
                model.light_dir[i] = d / n
                if L.castshadow:  # its depth range is the camera's [near, far] (MuJoCo): the light
                    # half of it before the centre, so all between the camera and far behind casts
                    model.light_pos[i] = centre - d / n * 0.5 * (self.far + self.near)
                else:
                    model.light_pos[i] = -d / n * 1000.0
                model.light_diffuse[i] = np.broadcast_to(L.diffuse, 3)
                model.light_specular[i] = np.broadcast_to(L.specular, 3)
                model.light_ambient[i] = np.broadcast_to(L.ambient, 3)
                model.light_castshadow[i] = bool(L.castshadow)
                model.light_active[i] = 1
            else:
                model.light_castshadow[i] = 0
                model.light_active[i] = 0
        if headlight is not None:
            amb, dif = float(headlight[0]), float(headlight[1])
            model.vis.headlight.ambient[:] = amb
            model.vis.headlight.diffuse[:] = dif
            model.vis.headlight.specular[:] = 0.0 if dif == 0 else 0.1

    def set_material(self, obj_id: int, specular: float = 0.3, shininess: float = 0.3) -> None:
        """Set the surface of object ``obj_id`` (all its instances): specular intensity and
        shininess, both in [0, 1] (MuJoCo's material; the defaults are the renderer's own)."""
        if int(obj_id) not in self.obj_ids:
            raise ValueError(f"unknown obj_id {obj_id} (renderer has {self.obj_ids})")
        for name, v in (("specular", specular), ("shininess", shininess)):
            if not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        mid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_MATERIAL, f"mat{int(obj_id)}")
        self.model.mat_specular[mid] = float(specular)
        self.model.mat_shininess[mid] = float(shininess)

    def _place(self, objects, primitives) -> list[int]:
        data = self.data
        data.mocap_pos[:] = _HIDDEN
        used: dict[int, int] = {}
        slots: list[int] = []
        for i, item in enumerate(objects):
            if len(item) != 3:
                raise ValueError(f"objects[{i}] must be (obj_id, R, t_mm)")
            obj_id, R, t = item
            R, t = _validate_pose(R, t, f"objects[{i}]")
            obj_id = int(obj_id)
            j = used.get(obj_id, 0)
            if (obj_id, 0) not in self._mocap:
                raise ValueError(f"objects[{i}]: unknown obj_id {obj_id} (renderer has {self.obj_ids})")
            if j >= self.max_instances:
                raise ValueError(
                    f"object {obj_id} appears more than max_instances={self.max_instances} times"
                )
            used[obj_id] = j + 1
            mid = self._mocap[(obj_id, j)]
            data.mocap_pos[mid] = t
            data.mocap_quat[mid] = _matrix_to_quat(R)
            slots.append(mid)
        if len(primitives) > self.n_primitives:
            raise ValueError(f"{len(primitives)} primitives requested, renderer has {self.n_primitives} slots")
        for j, p in enumerate(primitives):
            if p.shape not in _PRIM_TYPES:
                raise ValueError(f"primitive shape must be one of {PRIMITIVE_SHAPES}, got {p.shape!r}")
            R, t = _validate_pose(p.R, p.t, f"primitives[{j}]")
            g = self._prim_geom[j]
            self.model.geom_type[g] = _PRIM_TYPES[p.shape]
            size = np.asarray(p.size, np.float64)
            if size.shape != (3,) or np.any(size <= 0):
                raise ValueError(f"primitives[{j}]: size must be 3 positive numbers")
            self.model.geom_size[g] = size
            self.model.geom_rgba[g, :3] = np.clip(np.asarray(p.rgb, np.float64), 0, 1)
            self.model.geom_rgba[g, 3] = 1.0
            mid = self._prim_mocap[j]
            data.mocap_pos[mid] = t
            data.mocap_quat[mid] = _matrix_to_quat(R)
            slots.append(mid)
        return slots

    def _update(self, K: np.ndarray) -> None:
        m, d = self.model, self.data
        # geoms of hidden mocap bodies go to the hidden group (left out of the scene)
        placed = np.append(d.mocap_pos[:, 2] > _HIDDEN[2] / 2, True)  # index -1: not a mocap body
        m.geom_group[:] = np.where(placed[self._geom_mocap], self._geom_group0, _HIDE_GROUP)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_camlight(m, d)
        mujoco.mjv_updateScene(m, d, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL.value, self._scene)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        n, W, H = self.near, self.width, self.height
        # pixel centre u (OpenCV) is window coordinate u + 0.5; rows are flipped after reading
        left = n * (-cx - 0.5) / fx
        right = n * (W - cx - 0.5) / fx
        bottom = -n * (H - 0.5 - cy) / fy
        top = n * (cy + 0.5) / fy
        for c in (self._scene.camera[0], self._scene.camera[1]):
            c.frustum_center = 0.5 * (left + right)
            c.frustum_width = 0.5 * (right - left)
            c.frustum_bottom = bottom
            c.frustum_top = top
            c.frustum_near = n
            c.frustum_far = self.far

    def _segment(self, slots_by_mocap: np.ndarray) -> np.ndarray:
        scn = self._scene
        # the scene holds only the placed geoms, so the segment ids change from call to call
        geom_of_seg = np.full(scn.ngeom + 1, -1, np.int64)
        for i in range(scn.ngeom):
            g = scn.geoms[i]
            if g.segid >= 0 and g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                geom_of_seg[g.segid + 1] = g.objid
        self._segmap = geom_of_seg
        flags = scn.flags
        shadow = flags[mujoco.mjtRndFlag.mjRND_SHADOW]
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False  # ids only: no shadow passes
        try:
            mujoco.mjr_render(self._rect, scn, self._con)
            mujoco.mjr_readPixels(self._seg, None, self._rect, self._con)
        finally:
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = False
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = False
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadow
        # segment id (+1, 0 = background) -> geom -> mocap body -> instance, as one small table
        geom = self._segmap
        mocap = np.where(geom >= 0, self._geom_mocap[np.maximum(geom, 0)], -1)
        inst_of_seg = slots_by_mocap[mocap + 1]
        s = self._seg
        if len(inst_of_seg) <= 256:  # ids fit the red channel: one lookup on uint8
            inst = inst_of_seg[np.minimum(s[..., 0], len(inst_of_seg) - 1)]
        else:
            segid = s[..., 0].astype(np.int64) | (s[..., 1].astype(np.int64) << 8) | (s[..., 2].astype(np.int64) << 16)
            inst = inst_of_seg[np.minimum(segid, len(inst_of_seg) - 1)]
        return np.ascontiguousarray(inst[::-1])

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        objects: Sequence[tuple[int, np.ndarray, np.ndarray]],
        K: np.ndarray,
        *,
        primitives: Sequence[Primitive] = (),
        background: np.ndarray | None = None,
        depth: bool = True,
        masks: bool = True,
        full_masks: bool = False,
        shadows: bool = True,
    ) -> RenderOutput:
        """Render ``objects`` [(obj_id, R (3,3), t (3,) mm)] seen through pinhole ``K``.

        ``background`` (H, W, 3) uint8 is composited where nothing was drawn (needs masks).
        ``shadows=False`` skips the shadow passes of lights that cast shadows (each costs about
        two more draws of the scene), e.g. when only the masks or depth are wanted.
        Returns a RenderOutput; see its docstring for the fields.
        """
        if self._closed:
            raise RuntimeError("render called after close()")
        K = validate_intrinsics(K)
        if background is not None:
            background = np.asarray(background)
            if background.shape != (self.height, self.width, 3) or background.dtype != np.uint8:
                raise ValueError(
                    f"background must be uint8 ({self.height}, {self.width}, 3), got "
                    f"{background.dtype} {background.shape}"
                )
            masks = True
        with self._lock:
            self._gl.make_current()
            slots = self._place(objects, primitives)
            self._update(K)
            self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(shadows)
            mujoco.mjr_render(self._rect, self._scene, self._con)
            # One thing in the scene: its mask is where depth was written (same rasteriser,
            # same coverage), so the segmentation pass is skipped.
            single = len(slots) == 1 and (masks or full_masks) and not self._force_segmentation
            read_depth = depth or single
            mujoco.mjr_readPixels(self._rgb, self._depth if read_depth else None, self._rect, self._con)
            rgb = np.ascontiguousarray(self._rgb[::-1])
            z = None
            if depth:
                dbuf = self._depth[::-1].astype(np.float64)
                n, f = self.near, self.far
                z = f * n / (n + dbuf * (f - n))
                z[dbuf <= 0.0] = 0.0
                z = z.astype(np.float32)
            inst = mask_visib = mask_full = None
            n_obj = len(objects)
            if masks or full_masks:
                if single:
                    inst = np.where(self._depth[::-1] > 0.0, np.int32(0), np.int32(-1))
                else:
                    lut = np.full(self.model.nmocap + 1, -1, np.int32)
                    for i, mid in enumerate(slots):
                        lut[mid + 1] = i
                    inst = self._segment(lut)
                mask_visib = inst[None] == np.arange(n_obj, dtype=np.int32)[:, None, None]
                if background is not None:  # cv2.copyTo: ~15x faster than a broadcast np.copyto
                    rgb = cv2.copyTo(np.ascontiguousarray(background), (inst < 0).view(np.uint8), rgb)
            if full_masks and single:
                mask_full = mask_visib.copy()
            elif full_masks:
                mask_full = np.zeros((n_obj, self.height, self.width), bool)
                saved = self.data.mocap_pos.copy()
                for i in range(n_obj):
                    self.data.mocap_pos[:] = _HIDDEN
                    self.data.mocap_pos[slots[i]] = saved[slots[i]]
                    self._update(K)
                    lut = np.full(self.model.nmocap + 1, -1, np.int32)
                    lut[slots[i] + 1] = i
                    mask_full[i] = self._segment(lut) == i
                self.data.mocap_pos[:] = saved
            return RenderOutput(rgb=rgb, depth=z, instance=inst, mask_visib=mask_visib, mask_full=mask_full)

    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._gl.make_current()
            self._con.free()
        finally:
            self._gl.free()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass


_DEPTH_CACHE: "OrderedDict[tuple, Renderer]" = OrderedDict()
_DEPTH_CACHE_SIZE = 4


def _mesh_key(mesh: trimesh.Trimesh) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def render_depth(
    mesh: trimesh.Trimesh,
    K: np.ndarray,
    R: np.ndarray,
    t_mm: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """Depth image (float32 (H, W), mm along the optical axis, 0 where empty) of one mesh (mm)
    at pose (R, t_mm) seen through K. Renderers are cached per (mesh, size) for repeated calls
    (e.g. VSD over many estimates)."""
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("render_depth needs a non-empty trimesh.Trimesh")
    key = (_mesh_key(mesh), int(width), int(height))
    r = _DEPTH_CACHE.get(key)
    if r is None:
        r = Renderer({0: trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)}, width, height, n_lights=0)
        _DEPTH_CACHE[key] = r
        while len(_DEPTH_CACHE) > _DEPTH_CACHE_SIZE:
            _DEPTH_CACHE.popitem(last=False)[1].close()
    else:
        _DEPTH_CACHE.move_to_end(key)
    return r.render([(0, R, t_mm)], K, depth=True, masks=False).depth
