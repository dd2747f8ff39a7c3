"""A simulated RealSense-D435-like RGB-D camera, rendered by ray casting with Open3D's `RaycastingScene`.

One ray per pixel goes through the pixel centre (OpenCV / librealsense convention: pixel (u, v) is
at `u = fx * x / z + cx`) of a pinhole camera in the optical frame (x right, y down, z forward).
The ray direction is `K^-1 [u, v, 1]`, whose z component is 1, so Open3D's hit distance (in units
of the direction's length) is the z-depth directly.

Outputs, aligned pixel for pixel as `rs.align` gives them:

- depth: float32 z-depth in metres along the optical axis, 0 = no data;
- labels: the hit triangle's `SemanticClass` id (255 where the ray hits nothing);
- RGB: per-triangle base colour times a procedural texture (concrete, wood grain, cardboard, ...),
  Lambertian shading from a directional light plus ambient light and a ceiling-lamp pattern.

Noise (`CameraNoise`, `perturb_labels`: the noise model in `sim.camera_noise`, with what each imperfection
means) is drawn from the `numpy.random.Generator` passed in: D435 stereo depth noise (optionally correlated
over patches), flying pixels, dropouts, quantisation, stereo shadow (`sim.depth_artefacts`), a per-camera
depth scale error (truth `depth_scale_true`), optional label noise (truth `labels_true`), RGB sensor
noise and per-frame lighting variation; `depth_noise: false` turns every depth artefact off. The range
limits (`min_depth_m`, 0.28 m, and `max_depth_m` of `CameraModel`) always apply.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.sim.camera_noise import (
    D435_BASELINE_M,
    D435_SUBPIXEL_PX,
    CameraNoise,
    _correlation_kernel,
    _rgb_noise_luts,
    perturb_labels,
)
from palletpilot.sim.depth_artefacts import depth_scale, shadow_candidates, stereo_shadow
from palletpilot.sim.world import LabeledMesh, Texture, o3d_tensor

__all__ = [
    "D435_BASELINE_M",
    "D435_COLOR_VFOV_DEG",
    "D435_DEPTH_NATIVE_FOCAL_PX",
    "D435_DEPTH_NATIVE_SIZE",
    "D435_MAX_DEPTH_M",
    "D435_MIN_DEPTH_M",
    "D435_SUBPIXEL_PX",
    "R_BODY_OPTICAL",
    "CameraModel",
    "CameraNoise",
    "Lighting",
    "RaycastRenderer",
    "camera_mount_pose",
    "d435_color_intrinsics",
    "d435_depth_focal_px",
    "perturb_labels",
    "render",
]

D435_COLOR_VFOV_DEG = 42.8
"""Vertical field of view of the D435 colour imager (69.4 x 42.8 deg at 16:9; fx ~ 612 px at 480 rows)."""
D435_DEPTH_NATIVE_SIZE = (1280, 800)
D435_DEPTH_NATIVE_FOCAL_PX = 640.0
"""Depth imager focal length at its native 1280 x 800; stream modes scale then crop (640x480: 384 px)."""
D435_MIN_DEPTH_M = 0.28
D435_MAX_DEPTH_M = 10.0

# Optical frame axes expressed in a level, forward-looking body frame (x forward, y left, z up):
# optical x = -y (right), optical y = -z (down), optical z = +x (forward).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def d435_color_intrinsics(width: int = 640, height: int = 480) -> np.ndarray:
    """K (float64 3x3) of a D435-like colour stream: fx = fy from the 42.8 deg vertical FOV, centred.

    640x480 gives fx ~ 612 px (hfov ~ 55 deg), 848x480 the full 16:9 view (hfov ~ 69 deg).
    """
    f = 0.5 * height / np.tan(0.5 * np.deg2rad(D435_COLOR_VFOV_DEG))
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])


def d435_depth_focal_px(width: int = 640, height: int = 480) -> float:
    """Focal length (px) of the D435 depth imager in a stream mode: native 640 px at 1280x800, scaled to
    cover the mode then cropped (640x480 -> 384 px, 848x480 -> 424 px, 1280x720 -> 640 px)."""
    scale = max(width / D435_DEPTH_NATIVE_SIZE[0], height / D435_DEPTH_NATIVE_SIZE[1])
    return D435_DEPTH_NATIVE_FOCAL_PX * scale


def camera_mount_pose(position: ArrayLike, tilt: float, pan: float = 0.0, roll: float = 0.0) -> SE3:
    """`T_forklift_camera` (optical frame) of a camera at `position` (m, forklift frame) looking along +x,
    panned left by `pan` about the forklift z axis, tilted down by `tilt` about its own x (right) axis
    and rolled by `roll` about its optical axis (rad).

    Same convention as `sim.scenario.mount_transform`: R = Rz(pan) R_level Rx(-tilt) Rz(roll), where
    R_level is the level forward-looking optical frame (the paper's R_FC', eq. 6).
    """
    level = Rotation.from_matrix(R_BODY_OPTICAL)
    rotation = Rotation.from_euler("z", pan) * level * Rotation.from_euler("x", -tilt) * Rotation.from_euler("z", roll)
    return SE3(rotation, position)


@dataclass(frozen=True)
class CameraModel:
    """Pinhole RGB-D camera: image size, K (colour = aligned depth), depth imager focal length and range."""

    width: int
    height: int
    K: np.ndarray
    depth_focal_px: float
    min_depth_m: float = D435_MIN_DEPTH_M
    max_depth_m: float = D435_MAX_DEPTH_M

    @classmethod
    def d435(cls, width: int = 640, height: int = 480) -> CameraModel:
        """A D435-like camera at 640x480 or 848x480 (any size works; intrinsics scale as the real modes do)."""
        return cls(width, height, d435_color_intrinsics(width, height), d435_depth_focal_px(width, height))


@dataclass(frozen=True)
class Lighting:
    """A directional light plus ambient light (world frame); `direction` points from the scene to the light.

    `lamp_period_m` and `lamp_depth` modulate the direct light over the floor plan like rows of
    ceiling lamps: factor 1 + lamp_depth * cos(2 pi x / period) cos(2 pi y / period).
    """

    direction: tuple[float, float, float] = (0.35, 0.25, 1.0)
    ambient: float = 0.4
    diffuse: float = 0.7
    colour: tuple[float, float, float] = (1.0, 0.98, 0.94)
    lamp_period_m: float = 6.0
    lamp_depth: float = 0.12
    lamp_phase: tuple[float, float] = (0.0, 0.0)

    def unit_direction(self) -> np.ndarray:
        """The light direction as a unit vector (world frame)."""
        d = np.asarray(self.direction, dtype=float)
        return d / np.linalg.norm(d)

    def varied(self, rng: np.random.Generator) -> Lighting:
        """A per-frame variation: direction within ~15 deg, intensities +-20 %, colour temperature, lamp phase."""
        d = self.unit_direction() + rng.normal(0.0, 0.15, 3)
        d[2] = abs(d[2]) + 0.2  # the light stays above
        tint = 1.0 + rng.normal(0.0, 0.03, 3)
        return Lighting(
            direction=tuple(d),
            ambient=self.ambient * rng.uniform(0.8, 1.2),
            diffuse=self.diffuse * rng.uniform(0.8, 1.2),
            colour=tuple(np.asarray(self.colour) * tint),
            lamp_period_m=self.lamp_period_m,
            lamp_depth=self.lamp_depth,
            lamp_phase=tuple(rng.uniform(0.0, 2 * np.pi, 2)),
        )


# -- procedural textures ---------------------------------------------------------------------------

_TILE = 256  # texels per tile side (a power of two: wrap-around with a bit mask)
# (metres per tile, amplitude, gaussian sigma (v, u) in texels, extra high-frequency share)
_TEXTURE_PARAMS = {
    Texture.PLAIN: (1.0, 0.02, (4.0, 4.0), 0.0),
    Texture.CONCRETE: (2.0, 0.07, (6.0, 6.0), 0.5),
    Texture.WOOD: (0.6, 0.14, (0.8, 24.0), 0.2),
    Texture.CARDBOARD: (0.5, 0.05, (2.0, 2.0), 0.3),
    Texture.PAINTED_METAL: (1.0, 0.05, (10.0, 10.0), 0.2),
    Texture.FABRIC: (0.15, 0.08, (1.0, 1.0), 0.5),
}


@lru_cache(maxsize=1)
def _texture_tiles() -> tuple[np.ndarray, np.ndarray]:
    """Multiplicative texture tiles (T, S, S) float32 around 1 and texels per metre (T,), fixed seed.

    The texture pattern is part of the world's appearance, not scenario randomness, so it is the
    same in every run.
    """
    rng = np.random.default_rng(20240517)
    n = max(int(t) for t in Texture) + 1
    tiles = np.ones((n, _TILE, _TILE), np.float32)
    texels_per_m = np.ones(n, np.float32)
    for tex, (metres, amplitude, sigma, fine) in _TEXTURE_PARAMS.items():
        coarse = ndimage.gaussian_filter(rng.standard_normal((_TILE, _TILE)), sigma, mode="wrap")
        detail = ndimage.gaussian_filter(rng.standard_normal((_TILE, _TILE)), 0.7, mode="wrap")
        pattern = coarse / (coarse.std() + 1e-12) + fine * detail / (detail.std() + 1e-12)
        pattern /= pattern.std() + 1e-12
        tiles[tex] = np.clip(1.0 + amplitude * pattern, 0.3, 1.7)
        texels_per_m[tex] = _TILE / metres
    return tiles, texels_per_m


# -- the renderer ----------------------------------------------------------------------------------

_BACKGROUND = (0.05, 0.05, 0.06)  # colour where a ray leaves the scene (open roof)


@dataclass
class _SceneCache:
    """One Open3D scene and its per-triangle tables; row M (the last) stands for "no hit"."""

    key: bytes
    scene: o3d.t.geometry.RaycastingScene
    n_triangles: int
    classes: np.ndarray  # (M + 1,) uint8
    albedo: np.ndarray  # (M + 1, 3) float32
    normals: np.ndarray  # (M + 1, 3) float64, unit, world frame
    first_vertex: np.ndarray  # (M + 1, 3) float64, world frame
    tex_static: np.ndarray  # (M + 1, 7) float32: u0, v0, du1, dv1, du2, dv2 (texels), tile offset


@dataclass
class _RayCache:
    """Per camera model: camera-frame ray directions (z = 1), vignetting and reusable work buffers.

    Rendering is memory-bound: fresh 1 MB temporaries per step cost more (page faults) than the
    arithmetic, so every per-pixel intermediate lives in a buffer allocated once per camera.
    """

    key: bytes
    directions: np.ndarray  # (N, 1, 3) float32, camera frame
    vignette: np.ndarray  # (N,) float32, relative illumination cos^4 of the off-axis angle
    world_directions: np.ndarray  # (N, 1, 3) float32, world frame
    rays: np.ndarray  # (N, 6) float32: origin, direction (world frame)
    ray_halves: np.ndarray  # view of `rays` as (N, 2) records of three float32: [origin, direction]
    columns: np.ndarray  # (_N_COL, N) float32: per-pixel copies of the hit triangle's table columns
    f: list[np.ndarray]  # four (N,) float32 scratch arrays
    i: list[np.ndarray]  # two (N,) int32 scratch arrays
    b: list[np.ndarray]  # two (N,) bool scratch arrays


_XYZ = np.dtype((np.void, 12))  # three float32 as one record: copies rows of rays in one pass
_N_COL = 10  # per-triangle columns: shaded colour (3), texel coordinates u0 v0 du1 dv1 du2 dv2 (6), tile offset


def _mesh_digest(meshes: Sequence[LabeledMesh]) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for m in meshes:
        for arr in (m.vertices, m.triangles, m.classes, m.albedo, m.texture):
            h.update(np.ascontiguousarray(arr).tobytes())
    return h.digest()


class RaycastRenderer:
    """Renders RGB-D frames of a world with one Open3D `RaycastingScene`, reused across frames.

    `static` meshes (world frame) are fixed for the renderer's life. Meshes passed as `dynamic` to
    `render` (forks at a lift height, a carried pallet) join them; the scene is rebuilt only when the
    dynamic meshes change (a few ms for a small warehouse), so repeated frames of a standing forklift
    cost only the ray cast and the shading.

    Shading is exact per planar triangle: Lambert's cosine with a directional light is constant over a
    flat face, so it is computed once per triangle and frame; the texture is looked up per pixel from
    the hit's barycentric coordinates.
    """

    def __init__(self, static: LabeledMesh | Sequence[LabeledMesh]) -> None:
        self._static = static if isinstance(static, LabeledMesh) else LabeledMesh.merge(list(static))
        self._scene: _SceneCache | None = None
        self._rays: _RayCache | None = None
        _texture_tiles()  # build once, outside the timed frames

    # -- caches -------------------------------------------------------------------------------
    def _scene_for(self, dynamic: Sequence[LabeledMesh]) -> _SceneCache:
        key = _mesh_digest(dynamic)
        if self._scene is not None and self._scene.key == key:
            return self._scene
        mesh = LabeledMesh.merge([self._static, *dynamic])
        scene = o3d.t.geometry.RaycastingScene()
        m = mesh.n_triangles
        if m:
            scene.add_triangles(
                o3d_tensor(mesh.vertices.astype(np.float32)), o3d_tensor(mesh.triangles.astype(np.uint32))
            )
        corners = mesh.vertices[mesh.triangles]  # (M, 3 corners, 3)
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        _, texels_per_m = _texture_tiles()
        scale = texels_per_m[mesh.texture][:, None]
        tex_u = np.einsum("mkj,mj->mk", corners, mesh.tangent_u) * scale  # texel coordinates of the corners
        tex_v = np.einsum("mkj,mj->mk", corners, mesh.tangent_v) * scale
        # Keep coordinates small (float32 precision): shift each triangle by whole tiles.
        shift_u = np.floor(tex_u[:, 0] / _TILE)[:, None] * _TILE
        shift_v = np.floor(tex_v[:, 0] / _TILE)[:, None] * _TILE
        tex_u, tex_v = tex_u - shift_u, tex_v - shift_v
        tex = np.zeros((m + 1, 7), np.float32)
        tex[:m, 0], tex[:m, 1] = tex_u[:, 0], tex_v[:, 0]
        tex[:m, 2], tex[:m, 3] = tex_u[:, 1] - tex_u[:, 0], tex_v[:, 1] - tex_v[:, 0]
        tex[:m, 4], tex[:m, 5] = tex_u[:, 2] - tex_u[:, 0], tex_v[:, 2] - tex_v[:, 0]
        tex[:m, 6] = mesh.texture.astype(np.float32) * (_TILE * _TILE)
        tex[m, 6] = float(Texture.PLAIN) * _TILE * _TILE
        self._scene = _SceneCache(
            key=key,
            scene=scene,
            n_triangles=m,
            classes=np.append(mesh.classes, np.uint8(SemanticClass.UNLABELED)),
            albedo=np.vstack([mesh.albedo, np.asarray(_BACKGROUND, np.float32)[None]]).astype(np.float32),
            normals=np.vstack([normals, [[0.0, 0.0, -1.0]]]),
            first_vertex=np.vstack([corners[:, 0], [[0.0, 0.0, 1e6]]]),
            tex_static=tex,
        )
        return self._scene

    def _rays_for(self, camera: CameraModel) -> _RayCache:
        key = np.asarray(camera.K, dtype=np.float64).tobytes() + np.array([camera.width, camera.height]).tobytes()
        if self._rays is not None and self._rays.key == key:
            return self._rays
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
        directions = pixels @ np.linalg.inv(camera.K).T
        directions[:, 2] = 1.0  # exactly: the hit distance is then the z-depth
        cos2 = 1.0 / np.einsum("ij,ij->i", directions, directions)  # cos^2 of the off-axis angle
        n = u.size
        rays = np.empty((n, 6), np.float32)
        self._rays = _RayCache(
            key=key,
            directions=directions.astype(np.float32).reshape(n, 1, 3),
            vignette=(cos2 * cos2).astype(np.float32),
            world_directions=np.empty((n, 1, 3), np.float32),
            rays=rays,
            ray_halves=rays.view(_XYZ).reshape(n, 2),
            columns=np.empty((_N_COL, n), np.float32),
            f=[np.empty(n, np.float32) for _ in range(4)],
            i=[np.empty(n, np.int32) for _ in range(2)],
            b=[np.empty(n, bool) for _ in range(2)],
        )
        return self._rays

    # -- rendering ------------------------------------------------------------------------------
    def render(
        self,
        T_world_camera: SE3,
        camera: CameraModel,
        noise: CameraNoise | None = None,
        rng: np.random.Generator | None = None,
        dynamic: Sequence[LabeledMesh] = (),
        lighting: Lighting | None = None,
        fork_height: float = 0.0,
        truth: dict[str, np.ndarray] | None = None,
    ) -> FrameBundle:
        """Render depth, labels and RGB seen from `T_world_camera` (optical frame) as a `FrameBundle`.

        `dynamic` meshes (world frame) join the static world for this frame. `noise` defaults to an
        ideal camera; `rng` is required whenever noise or lighting variation draws random numbers.
        `fork_height` (m) and `truth` (keys ending in `_true`) are passed through to the bundle; with
        label noise, the exact labels are added to the truth as `labels_true`, with depth noise the
        camera's depth scale error s (measured z = true z (1 + s)) as `depth_scale_true` (0-d float64).
        """
        noise = noise or CameraNoise.off()
        needs_rng = noise.depth_noise or noise.label_noise or noise.rgb_sigma > 0 or noise.lighting_variation
        if needs_rng and rng is None:
            raise ValueError("RaycastRenderer.render: noise or lighting variation needs a numpy Generator `rng`")
        lighting = lighting or Lighting()
        if noise.lighting_variation:
            assert rng is not None  # checked above (needs_rng)
            lighting = lighting.varied(rng)

        sc = self._scene_for(dynamic)
        rc = self._rays_for(camera)
        h, w = camera.height, camera.width
        # Rotate the camera-frame directions into the world. cv2.transform, not a BLAS matmul: a
        # multi-threaded BLAS call right after Embree's TBB workers oversubscribes two cores badly.
        cv2.transform(rc.directions, T_world_camera.R.astype(np.float32), dst=rc.world_directions)
        rc.ray_halves[:, 1] = rc.world_directions.reshape(-1).view(_XYZ)
        rc.ray_halves[:, 0] = T_world_camera.t.astype(np.float32).view(_XYZ)[0]
        hits = sc.scene.cast_rays(o3d.core.Tensor.from_numpy(rc.rays))
        z = hits["t_hit"].numpy()  # z-depth (the directions have a unit z component); inf where missed
        prim = hits["primitive_ids"].numpy()
        np.minimum(prim, np.uint32(sc.n_triangles), out=prim)  # misses -> the extra last row
        hit = np.less(prim, sc.n_triangles, out=rc.b[0])

        labels = np.take(sc.classes, prim).reshape(h, w)
        rgb = self._shade(T_world_camera, prim, hits["primitive_uvs"].numpy(), rc, sc, lighting, noise, rng)
        truth = dict(truth or {})
        shadow, scale = None, 0.0
        if noise.depth_noise:
            assert rng is not None  # checked above (needs_rng)
            if noise.stereo_shadow:
                fx, base = float(camera.K[0, 0]), noise.baseline_m
                shadow = shadow_candidates(z, hit, fx, base, w, (rc.f[0], rc.f[1]))
                shadow = shadow[(z[shadow] >= camera.min_depth_m) & (z[shadow] <= camera.max_depth_m)]
                shadow = stereo_shadow(sc.scene, T_world_camera, rc.world_directions, z, shadow, base)
            scale = depth_scale(rng, noise.depth_scale_error)
            truth["depth_scale_true"] = np.array(scale)
        depth = self._measure_depth(z, hit, camera, rc, noise, rng, shadow, scale)
        if noise.label_noise:
            truth["labels_true"] = labels  # the exact labels, to score a segmenter against
            assert rng is not None  # checked above (needs_rng)
            labels = perturb_labels(labels, noise.label_noise_px, rng)
        return FrameBundle(
            depth=depth.reshape(h, w),
            K=np.array(camera.K, dtype=np.float64),
            labels=labels,
            rgb=rgb.reshape(h, w, 3),
            fork_height=fork_height,
            truth=truth,
        )

    @staticmethod
    def _shade(
        T_world_camera: SE3,
        prim: np.ndarray,
        barycentric: np.ndarray,
        rc: _RayCache,
        sc: _SceneCache,
        lighting: Lighting,
        noise: CameraNoise,
        rng: np.random.Generator | None,
    ) -> np.ndarray:
        """Textured Lambertian colour of every pixel, (N, 3) uint8."""
        # Per triangle (M rows, cheap): the side facing the camera, its Lambert cosine and its colour.
        facing = np.sign(np.einsum("ij,ij->i", sc.normals, T_world_camera.t - sc.first_vertex))
        cos = np.maximum(facing * (sc.normals @ lighting.unit_direction()), 0.0)
        radiance = lighting.ambient + lighting.diffuse * cos
        tri = np.empty((_N_COL, sc.n_triangles + 1), np.float32)
        tri[:3] = (sc.albedo * radiance[:, None] * (np.asarray(lighting.colour) * 255.0)).T
        tri[3:] = sc.tex_static.T
        col = rc.columns  # contiguous per-pixel copies: gathers are cheap, strided arithmetic is not
        for k in range(_N_COL):
            np.take(tri[k], prim, out=col[k])

        # Texture: texel coordinates interpolated with the hit's barycentric coordinates (b1, b2).
        b1, b2, tu, tv = rc.f
        np.copyto(b1, barycentric[:, 0])
        np.copyto(b2, barycentric[:, 1])
        np.multiply(b1, col[5], out=tu)
        tu += col[3]
        np.multiply(b2, col[7], out=tv)  # tv as scratch
        tu += tv
        np.multiply(b1, col[6], out=tv)
        tv += col[4]
        np.multiply(b2, col[8], out=b1)
        tv += b1
        iu, iv = rc.i
        mask = _TILE - 1
        np.copyto(iu, tu, casting="unsafe")
        np.copyto(iv, tv, casting="unsafe")
        iu &= mask
        iv &= mask
        iv *= _TILE
        iv += iu
        np.copyto(iu, col[9], casting="unsafe")  # the tile's offset in the flat tile array
        iv += iu
        tiles, _ = _texture_tiles()
        gain = np.take(tiles.reshape(-1), iv, out=b2)
        gain *= rc.vignette
        for k in range(3):
            col[k] *= gain
        rgb = cv2.merge([cv2.convertScaleAbs(col[k]) for k in range(3)]).reshape(-1, 3)  # saturating uint8
        if noise.rgb_sigma > 0:
            assert rng is not None  # `render` requires it with RGB noise
            # One random byte per sample picks a Gaussian quantile: zero-mean noise of std rgb_sigma.
            up, down = _rgb_noise_luts(noise.rgb_sigma)
            draw = rng.integers(0, 256, rgb.shape, dtype=np.uint8)
            cv2.add(rgb, cv2.LUT(draw, up), dst=rgb)
            cv2.subtract(rgb, cv2.LUT(draw, down), dst=rgb)
        return rgb

    @staticmethod
    def _measure_depth(
        z: np.ndarray,
        hit: np.ndarray,
        camera: CameraModel,
        rc: _RayCache,
        noise: CameraNoise,
        rng: np.random.Generator | None,
        shadow: np.ndarray | None = None,
        scale: float = 0.0,
    ) -> np.ndarray:
        """Turn true z-depth (N,; inf where missed) into a D435-like measurement (N,), 0 = no data.

        With depth noise: `shadow` (flat pixel indices) get no depth, the rest is scaled by `1 + scale`.
        """
        depth = np.zeros(z.shape, np.float32)
        np.copyto(depth, z, where=hit)
        if noise.depth_noise:
            assert rng is not None  # `render` requires it with depth noise
            h, w = camera.height, camera.width
            scratch, noisy, z_max, z_min = rc.f
            # Flying pixels: at a depth edge in the 3x3 neighbourhood, mix foreground and background.
            far = np.minimum(z, np.float32(2.0 * camera.max_depth_m), out=scratch).reshape(h, w)
            kernel = np.ones((3, 3), np.uint8)
            cv2.dilate(far, kernel, dst=z_max.reshape(h, w))
            cv2.erode(far, kernel, dst=z_min.reshape(h, w))
            edge = np.greater(
                z_max, np.multiply(z_min, np.float32(1.0 + noise.edge_jump_rel), out=scratch), out=rc.b[1]
            )
            edge &= hit
            idx = np.flatnonzero(edge)
            if idx.size and noise.flying_pixel_rate > 0:
                idx = idx[rng.random(idx.size) < noise.flying_pixel_rate]
                lo = z_min[idx]
                hi = np.minimum(z_max[idx], np.float32(camera.max_depth_m))
                depth[idx] = lo + rng.random(idx.size, dtype=np.float32) * (hi - lo)
            if shadow is not None:
                depth[shadow] = 0.0  # the right imager cannot see these points: no disparity
            if scale != 0.0:
                depth *= np.float32(1.0 + scale)
            # Stereo: the disparity d = f B / z is measured with a subpixel error; z = f B / d.
            fb = np.float32(camera.depth_focal_px * noise.baseline_m)
            with np.errstate(divide="ignore", invalid="ignore"):
                disparity = np.divide(fb, depth, out=scratch)  # inf where there is no depth
                rng.standard_normal(out=noisy, dtype=np.float32)
                if noise.depth_correlation_px > 1.0:  # spread over a patch, the per-pixel sigma kept
                    img = noisy.reshape(h, w)
                    kernel, gain = _correlation_kernel(noise.depth_correlation_px)
                    cv2.sepFilter2D(img, -1, kernel, kernel, dst=img, borderType=cv2.BORDER_REFLECT)
                    noisy *= np.float32(gain)
                noisy *= np.float32(noise.disparity_sigma_px)
                disparity += noisy
                np.divide(fb, disparity, out=depth)  # 0 where no depth; < 0 if noise flipped d (cut below)
            if noise.depth_unit_m > 0:
                unit = np.float32(noise.depth_unit_m)
                depth /= unit
                np.rint(depth, out=depth)
                depth *= unit
            if noise.invalid_rate > 0:
                n_invalid = rng.binomial(depth.size, noise.invalid_rate)
                depth[rng.choice(depth.size, n_invalid, replace=False)] = 0.0
        np.copyto(depth, np.float32(0.0), where=np.less(depth, np.float32(camera.min_depth_m), out=rc.b[1]))
        np.copyto(depth, np.float32(0.0), where=np.greater(depth, np.float32(camera.max_depth_m), out=rc.b[1]))
        return depth


def render(
    world_meshes: LabeledMesh | Sequence[LabeledMesh],
    T_world_camera: SE3,
    K: np.ndarray,
    width: int,
    height: int,
    noise: CameraNoise | None = None,
    rng: np.random.Generator | None = None,
) -> FrameBundle:
    """One-off render of `world_meshes` (world frame) with a D435-like depth sensor at K's resolution.

    Builds a fresh scene each call; use `RaycastRenderer` to render many frames of one world.
    """
    camera = CameraModel(width, height, np.asarray(K, dtype=np.float64), d435_depth_focal_px(width, height))
    return RaycastRenderer(world_meshes).render(T_world_camera, camera, noise, rng)
