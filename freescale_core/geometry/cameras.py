"""Camera conventions, in one place.

Internal convention (everywhere in FreeScale):

* camera axes are OpenCV's: +x right, +y down, +z forward (viewing direction);
* poses are 4x4 rigid transforms named by the frames they map between:
  ``world_from_cam`` maps camera-frame points to world points (camera-to-world, "c2w"),
  ``cam_from_world`` is its inverse ("w2c", what COLMAP stores);
* quaternions are named by their layout: ``quat_wxyz`` (COLMAP text files, PLY ``rot_*``)
  or ``quat_xyzw`` (pycolmap's ``Rotation3d.quat``, scipy);
* intrinsics are pinhole ``fx, fy, cx, cy`` in pixels, with the pixel centre convention of
  COLMAP/OpenCV: the centre of the top-left pixel is at (0.5, 0.5).

Other conventions are converted here, at the edges, and nowhere else:

* COLMAP: ``cam_from_world`` from ``quat_wxyz`` + ``t``.
* nerfstudio / DL3DV ``transforms.json``: ``transform_matrix`` is camera-to-world in OpenGL
  camera axes (+y up, +z backward), optionally after an ``applied_transform`` (3x4) that maps
  the original (COLMAP) world into the nerfstudio world.
* LVSM metadata: ``w2c`` (4x4, OpenCV axes) and ``fxfycxcy``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from freescale_core.errors import ShapeError

# OpenGL <-> OpenCV camera axes: flip y and z. Its own inverse.
CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


# --------------------------------------------------------------------------- rotations
def quat_wxyz_to_rotmat(quat_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``[..., 4]`` (w, x, y, z) to rotation matrices ``[..., 3, 3]``.

    The quaternion is normalised first, so any non-zero 4-vector is accepted.
    """
    q = np.asarray(quat_wxyz, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ShapeError("quat_wxyz", q.shape, "[..., 4]")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (w, x, y, z), w >= 0.

    Uses the numerically stable branch on the largest of (w, x, y, z).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ShapeError("R", R.shape, "[..., 3, 3]")
    batch = R.shape[:-2]
    M = R.reshape(-1, 3, 3)
    m00, m01, m02 = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    m10, m11, m12 = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    m20, m21, m22 = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    # 4 * (w^2, x^2, y^2, z^2)
    sq = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    k = np.argmax(sq, axis=-1)
    q = np.empty((M.shape[0], 4))
    # each candidate row is (w, x, y, z) * 4 * component k
    cands = np.stack(
        [
            np.stack([sq[:, 0], m21 - m12, m02 - m20, m10 - m01], -1),
            np.stack([m21 - m12, sq[:, 1], m01 + m10, m02 + m20], -1),
            np.stack([m02 - m20, m01 + m10, sq[:, 2], m12 + m21], -1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, sq[:, 3]], -1),
        ],
        axis=1,
    )
    q = cands[np.arange(M.shape[0]), k]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(batch + (4,))


def quat_xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """Reorder quaternions from (x, y, z, w) (pycolmap, scipy) to (w, x, y, z)."""
    q = np.asarray(q_xyzw)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def quat_wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """Reorder quaternions from (w, x, y, z) to (x, y, z, w) (pycolmap, scipy)."""
    q = np.asarray(q_wxyz)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def slerp_wxyz(q0: np.ndarray, q1: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions ``[..., 4]`` (wxyz).

    ``t = 0`` gives ``q0``, ``t = 1`` gives ``q1``; takes the short arc.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    small = sin_t < 1e-8
    w0 = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / np.where(small, 1.0, sin_t))
    w1 = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, sin_t))
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees between rotation matrices ``[..., 3, 3]``."""
    rel = np.einsum("...ji,...jk->...ik", R_a, R_b)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


# --------------------------------------------------------------------------- poses
def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotations ``[..., 3, 3]`` and translations ``[..., 3]`` into ``[..., 4, 4]``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``[..., 4, 4]`` (exact: R^T, -R^T t)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``world_from_cam`` ``[..., 4, 4]`` for cameras at ``eye`` looking at ``target``.

    OpenCV axes: the camera's +z points at the target and its -y (image up) is as close to
    ``up`` as possible. Where ``up`` is parallel to the viewing direction a fallback up
    vector is used, so the result is always a proper rotation.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.broadcast_to(np.asarray(up, dtype=np.float64), eye.shape)
    z = target - eye
    z = z / np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), 1e-12)
    x = np.cross(z, up)  # right = down x forward (OpenCV x = y cross z) with down = -up
    bad = np.linalg.norm(x, axis=-1) < 1e-6
    if np.any(bad):
        alt = np.where(np.abs(z[..., 0:1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        x = np.where(bad[..., None], np.cross(z, np.cross(alt, z)), x)
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)  # columns are camera axes in world
    return make_pose(R, eye)


# --------------------------------------------------------------------------- converters
def colmap_to_cam_from_world(quat_wxyz: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP image pose (``QW QX QY QZ TX TY TZ``) to ``cam_from_world`` ``[..., 4, 4]``."""
    return make_pose(quat_wxyz_to_rotmat(quat_wxyz), tvec)


def cam_from_world_to_colmap(cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` ``[..., 4, 4]`` to COLMAP ``(quat_wxyz, tvec)``."""
    T = np.asarray(cam_from_world, dtype=np.float64)
    return rotmat_to_quat_wxyz(T[..., :3, :3]), T[..., :3, 3].copy()


def nerfstudio_to_world_from_cam(
    transform_matrix: np.ndarray, applied_transform: np.ndarray | None = None
) -> np.ndarray:
    """nerfstudio/DL3DV ``transform_matrix`` (c2w, OpenGL axes) to ``world_from_cam`` (OpenCV).

    Args:
        transform_matrix: ``[..., 4, 4]`` (or ``[..., 3, 4]``) camera-to-world, OpenGL axes.
        applied_transform: optional ``[3, 4]`` or ``[4, 4]`` transform that nerfstudio applied
            to the original world; when given, it is undone so the result lives in the
            original (e.g. COLMAP) world.
    Returns:
        ``[..., 4, 4]`` world_from_cam in OpenCV camera axes.
    """
    c2w = _as_4x4(transform_matrix, "transform_matrix")
    T = c2w @ CV_FROM_GL
    if applied_transform is not None:
        A = _as_4x4(applied_transform, "applied_transform")
        T = np.linalg.inv(A) @ T
    return T


def world_from_cam_to_nerfstudio(
    world_from_cam: np.ndarray, applied_transform: np.ndarray | None = None
) -> np.ndarray:
    """Inverse of :func:`nerfstudio_to_world_from_cam`."""
    T = _as_4x4(world_from_cam, "world_from_cam")
    if applied_transform is not None:
        T = _as_4x4(applied_transform, "applied_transform") @ T
    return T @ CV_FROM_GL


def lvsm_frame(
    world_from_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float
) -> dict:
    """One LVSM metadata frame: ``{"w2c": 4x4 list, "fxfycxcy": [fx, fy, cx, cy]}``."""
    w2c = invert_pose(world_from_cam)
    return {"w2c": w2c.tolist(), "fxfycxcy": [float(fx), float(fy), float(cx), float(cy)]}


def lvsm_to_world_from_cam(frame: dict) -> tuple[np.ndarray, np.ndarray]:
    """LVSM metadata frame to ``(world_from_cam [4, 4], fxfycxcy [4])``."""
    w2c = _as_4x4(np.asarray(frame["w2c"], dtype=np.float64), "w2c")
    return invert_pose(w2c), np.asarray(frame["fxfycxcy"], dtype=np.float64)


def _as_4x4(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] == (3, 4):
        bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), T.shape[:-2] + (1, 4))
        T = np.concatenate([T, bottom], axis=-2)
    if T.shape[-2:] != (4, 4):
        raise ShapeError(name, T.shape, "[..., 4, 4] or [..., 3, 4]")
    return T


# --------------------------------------------------------------------------- cameras
@dataclass
class Cameras:
    """A batch of N pinhole cameras in the internal convention.

    Attributes:
        world_from_cam: ``[N, 4, 4]`` float64, OpenCV camera axes.
        fx, fy, cx, cy: ``[N]`` float64 pixels (centre of top-left pixel at 0.5, 0.5).
        width, height: ``[N]`` int image size in pixels.
    """

    world_from_cam: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: np.ndarray
    height: np.ndarray
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.world_from_cam = np.asarray(self.world_from_cam, dtype=np.float64)
        if self.world_from_cam.ndim != 3 or self.world_from_cam.shape[1:] != (4, 4):
            raise ShapeError("world_from_cam", self.world_from_cam.shape, "[N, 4, 4]")
        n = self.world_from_cam.shape[0]
        for name in ("fx", "fy", "cx", "cy"):
            v = np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (n,)).copy()
            setattr(self, name, v)
        for name in ("width", "height"):
            v = np.broadcast_to(np.asarray(getattr(self, name), dtype=np.int64), (n,)).copy()
            setattr(self, name, v)

    def __len__(self) -> int:
        return self.world_from_cam.shape[0]

    @property
    def cam_from_world(self) -> np.ndarray:
        """``[N, 4, 4]`` world-to-camera transforms."""
        return invert_pose(self.world_from_cam)

    @property
    def centers(self) -> np.ndarray:
        """``[N, 3]`` camera centres in world coordinates."""
        return self.world_from_cam[:, :3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """``[N, 3]`` unit viewing directions (camera +z) in world coordinates."""
        return self.world_from_cam[:, :3, 2].copy()

    @property
    def K(self) -> np.ndarray:
        """``[N, 3, 3]`` intrinsic matrices."""
        K = np.zeros((len(self), 3, 3))
        K[:, 0, 0], K[:, 1, 1] = self.fx, self.fy
        K[:, 0, 2], K[:, 1, 2] = self.cx, self.cy
        K[:, 2, 2] = 1.0
        return K

    def subset(self, idx) -> "Cameras":
        """Cameras at indices ``idx`` (any numpy index)."""
        idx = np.atleast_1d(np.arange(len(self))[idx])
        return Cameras(
            self.world_from_cam[idx], self.fx[idx], self.fy[idx], self.cx[idx], self.cy[idx],
            self.width[idx], self.height[idx], dict(self.extras),
        )

    @staticmethod
    def concat(parts: list["Cameras"]) -> "Cameras":
        """Concatenate camera batches."""
        return Cameras(
            np.concatenate([p.world_from_cam for p in parts]),
            *(np.concatenate([getattr(p, n) for p in parts])
              for n in ("fx", "fy", "cx", "cy", "width", "height")),
        )

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points into every camera.

        Args:
            points_world: ``[P, 3]``.
        Returns:
            ``(uv [N, P, 2] pixels, depth [N, P] camera z)``; uv is meaningless where depth <= 0.
        """
        X = np.asarray(points_world, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ShapeError("points_world", X.shape, "[P, 3]")
        cfw = self.cam_from_world
        Xc = np.einsum("nij,pj->npi", cfw[:, :3, :3], X) + cfw[:, None, :3, 3]
        z = Xc[..., 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        u = self.fx[:, None] * Xc[..., 0] / zs + self.cx[:, None]
        v = self.fy[:, None] * Xc[..., 1] / zs + self.cy[:, None]
        return np.stack([u, v], axis=-1), z

    def scaled(self, factor: float) -> "Cameras":
        """Same cameras with images resized by ``factor`` (intrinsics scaled accordingly)."""
        w = np.maximum(1, np.round(self.width * factor)).astype(np.int64)
        h = np.maximum(1, np.round(self.height * factor)).astype(np.int64)
        sx, sy = w / self.width, h / self.height
        return Cameras(self.world_from_cam.copy(), self.fx * sx, self.fy * sy, self.cx * sx,
                       self.cy * sy, w, h, dict(self.extras))
