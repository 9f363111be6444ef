"""Exact, vectorised ray casting against textured rectangles (the sample scene's renderer).

The procedural sample scene (:mod:`freescale_core.scene.sample`) is made of one primitive:
a one-sided, textured rectangle ("quad") in 3D. A box is six quads with outward normals.
This module intersects rays with quads and looks textures up; it knows nothing about the
scene layout, cameras on disk or files.

Conventions:

* A quad has a centre ``c``, unit in-plane axes ``right`` and ``up`` and half sizes
  ``(hr, hu)`` in metres. Its normal is ``right x up`` and it is visible from that side only
  (back faces are culled), so a closed box shows only its outside.
* Face coordinates of a point ``p`` on the quad: ``a = (p - c) . right``,
  ``b = (p - c) . up``, with ``|a| <= hr`` and ``|b| <= hu``.
* Texture coordinates: ``u = (a + hr) / period_r``, ``v = (hu - b) / period_u`` (texture row 0
  at the top of the face as seen from the front, not mirrored). ``period`` is the size in
  metres of one copy of the texture; a face whose period equals its size shows the photo
  once (stretched), a smaller period tiles it.
* Pinhole rays follow COLMAP/OpenCV: pixel ``(x, y)`` has its centre at ``(x + 0.5, y + 0.5)``
  and its ray is ``d_cam = K^-1 [x + 0.5, y + 0.5, 1] = (xn, yn, 1)`` (not normalised), so the
  ray parameter ``t`` of a hit *is* its camera-frame depth ``z``.

Everything is element-wise numpy (no reductions along rays), so a pixel's result does not
depend on which other pixels are cast with it: rendering a crop or a bounding box of a quad
gives bit-identical values to rendering the full image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freescale_core.errors import ShapeError


# --------------------------------------------------------------------------- quads
@dataclass(frozen=True)
class Quads:
    """Q one-sided textured rectangles (world frame, metres).

    Attributes:
        center: ``[Q, 3]`` centres.
        right: ``[Q, 3]`` unit in-plane axis (texture +u direction).
        up: ``[Q, 3]`` unit in-plane axis orthogonal to ``right`` (texture -v direction).
        half: ``[Q, 2]`` half sizes ``(hr, hu)`` along ``right`` and ``up``.
        tex_id: ``[Q]`` int index into the :class:`TextureBank`.
        period: ``[Q, 2]`` metres per texture copy along ``right`` and ``up``.
        wrap: ``[Q]`` bool; True repeats the texture (tiling), False clamps at its border.
        shade: ``[Q]`` float Lambertian factor (ambient + diffuse) of the face; faces are
            flat and the light directional, so shading is constant per quad.
    """

    center: np.ndarray
    right: np.ndarray
    up: np.ndarray
    half: np.ndarray
    tex_id: np.ndarray
    period: np.ndarray
    wrap: np.ndarray
    shade: np.ndarray

    def __post_init__(self) -> None:
        q = np.asarray(self.center).shape[0]
        for name, shape in (("center", (q, 3)), ("right", (q, 3)), ("up", (q, 3)),
                            ("half", (q, 2)), ("tex_id", (q,)), ("period", (q, 2)),
                            ("wrap", (q,)), ("shade", (q,))):
            if np.asarray(getattr(self, name)).shape != shape:
                raise ShapeError(name, np.asarray(getattr(self, name)).shape, str(list(shape)))

    def __len__(self) -> int:
        return self.center.shape[0]

    @property
    def normal(self) -> np.ndarray:
        """``[Q, 3]`` outward unit normals ``right x up``."""
        return np.cross(self.right, self.up)

    @property
    def area(self) -> np.ndarray:
        """``[Q]`` areas in square metres."""
        return 4.0 * self.half[:, 0] * self.half[:, 1]

    def corners(self) -> np.ndarray:
        """``[Q, 4, 3]`` corner points."""
        s = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        return (self.center[:, None, :]
                + s[None, :, 0:1] * self.half[:, None, 0:1] * self.right[:, None, :]
                + s[None, :, 1:2] * self.half[:, None, 1:2] * self.up[:, None, :])


def box_faces(center: np.ndarray, half_size: np.ndarray, yaw_deg: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The six outward faces of a box rotated by ``yaw_deg`` about world +z.

    Args:
        center: ``[3]`` box centre.
        half_size: ``[3]`` half extents along the box's own x, y, z axes.
        yaw_deg: rotation about world +z, degrees.
    Returns:
        ``(center [6, 3], right [6, 3], up [6, 3], half [6, 2])`` in face order
        +x, -x, +y, -y, +z (top), -z (bottom). Side faces have ``up`` = +z.
    """
    c = np.asarray(center, dtype=np.float64)
    h = np.asarray(half_size, dtype=np.float64)
    psi = np.radians(yaw_deg)
    ex = np.array([np.cos(psi), np.sin(psi), 0.0])
    ey = np.array([-np.sin(psi), np.cos(psi), 0.0])
    ez = np.array([0.0, 0.0, 1.0])
    # (normal, right, up, (half_r, half_u)) with right x up = normal
    faces = [
        (ex, ey, ez, (h[1], h[2])), (-ex, -ey, ez, (h[1], h[2])),
        (ey, -ex, ez, (h[0], h[2])), (-ey, ex, ez, (h[0], h[2])),
        (ez, ex, ey, (h[0], h[1])), (-ez, ex, -ey, (h[0], h[1])),
    ]
    offsets = np.array([h[0], h[0], h[1], h[1], h[2], h[2]])
    centers = np.stack([c + off * f[0] for off, f in zip(offsets, faces)])
    rights = np.stack([f[1] for f in faces])
    ups = np.stack([f[2] for f in faces])
    halves = np.array([f[3] for f in faces], dtype=np.float64)
    return centers, rights, ups, halves


# --------------------------------------------------------------------------- intersection
@dataclass
class Hits:
    """Nearest hits of a set of rays (any leading shape ``S``).

    Attributes:
        t: ``S`` float64 ray parameter of the hit (camera z for pinhole rays), ``inf`` = miss.
        quad: ``S`` int32 index of the quad hit, ``-1`` = miss.
        a, b: ``S`` float64 face coordinates of the hit (0 for misses).
    """

    t: np.ndarray
    quad: np.ndarray
    a: np.ndarray
    b: np.ndarray


def _pixel_range(lo: float, hi: float, n: int) -> tuple[int, int]:
    """Pixel indices ``[i0, i1)`` whose centres ``i + 0.5`` may lie in ``[lo, hi]``."""
    i0 = int(np.clip(np.floor(lo - 0.5), 0, n))
    i1 = int(np.clip(np.ceil(hi - 0.5) + 1, 0, n))
    return i0, i1


def cast_pinhole(quads: Quads, world_from_cam: np.ndarray, fx: float, fy: float, cx: float,
                 cy: float, width: int, height: int, near: float,
                 rows: tuple[int, int] | None = None) -> Hits:
    """Nearest quad hit of every pixel-centre ray of a pinhole camera.

    Each quad is only tested against the pixels inside its projected bounding box (plus one
    pixel), when all its corners are in front of the camera; otherwise against all pixels.
    Results are identical to testing all pixels (see the module note on element-wise maths).

    Args:
        quads: the scene.
        world_from_cam: ``[4, 4]`` camera pose, OpenCV axes.
        fx, fy, cx, cy: intrinsics in pixels (pixel centres at ``i + 0.5``).
        width, height: image size in pixels.
        near: hits with camera depth ``<= near`` (metres) are ignored.
        rows: optional band ``[r0, r1)`` of image rows to cast (bit-identical to the same
            rows of a full cast; bounds memory for large images).
    Returns:
        :class:`Hits` with arrays ``[H, W]`` (``[r1 - r0, W]`` with ``rows``); ``t`` is the
        camera-frame depth.
    """
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError("world_from_cam", T.shape, "[4, 4]")
    W = int(width)
    r0, r1 = (0, int(height)) if rows is None else (int(rows[0]), int(rows[1]))
    H = r1 - r0
    R, o = T[:3, :3], T[:3, 3]
    # quad frames in camera coordinates: x_cam = R^T (x_world - o)
    c_c = (quads.center - o) @ R  # [Q, 3]
    r_c = quads.right @ R
    u_c = quads.up @ R
    n_c = quads.normal @ R
    num = np.sum(n_c * c_c, axis=1)  # [Q] n.(c - o); < 0 iff the camera is on the front side
    r_off = np.sum(r_c * c_c, axis=1)
    u_off = np.sum(u_c * c_c, axis=1)
    corners_c = (quads.corners() - o) @ R  # [Q, 4, 3]

    xs = (np.arange(W, dtype=np.float64) + 0.5 - cx) / fx  # [W]
    ys = (np.arange(r0, r1, dtype=np.float64) + 0.5 - cy) / fy  # [H]
    t_best = np.full((H, W), np.inf)
    q_best = np.full((H, W), -1, dtype=np.int32)
    a_best = np.zeros((H, W))
    b_best = np.zeros((H, W))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for q in range(len(quads)):
            if not num[q] < 0.0:
                continue  # back face (or edge-on): invisible from this camera
            z = corners_c[q, :, 2]
            if np.all(z > near):
                pu = fx * corners_c[q, :, 0] / z + cx
                pv = fy * corners_c[q, :, 1] / z + cy
                x0, x1 = _pixel_range(pu.min() - 1.0, pu.max() + 1.0, W)
                y0, y1 = _pixel_range(pv.min() - 1.0 - r0, pv.max() + 1.0 - r0, H)
            elif np.all(z <= near):
                continue
            else:
                x0, x1, y0, y1 = 0, W, 0, H
            if x1 <= x0 or y1 <= y0:
                continue
            xb = xs[None, x0:x1]
            yb = ys[y0:y1, None]
            den = n_c[q, 0] * xb + n_c[q, 1] * yb + n_c[q, 2]
            t = num[q] / den
            a = t * (r_c[q, 0] * xb + r_c[q, 1] * yb + r_c[q, 2]) - r_off[q]
            b = t * (u_c[q, 0] * xb + u_c[q, 1] * yb + u_c[q, 2]) - u_off[q]
            tb = t_best[y0:y1, x0:x1]
            m = ((den < 0.0) & (t > near) & (t < tb)
                 & (np.abs(a) <= quads.half[q, 0]) & (np.abs(b) <= quads.half[q, 1]))
            if not m.any():
                continue
            tb[m] = t[m]
            q_best[y0:y1, x0:x1][m] = q
            a_best[y0:y1, x0:x1][m] = a[m]
            b_best[y0:y1, x0:x1][m] = b[m]
    return Hits(t_best, q_best, a_best, b_best)


def cast_rays(quads: Quads, origins: np.ndarray, dirs: np.ndarray, near: float = 0.0) -> Hits:
    """Nearest quad hit of arbitrary world-frame rays ``origins + t * dirs``.

    Args:
        quads: the scene.
        origins: ``[R, 3]`` (or broadcastable) ray origins.
        dirs: ``[R, 3]`` ray directions (any length; ``t`` is in units of ``|dirs|``).
        near: hits with ``t <= near`` are ignored.
    Returns:
        :class:`Hits` with arrays ``[R]``.
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ShapeError("dirs", d.shape, "[R, 3]")
    o = np.broadcast_to(o, d.shape)
    n_rays = d.shape[0]
    n = quads.normal
    t_best = np.full(n_rays, np.inf)
    q_best = np.full(n_rays, -1, dtype=np.int32)
    a_best = np.zeros(n_rays)
    b_best = np.zeros(n_rays)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for q in range(len(quads)):
            co = quads.center[q] - o  # [R, 3]
            den = d @ n[q]
            t = (co @ n[q]) / den
            a = t * (d @ quads.right[q]) - co @ quads.right[q]
            b = t * (d @ quads.up[q]) - co @ quads.up[q]
            m = ((den < 0.0) & (t > near) & (t < t_best)
                 & (np.abs(a) <= quads.half[q, 0]) & (np.abs(b) <= quads.half[q, 1]))
            t_best[m] = t[m]
            q_best[m] = q
            a_best[m] = a[m]
            b_best[m] = b[m]
    return Hits(t_best, q_best, a_best, b_best)


# --------------------------------------------------------------------------- textures
class TextureBank:
    """T square RGB textures with mip-maps, sampled trilinearly (repeat or clamp).

    Every mip level of every texture is stored twice with a one-texel border, once padded
    for repeating (border = opposite edge) and once for clamping (border = edge), as RGBA
    float32 texels packed into one flat buffer; a bilinear tap is then one ``np.take`` of
    16-byte elements, with no per-tap wrapping logic.

    Args:
        textures: ``[T, S, S, 3]`` float32 in [0, 1]; ``S`` a power of two.
    """

    def __init__(self, textures: np.ndarray):
        tex = np.asarray(textures, dtype=np.float32)
        if tex.ndim != 4 or tex.shape[1] != tex.shape[2] or tex.shape[3] != 3:
            raise ShapeError("textures", tex.shape, "[T, S, S, 3]")
        S = tex.shape[1]
        if S < 1 or S & (S - 1):
            raise ValueError(f"texture size must be a power of two, got {S}")
        self.n_textures, self.size = tex.shape[0], S
        levels = [tex]
        while levels[-1].shape[1] > 1:
            t = levels[-1]
            levels.append(0.25 * (t[:, 0::2, 0::2] + t[:, 1::2, 0::2]
                                  + t[:, 0::2, 1::2] + t[:, 1::2, 1::2]))
        self.n_levels = len(levels)
        self._sizes = np.array([lv.shape[1] for lv in levels], dtype=np.int64)
        blocks = []
        for lv in levels:
            lv4 = np.concatenate([lv, np.zeros(lv.shape[:3] + (1,), np.float32)], axis=3)
            clamp = np.pad(lv4, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
            wrap = np.pad(lv4, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="wrap")
            # variant index = 2 * texture + wrap
            blocks.append(np.stack([clamp, wrap], axis=1).reshape(-1, 4))
        self.offsets = np.cumsum([0] + [len(b) for b in blocks])[:-1].astype(np.int64)
        flat = np.ascontiguousarray(np.concatenate(blocks))  # [M, 4] float32
        self._texels = flat.view(np.complex128).reshape(-1)  # [M] 16-byte texels

    def _tap(self, idx: np.ndarray) -> np.ndarray:
        return np.take(self._texels, idx).view(np.float32).reshape(-1, 4)

    def _bilinear(self, var: np.ndarray, u: np.ndarray, v: np.ndarray,
                  level: np.ndarray) -> np.ndarray:
        s = self._sizes[level]  # [R] int64 level size
        sp = s + 2  # padded row length
        sf = s.astype(np.float32)
        x = u * sf - np.float32(0.5)
        y = v * sf - np.float32(0.5)
        x0f, y0f = np.floor(x), np.floor(y)
        wx = (x - x0f)[:, None]
        wy = (y - y0f)[:, None]
        i00 = (self.offsets[level] + var * (sp * sp) + (y0f.astype(np.int64) + 1) * sp
               + (x0f.astype(np.int64) + 1))
        top = self._tap(i00)
        top += (self._tap(i00 + 1) - top) * wx
        bot = self._tap(i00 + sp)
        bot += (self._tap(i00 + sp + 1) - bot) * wx
        top += (bot - top) * wy
        return top

    def sample(self, tex: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray,
               wrap: np.ndarray) -> np.ndarray:
        """Trilinear texture lookup.

        Args:
            tex: ``[R]`` int texture index.
            u, v: ``[R]`` texture coordinates (1.0 = one texture width/height, v downwards).
            lod: ``[R]`` mip level (0 = full resolution), fractional; clipped to the pyramid.
            wrap: ``[R]`` bool, repeat (True) or clamp (False) outside [0, 1].
        Returns:
            ``[R, 3]`` float32 RGB.
        """
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        wrap = np.asarray(wrap, dtype=bool)
        # reduce to [0, 1] in float64 (tiled coordinates can be large), then float32
        u = np.where(wrap, u - np.floor(u), np.clip(u, 0.0, 1.0)).astype(np.float32)
        v = np.where(wrap, v - np.floor(v), np.clip(v, 0.0, 1.0)).astype(np.float32)
        var = 2 * np.asarray(tex, dtype=np.int64) + wrap
        lod = np.clip(np.asarray(lod, dtype=np.float32), 0.0, self.n_levels - 1)
        l0f = np.floor(lod)
        w = (lod - l0f)[:, None]
        l0 = l0f.astype(np.int64)
        l1 = np.minimum(l0 + 1, self.n_levels - 1)
        c0 = self._bilinear(var, u, v, l0)
        c0 += (self._bilinear(var, u, v, l1) - c0) * w
        return c0[:, :3]
