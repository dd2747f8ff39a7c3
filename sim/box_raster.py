"""A z-buffer rasteriser of textured boxes and convex polygons, in numpy and OpenCV (`sim.pallet_scenes`).

Every box face is a convex polygon: clipped at the near plane (`clip_near`), filled (`cv2.fillConvexPoly`)
within its image bounding box, its inverse depth interpolated in the image plane (exact for a plane) and
tested against the z-buffer. Each pixel gets its polygon's colour (times a repeating texture image sampled at
the pixel's point on the face, a Lambert shade from one directional light with an ambient share, and a
darkening factor) and its semantic label. World frame: metres, any orientation; camera frame: x right,
y down, z forward (OpenCV).

Public API: `Box`, `Canvas`, `clip_near`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Box:
    """An axis-aligned box in its own frame, placed by `R` (3x3) and `t` (3,) in the world frame (metres).

    `size` (dx, dy, dz), centred on its own origin; `label` the semantic class; `colour` RGB 0..1;
    `texture` one of the frame's texture images (index); `texel_m` metres per texel; `grain_axis` the box's
    own axis (0, 1, 2) along which the texture's rows run (a board's grain); `dark` a brightness factor
    (pocket interiors, dirt).
    """

    size: np.ndarray
    R: np.ndarray
    t: np.ndarray
    label: int
    colour: np.ndarray
    texture: int
    texel_m: float
    grain_axis: int = 0
    dark: float = 1.0


_FACES = (  # each face of a unit box: normal axis, sign, the two in-plane axes
    (0, 1, 1, 2),
    (0, -1, 1, 2),
    (1, 1, 0, 2),
    (1, -1, 0, 2),
    (2, 1, 0, 1),
    (2, -1, 0, 1),
)


class Canvas:
    """Colour, labels and a z-buffer of one frame, and the camera that draws into them.

    `K` the pinhole intrinsics (3x3, pixels); `R_cw`, `t_cw` the world-to-camera rotation and translation
    (p_camera = R_cw p_world + t_cw, metres); `size` (width, height) pixels; `textures` the frame's texture
    images (2-D float arrays around 1.0, repeating); `light` (direction the light travels, world frame, unit;
    its RGB colour; the ambient share 0..1). Pixels nothing covers keep label 255 and colour 0.
    """

    def __init__(
        self,
        K: np.ndarray,
        R_cw: np.ndarray,
        t_cw: np.ndarray,
        size: tuple[int, int],
        textures: list[np.ndarray],
        light: tuple[np.ndarray, np.ndarray, float],
    ) -> None:
        self.K, self.R_cw, self.t_cw = K, R_cw, t_cw
        self.w, self.h = size
        self.rgb = np.zeros((self.h, self.w, 3), np.float32)
        self.labels = np.full((self.h, self.w), 255, np.uint8)
        self.inv_z = np.zeros((self.h, self.w), np.float32)  # 1/depth; 0 = nothing drawn yet
        self.textures = textures
        self.light_dir, self.light_rgb, self.ambient = light
        self.K_inv = np.linalg.inv(K)

    def polygon(
        self,
        corners_w: np.ndarray,
        normal_w: np.ndarray,
        axes_w: np.ndarray,
        colour: np.ndarray,
        label: int,
        texture: int,
        texel_m: float,
        dark: float = 1.0,
    ) -> None:
        """Draw one planar convex polygon (N, 3) world corners, outward `normal_w`, texture `axes_w` (2, 3)."""
        cam = corners_w @ self.R_cw.T + self.t_cw
        n_cam = self.R_cw @ normal_w
        if float(n_cam @ cam.mean(axis=0)) >= 0.0:  # seen from behind
            return
        cam = clip_near(cam, 0.02)
        if len(cam) < 3:
            return
        uv = cam @ self.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        x0, y0 = np.floor(uv.min(axis=0)).astype(int)
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.w - 1), min(y1, self.h - 1)
        if x1 < x0 or y1 < y0:
            return
        mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
        pts = np.round((uv - [x0, y0]) * 16).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)
        ys, xs = np.nonzero(mask)
        if ys.size == 0:
            return
        ys, xs = ys + y0, xs + x0
        # the ray through each pixel meets the polygon's plane n.p = d at depth z: 1/z = n.(K^-1 [u v 1]) / d
        d = float(n_cam @ cam[0])
        rays = self.K_inv @ np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, float)])
        inv_z = (n_cam @ rays) / d
        keep = inv_z > self.inv_z[ys, xs]
        if not keep.any():
            return
        ys, xs, inv_z, rays = ys[keep], xs[keep], inv_z[keep], rays[:, keep]
        p_cam = rays / inv_z  # (3, n) points on the polygon, camera frame
        p_w = self.R_cw.T @ (p_cam - self.t_cw[:, None])
        s = (axes_w[0] @ (p_w - corners_w[0][:, None])) / texel_m
        t = (axes_w[1] @ (p_w - corners_w[0][:, None])) / texel_m
        image = self.textures[texture]
        tex = image[t.astype(np.int64) % image.shape[0], s.astype(np.int64) % image.shape[1]]
        shade = self.ambient + (1 - self.ambient) * max(0.0, float(-normal_w @ self.light_dir))
        colour_px = (colour * self.light_rgb * shade * dark)[None, :] * tex[:, None]
        self.rgb[ys, xs] = colour_px
        self.labels[ys, xs] = label
        self.inv_z[ys, xs] = inv_z

    def box(self, b: Box) -> None:
        """Draw the visible faces of a box."""
        half = b.size / 2
        for axis, sign, a1, a2 in _FACES:
            n_local = np.zeros(3)
            n_local[axis] = sign
            e1, e2 = np.zeros(3), np.zeros(3)
            e1[a1], e2[a2] = 1.0, 1.0
            centre = n_local * half
            corners = np.array(
                [centre + s1 * e1 * half + s2 * e2 * half for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            )
            # texture rows run along the grain axis when it lies in the face
            u_ax, v_ax = (e2, e1) if a1 == b.grain_axis else (e1, e2)
            corners_w = corners @ b.R.T + b.t
            dark = b.dark * (0.6 if (axis == 2 and sign < 0) else 1.0)
            self.polygon(
                corners_w,
                b.R @ n_local,
                np.stack([b.R @ u_ax, b.R @ v_ax]),
                b.colour,
                b.label,
                b.texture,
                b.texel_m,
                dark,
            )


def clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """The polygon (N, 3) camera-frame points clipped to z >= near (Sutherland-Hodgman, one plane)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            f = (near - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out) if out else np.zeros((0, 3))
