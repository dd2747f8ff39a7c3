"""What real cameras and real pallets add to a rendered dataset frame (`sim.dataset`, `realism=True`).

Issue 37: the shipped segmentation model, trained on renders, labels about a third of a real photo's
pallet front faces as pallet (`palletpilot bench realdata`). The renders' pallets are clean boxes of one
wood tone with a fixed grain texture, and their images are what an ideal camera with a fixed exposure
sees. This module draws, per frame, from its own generator (`sim.dataset` seeds it `(seed, index, 3)`),
so that the scene, colours and light of the frame stay those drawn without it:

- `wear_pallet` (the mesh, before rendering; each pallet on its own): every board and block its own
  tone (x0.78..1.18: planks from different trees), one part in twelve a replaced board (fresh pale pine)
  and one in twelve weathered grey; on two pallets in five, pressed-chip blocks (pale, yellowish, the
  speckled `CONCRETE` texture) instead of solid wood ones; on three in five, dirt darkening the parts
  towards the floor (up to x0.5 at the bottom). Plastic pallets get the dirt only.
- `camera_effects` (the rendered frame): wear in the image (three frames in five: low-frequency dark
  blotches on the pallet pixels, up to 35 % darker); glare (one frame in three: one to three bright
  soft spots, a lamp or window flaring, and a veiling haze); auto-exposure (every frame: a gain that
  brings the frame's centre-weighted mean to 0.32..0.55 of full scale, within x0.4..3, then a soft
  shoulder instead of a hard clip, so bright backgrounds darken the pallet and dark ones blow it out);
  lens distortion (one frame in two: radial Brown-Conrady k1 -0.30..0.05, k2 -0.05..0.10, tangential
  +-0.002, the frame zoomed in until no pixel falls outside the render; RGB bilinear, labels and depth
  nearest, so they stay aligned; K becomes the zoomed camera's and the coefficients, OpenCV order
  k1, k2, p1, p2, k3, the bundle's `dist`: perception undistorts such a frame before it segments it,
  training reads the distorted image as it is, for cameras whose coefficients nobody gives).

Motion blur, defocus, sensor noise, white balance, gamma, JPEG and vignetting are drawn per training
step by `perception.training_batches.augment`, so they are not baked in here.

Public API: `wear_pallet`, `camera_effects`, `distortion_maps`.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.sim.world import LabeledMesh, Texture

_PALLET = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
_FRESH_PINE = np.array([0.86, 0.72, 0.50])
_CHIP = np.array([0.80, 0.68, 0.46])


def _parts(mesh: LabeledMesh) -> list[np.ndarray]:
    """Triangle indices of each connected piece (a board or a block) of the pallet-class triangles."""
    rows = np.nonzero(np.isin(mesh.classes, _PALLET))[0]
    if rows.size == 0:
        return []
    tri = mesh.triangles[rows]
    n = mesh.vertices.shape[0]
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]]])
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    piece = component[tri[:, 0]]
    return [rows[piece == c] for c in np.unique(piece)]


def wear_pallet(mesh: LabeledMesh, plastic: bool, real: np.random.Generator) -> LabeledMesh:
    """A copy of one pallet's mesh (world frame, with its load) with per-part tones, replaced and
    weathered boards, pressed-chip blocks and dirt towards the floor (module docstring); the load and
    the geometry are untouched."""
    out = LabeledMesh.merge([mesh, LabeledMesh.empty()])  # albedo and texture copied
    parts = _parts(out)
    if not parts:
        return out
    z = out.vertices[:, 2]
    z_lo, z_hi = (
        float(z[out.triangles[np.concatenate(parts)]].min()),
        float(z[out.triangles[np.concatenate(parts)]].max()),
    )
    dirt = real.uniform(0.1, 0.5) if real.random() < 0.6 else 0.0
    chip = (not plastic) and real.random() < 0.4
    chip_colour = _CHIP * real.uniform(0.8, 1.12) * real.uniform(0.95, 1.05, 3)
    for rows in parts:
        if not plastic:
            block = bool(np.any(np.abs(out.tangent_u[rows, 2]) > 0.9))  # blocks' grain runs vertically
            k = real.random()
            if block and chip:
                out.albedo[rows] = chip_colour
                out.texture[rows] = int(Texture.CONCRETE)
            elif k < 1 / 12:
                out.albedo[rows] = _FRESH_PINE * real.uniform(0.9, 1.1, 3)
            elif k < 2 / 12:
                out.albedo[rows] = np.full(3, real.uniform(0.25, 0.5)) * (1.04, 1.0, 0.93)
            else:
                out.albedo[rows] *= real.uniform(0.78, 1.18)
        height = (z[out.triangles[rows]].mean() - z_lo) / max(z_hi - z_lo, 1e-6)
        out.albedo[rows] *= 1.0 - dirt * (1.0 - height)
    np.clip(out.albedo, 0.0, 1.0, out=out.albedo)
    return out


def _blotches(shape: tuple[int, int], real: np.random.Generator, cell_px: int) -> np.ndarray:
    """A smooth random field 0..1 of `shape`, varying over about `cell_px` pixels."""
    h, w = shape
    low = real.random((max(2, h // cell_px), max(2, w // cell_px))).astype(np.float32)
    return np.clip(cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)


def _glare(img: np.ndarray, real: np.random.Generator) -> None:
    """One to three bright soft spots in the upper two thirds and a veiling haze (in place, 0..1 float)."""
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    light = np.zeros((h, w), np.float32)
    for _ in range(int(real.integers(1, 4))):
        cx, cy, sigma = real.uniform(0, w), real.uniform(0, 2 * h / 3), real.uniform(15.0, 150.0)
        light += real.uniform(0.3, 1.0) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma * sigma))
    tint = real.uniform(0.9, 1.1, 3).astype(np.float32)
    img += light[..., None] * tint
    haze = real.uniform(0.0, 0.15)
    img += haze * (1.0 - np.minimum(img, 1.0))


def _expose(img: np.ndarray, real: np.random.Generator) -> np.ndarray:
    """Auto-exposure to a centre-weighted mean of 0.32..0.55 (gain x0.4..3) and a soft shoulder (0..1 float)."""
    h, w = img.shape[:2]
    yy, xx = np.ogrid[0:h, 0:w]
    weight = np.exp(-(((yy - h / 2) / (0.5 * h)) ** 2 + ((xx - w / 2) / (0.5 * w)) ** 2)).astype(np.float32)
    luma = img @ np.array([0.299, 0.587, 0.114], np.float32)
    mean = float((luma * weight).sum() / weight.sum())
    gain = float(np.clip(real.uniform(0.32, 0.55) / max(mean, 1e-3), 0.4, 3.0))
    x = img * gain
    knee = real.uniform(0.7, 0.9)
    soft = knee + (1.0 - knee) * np.tanh((x - knee) / (1.0 - knee))
    return np.where(x > knee, soft, x)


def distortion_maps(
    K: np.ndarray, shape: tuple[int, int], dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remap tables (float32 x, y in the pinhole render) for a distorted image of `shape` and its camera
    matrix: the render's focal lengths times the zoom that keeps every pixel's source inside the render."""
    h, w = shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    def sources(points: np.ndarray, zoom: float) -> np.ndarray:
        K_out = np.array([[fx * zoom, 0, cx], [0, fy * zoom, cy], [0, 0, 1]])
        norm = cv2.undistortPoints(points.reshape(-1, 1, 2), K_out, dist).reshape(-1, 2)
        return norm * (fx, fy) + (cx, cy)

    edge = np.concatenate(
        [
            np.stack([np.linspace(0, w - 1, 64), np.zeros(64)], 1),
            np.stack([np.linspace(0, w - 1, 64), np.full(64, h - 1)], 1),
            np.stack([np.zeros(48), np.linspace(0, h - 1, 48)], 1),
            np.stack([np.full(48, w - 1), np.linspace(0, h - 1, 48)], 1),
        ]
    ).astype(np.float32)
    zoom = 1.0
    for _ in range(6):  # the sources of the border pixels inside the render (half a pixel to spare)
        src = sources(edge, zoom)
        over = max(
            float(np.max(np.abs(src[:, 0] - cx) / max(cx - 0.5, w - 1.5 - cx))),
            float(np.max(np.abs(src[:, 1] - cy) / max(cy - 0.5, h - 1.5 - cy))),
        )
        if over <= 1.0:
            break
        zoom *= over * 1.001
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    src = sources(np.stack([xx.ravel(), yy.ravel()], 1), zoom).astype(np.float32)
    K_out = np.array(K, dtype=np.float64)
    K_out[0, 0], K_out[1, 1] = fx * zoom, fy * zoom
    return src[:, 0].reshape(h, w), src[:, 1].reshape(h, w), K_out


def _distort(bundle: FrameBundle, rgb: np.ndarray, real: np.random.Generator) -> tuple[FrameBundle, np.ndarray]:
    """The bundle (labels, depth, K, truth) and RGB as a camera with random radial and tangential distortion."""
    dist = np.array(
        [
            real.uniform(-0.30, 0.05),
            real.uniform(-0.05, 0.10),
            real.uniform(-0.002, 0.002),
            real.uniform(-0.002, 0.002),
            0.0,
        ]
    )
    map_x, map_y, K = distortion_maps(np.asarray(bundle.K, float), rgb.shape[:2], dist)
    rgb = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    nearest, edge = cv2.INTER_NEAREST, cv2.BORDER_REPLICATE
    depth = cv2.remap(np.asarray(bundle.depth, np.float32), map_x, map_y, nearest, borderMode=edge).astype(
        bundle.depth.dtype, copy=False
    )
    labels = None if bundle.labels is None else cv2.remap(bundle.labels, map_x, map_y, nearest, borderMode=edge)
    return dataclasses.replace(bundle, depth=depth, labels=labels, K=K, dist=dist), rgb


def camera_effects(bundle: FrameBundle, real: np.random.Generator) -> FrameBundle:
    """The rendered frame as a real camera gives it: wear on the pallet pixels, glare, auto-exposure and
    lens distortion (module docstring). A bundle without RGB is returned as it is."""
    if bundle.rgb is None:
        return bundle
    img = bundle.rgb.astype(np.float32) / 255.0
    if bundle.labels is not None and real.random() < 0.6:
        pallet = np.isin(bundle.labels, _PALLET)
        if pallet.any():
            field = _blotches(img.shape[:2], real, int(real.integers(8, 40)))
            img[pallet] *= (1.0 - real.uniform(0.1, 0.35) * field[pallet])[:, None]
    if real.random() < 1 / 3:
        _glare(img, real)
    img = _expose(img, real)
    rgb = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if real.random() < 0.5:
        bundle, rgb = _distort(bundle, rgb, real)
    return dataclasses.replace(bundle, rgb=rgb)
