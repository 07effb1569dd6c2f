"""A textured mesh in a MuJoCo scene, rendered from our `Camera`s: lit RGB and exact masks.

MuJoCo's renderer runs headless through EGL (Mesa). The model is compiled once per scene; each
view only moves the one MuJoCo camera and sets its intrinsics, so rendering many views is cheap.
Masks come from MuJoCo's segmentation pass (geom ids per pixel), never from thresholding colours.

MuJoCo cameras look down -z with y up (OpenGL axes); their intrinsic mode takes focal lengths and
a principal-point offset in sensor units. We make one sensor unit one pixel, so the focal lengths
are K's and the offset is the principal point's distance from the image centre (MuJoCo measures
it with both axes flipped relative to OpenCV's pixel axes; `tests/rig/test_synthetic.py` pins
this against rasterised mesh silhouettes to a few hundredths of a pixel).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import mujoco
import numpy as np

from calibration.camera import Camera, c2w_opencv_to_opengl, undistort_normalized
from calibration.sim3 import Sim3
from calibration.so3 import matrix_to_quat

_OBJECT_GROUP = 1  # MuJoCo geom group of the object; the backdrop lives in group 0
_BACKDROP_EXTENT = 12.0  # backdrop half-size in object radii: reaches past the image edges at ring distances


@dataclass(frozen=True)
class TexturedMesh:
    """Triangle mesh in metres: `vertices` [N, 3], `faces` [F, 3]; `uv` [N, 2] and `texture` [H, W, 3] uint8, or a flat `rgba`."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)

    @cached_property
    def bounds(self) -> np.ndarray:
        """[2, 3] min and max corner."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @cached_property
    def radius(self) -> float:
        """Radius of the sphere around the bounding-box centre that holds every vertex."""
        centre = self.bounds.mean(0)
        return float(np.linalg.norm(self.vertices - centre, axis=1).max())


def load_textured_mesh(path: str | os.PathLike, *, texture_size: int | None = 1024) -> TexturedMesh:
    """Read an OBJ/GLB/PLY/STL with its texture (per-vertex UVs; seams split by trimesh).

    texture_size: longest texture side after downscaling (None keeps it); renders of a few hundred
    pixels gain nothing from a 4k texture and the model compiles faster.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: mesh file does not exist")
    try:
        tm = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on corrupt files
        raise ValueError(f"{path}: cannot be read as a mesh ({e})") from None
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise ValueError(f"{path}: holds no triangles")
    vertices = np.asarray(tm.vertices, np.float64)
    faces = np.asarray(tm.faces, np.int64)
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"{path}: vertices contain NaN or inf")
    uv = texture = None
    rgba = (0.7, 0.7, 0.7, 1.0)
    visual = tm.visual
    image = getattr(getattr(visual, "material", None), "image", None)
    if getattr(visual, "uv", None) is not None and image is not None and len(visual.uv) == len(vertices):
        uv = np.asarray(visual.uv, np.float64)
        texture = np.asarray(image.convert("RGB"))
        if texture_size is not None and max(texture.shape[:2]) > texture_size:
            f = texture_size / max(texture.shape[:2])
            size = (max(1, round(texture.shape[1] * f)), max(1, round(texture.shape[0] * f)))
            texture = cv2.resize(texture, size, interpolation=cv2.INTER_AREA)
    else:
        colors = getattr(visual, "face_colors", None) if visual.kind == "face" else getattr(visual, "vertex_colors", None)
        if colors is not None and len(colors):
            rgba = tuple(float(c) for c in np.asarray(colors, np.float64).mean(0) / 255.0)
    return TexturedMesh(vertices, faces, uv, texture, rgba)


@dataclass(frozen=True)
class Light:
    """Scene lighting: a directional key light (`direction` it shines along, object frame) plus a camera headlight.

    Intensities are MuJoCo's (0..1 per channel); `color` tints the key light (a warm or cold lamp).
    """

    direction: tuple[float, float, float] = (0.3, 0.2, -1.0)
    diffuse: float = 0.6
    ambient: float = 0.25
    headlight: float = 0.35
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)


def camera_to_mujoco(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Our pinhole camera -> MuJoCo camera (pos [3], quat wxyz [4], intrinsic [4], sensorsize [2]), one sensor unit per pixel."""
    gl = c2w_opencv_to_opengl(camera.c2w)
    k = camera.K
    intrinsic = np.array([k[0, 0], k[1, 1], -(k[0, 2] - camera.width / 2.0), -(k[1, 2] - camera.height / 2.0)])
    return gl[:3, 3].copy(), matrix_to_quat(gl[:3, :3]), intrinsic, np.array([camera.width, camera.height], np.float64)


def distortion_render_plan(camera: Camera) -> tuple[Camera, np.ndarray, np.ndarray]:
    """How to make `camera`'s distorted image: a pinhole camera (same focal lengths, canvas grown to
    cover every distorted pixel's ray) and cv2.remap maps [H, W] float32 from that canvas."""
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    k_inv = np.linalg.inv(camera.K)
    xy = undistort_normalized(uv @ k_inv[:2, :2].T + k_inv[:2, 2], camera.dist)
    src = xy @ camera.K[:2, :2].T + camera.K[:2, 2]
    lo = np.floor(src.min(0)).astype(int) - 1
    hi = np.ceil(src.max(0)).astype(int) + 1
    lo = np.maximum(lo, [-2 * camera.width, -2 * camera.height])  # wild distortion models must not ask for huge canvases
    hi = np.minimum(hi, [3 * camera.width, 3 * camera.height])
    k = camera.K.copy()
    k[:2, 2] -= lo
    canvas = Camera(k, int(hi[0] - lo[0]), int(hi[1] - lo[1]), np.zeros(0), camera.c2w)
    src = src - lo - 0.5  # cv2 pixel centres are integers
    return canvas, src[:, 0].reshape(u.shape).astype(np.float32), src[:, 1].reshape(u.shape).astype(np.float32)


class SyntheticScene:
    """A textured mesh (and optionally a backdrop) compiled into a MuJoCo model once, rendered many times.

    The scene's world frame is the mesh's own frame (the object frame, metres). The backdrop is a
    textured floor plane (the conveyor) at z = 0 of `floor_to_object`'s source frame, under a
    gradient sky, so neither the floor nor the background is a flat colour.
    """

    def __init__(
        self,
        mesh: TexturedMesh,
        *,
        backdrop: bool = False,
        floor_to_object: Sim3 | None = None,
        background_rgb: tuple[float, float, float] = (0.55, 0.57, 0.6),
    ) -> None:
        self.mesh = mesh
        self.backdrop = backdrop
        if floor_to_object is None:
            lo, hi = mesh.bounds
            floor_to_object = Sim3(1.0, np.eye(3), np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]))
        self.floor_to_object = floor_to_object
        self.model = _build_model(mesh, backdrop, floor_to_object, background_rgb)
        self.data = mujoco.MjData(self.model)
        self._object_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "object")
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}

    @staticmethod
    def from_mesh(
        mesh_path: str | os.PathLike,
        *,
        backdrop: bool = False,
        floor_to_object: Sim3 | None = None,
        texture_size: int | None = 1024,
        background_rgb: tuple[float, float, float] = (0.55, 0.57, 0.6),
    ) -> SyntheticScene:
        return SyntheticScene(
            load_textured_mesh(mesh_path, texture_size=texture_size),
            backdrop=backdrop,
            floor_to_object=floor_to_object,
            background_rgb=background_rgb,
        )

    def default_light(self) -> Light:
        """Key light from above the floor (down along the floor's -z), tilted so faces shade differently."""
        d = self.floor_to_object.rotation @ np.array([0.3, 0.2, -1.0])
        return Light(direction=tuple(d / np.linalg.norm(d)))

    def render(
        self,
        cameras_object: Sequence[Camera],
        *,
        light: Light | Sequence[Light] | None = None,
        noise_std: float = 0.0,
        seed: int = 0,
        object_visible: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 [V, H, W, 3] and exact object masks bool [V, H, W] for cameras in the object frame (OpenCV c2w).

        light: one light for all views or one per view. noise_std: Gaussian sensor noise, in units
        of full scale (0.01 = 2.55 grey levels), seeded by `seed`. Distorted cameras get a
        distorted image (rendered pinhole on a canvas that covers it, then warped), as a real camera would deliver it.
        object_visible=False renders the empty rig (the background frame); its masks are empty.
        """
        cams = list(cameras_object)
        if not cams:
            raise ValueError("render needs at least one camera")
        w, h = cams[0].width, cams[0].height
        if any((c.width, c.height) != (w, h) for c in cams):
            raise ValueError("all cameras of one render call must share one image size")
        lights = [light or self.default_light()] * len(cams) if light is None or isinstance(light, Light) else list(light)
        if len(lights) != len(cams):
            raise ValueError(f"got {len(lights)} lights for {len(cams)} cameras")
        option = mujoco.MjvOption()
        option.geomgroup[_OBJECT_GROUP] = int(object_visible)
        rng = np.random.default_rng(seed)
        images = np.empty((len(cams), h, w, 3), np.uint8)
        masks = np.empty((len(cams), h, w), bool)
        for i, (cam, lt) in enumerate(zip(cams, lights)):
            target = cam
            if not cam.is_pinhole:
                target, mx, my = distortion_render_plan(cam)
            renderer = self._renderer(target.width, target.height)
            self._set_camera(target)
            self._set_light(lt)
            mujoco.mj_forward(self.model, self.data)
            renderer.update_scene(self.data, camera=0, scene_option=option)
            rgb = renderer.render().astype(np.float32) / 255.0
            mask = np.zeros((target.height, target.width), bool)
            if object_visible:
                renderer.enable_segmentation_rendering()
                renderer.update_scene(self.data, camera=0, scene_option=option)
                seg = renderer.render()
                renderer.disable_segmentation_rendering()
                mask = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (seg[..., 0] == self._object_geom)
            if not cam.is_pinhole:
                rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                mask = cv2.remap(mask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE) > 0
            if noise_std > 0:
                rgb = rgb + rng.normal(0.0, noise_std, rgb.shape).astype(np.float32)
            images[i] = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            masks[i] = mask
        return images, masks

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    def __enter__(self) -> SyntheticScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _renderer(self, width: int, height: int) -> mujoco.Renderer:
        key = (width, height)
        if key not in self._renderers:
            vis = self.model.vis.global_
            vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
            self._renderers[key] = mujoco.Renderer(self.model, height, width)
        return self._renderers[key]

    def _set_camera(self, camera: Camera) -> None:
        pos, quat, intrinsic, sensor = camera_to_mujoco(camera)
        m = self.model
        m.cam_pos[0], m.cam_quat[0] = pos, quat
        m.cam_intrinsic[0], m.cam_sensorsize[0] = intrinsic, sensor
        m.cam_resolution[0] = (camera.width, camera.height)
        # Clip planes relative to the camera's distance to the object, so depth precision stays fine.
        dist = np.linalg.norm(camera.center - self.mesh.bounds.mean(0))
        m.vis.map.znear = max(1e-4, 0.05 * (dist - self.mesh.radius)) / m.stat.extent
        m.vis.map.zfar = (dist + 3 * _BACKDROP_EXTENT * self.mesh.radius) / m.stat.extent

    def _set_light(self, light: Light) -> None:
        m = self.model
        d = np.asarray(light.direction, np.float64)
        m.light_dir[0] = d / np.linalg.norm(d)
        m.light_diffuse[0] = light.diffuse * np.asarray(light.color)
        m.light_ambient[0] = 0.0
        m.light_specular[0] = 0.15 * light.diffuse
        m.vis.headlight.ambient[:] = light.ambient
        m.vis.headlight.diffuse[:] = light.headlight
        m.vis.headlight.specular[:] = 0.05


def _build_model(mesh: TexturedMesh, backdrop: bool, floor_to_object: Sim3, background_rgb) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    spec.stat.extent = 1.0
    spec.visual.quality.shadowsize = 2048
    spec.visual.rgba.haze = [0, 0, 0, 0]

    mj_mesh = spec.add_mesh(name="object")
    mj_mesh.uservert = mesh.vertices.astype(np.float32).ravel()
    mj_mesh.userface = mesh.faces.astype(np.int32).ravel()
    mj_mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # scans are rarely watertight
    material = spec.add_material(name="object", specular=0.2, shininess=0.2, rgba=list(mesh.rgba))
    if mesh.texture is not None:
        mj_mesh.usertexcoord = mesh.uv.astype(np.float32).ravel()
        tex = spec.add_texture(name="object", type=mujoco.mjtTexture.mjTEXTURE_2D)
        tex.width, tex.height, tex.nchannel = mesh.texture.shape[1], mesh.texture.shape[0], 3
        # OBJ's v runs bottom-up; MuJoCo's texture rows run top-down from v = 1.
        tex.data = np.ascontiguousarray(np.flipud(mesh.texture)).tobytes()
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "object"
        material.rgba = [1, 1, 1, 1]
    spec.worldbody.add_geom(
        name="object",
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname="object",
        material="object",
        group=_OBJECT_GROUP,
        contype=0,
        conaffinity=0,
    )

    sky = spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, width=256, height=256)
    if backdrop:
        sky.builtin = mujoco.mjtBuiltin.mjBUILTIN_GRADIENT
        sky.rgb1, sky.rgb2 = [0.75, 0.78, 0.82], [0.25, 0.27, 0.3]
        belt = spec.add_texture(name="belt", type=mujoco.mjtTexture.mjTEXTURE_2D, width=512, height=512)
        belt.builtin = mujoco.mjtBuiltin.mjBUILTIN_CHECKER
        belt.rgb1, belt.rgb2 = [0.32, 0.34, 0.36], [0.42, 0.42, 0.4]
        belt.mark = mujoco.mjtMark.mjMARK_RANDOM
        belt.random = 0.02
        belt.markrgb = [0.8, 0.8, 0.75]
        spec.add_material(name="belt", texrepeat=[20, 20], specular=0.1, reflectance=0.0).textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = (
            "belt"
        )
        half = _BACKDROP_EXTENT * max(mesh.radius, 1e-3)
        spec.worldbody.add_geom(
            name="backdrop",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[half, half, 0.01],
            material="belt",
            pos=floor_to_object.translation,
            quat=matrix_to_quat(floor_to_object.rotation),
            group=0,
            contype=0,
            conaffinity=0,
        )
    else:
        sky.builtin = mujoco.mjtBuiltin.mjBUILTIN_FLAT
        sky.rgb1 = sky.rgb2 = list(background_rgb)
    # The key light: directional, shadows only where there is a floor to catch them.
    spec.worldbody.add_light(name="key", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, castshadow=backdrop, pos=[0, 0, 1], dir=[0, 0, -1])
    spec.worldbody.add_camera(name="rig")
    cam = spec.cameras[0]
    cam.sensor_size, cam.resolution, cam.focal_pixel = [1.0, 1.0], [1, 1], [1.0, 1.0]
    try:
        return spec.compile()
    except ValueError as e:
        raise ValueError(f"MuJoCo cannot build a scene from this mesh ({e})") from None
