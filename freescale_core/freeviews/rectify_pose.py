"""Pose rectification of rejected free views (METHOD.md stage 8).

A candidate that fails the quality filter is pulled toward its nearest training camera and
re-rendered, with decreasing steps {0.7, 0.5, 0.3}, until one passes.

* **Nearest** training camera: smallest camera-centre distance (ties: lowest index). Centre
  distance is what the step moves along, and the training camera is where the reconstruction is
  known to be good; orientation is not part of "nearest" (the slerp brings it along).
* **Unit** (``PoseRectifyConfig.step_unit``):

  - ``"fraction"`` (default, ours): a step ``s`` is the *remaining* offset as a fraction of the
    original one: ``c(s) = c_ref + s (c_cand - c_ref)``, ``q(s) = slerp(q_ref, q_cand, s)``.
    ``s = 1`` is the candidate, ``s = 0`` the reference. Scale-free: scenes come in arbitrary
    COLMAP units, so a fixed world distance means different things per scene, and a candidate
    closer than 0.7 units would be pushed *away* from (or past) the reference.
  - ``"world"`` (authors): the camera is put ``s`` world units from the reference along the
    same line, ``c(s) = c_ref + s * unit(c_cand - c_ref)``, rotation slerped by
    ``s / |c_cand - c_ref|``. Steps that are not shorter than the original distance do not move
    toward the reference and are skipped.

Intrinsics and image size are the candidate's, unchanged.
"""

from __future__ import annotations

import numpy as np

from schemas.freeview import PoseRectifyConfig

from freescale_core.geometry.cameras import make_pose, quat_wxyz_to_rotmat, rotmat_to_quat_wxyz, slerp_wxyz
from freescale_core.errors import ShapeError

__all__ = ["nearest_training_camera", "interpolate_pose", "rectification_poses"]


def nearest_training_camera(train_world_from_cam: np.ndarray, world_from_cam: np.ndarray) -> int:
    """Index of the training camera whose centre is nearest to the given camera's centre.

    Args:
        train_world_from_cam: ``[T, 4, 4]`` training poses.
        world_from_cam: ``[4, 4]`` the candidate's pose.
    Returns:
        Training index (lowest index on ties).
    """
    T = np.asarray(train_world_from_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] == 0:
        raise ShapeError("train_world_from_cam", T.shape, "[T>=1, 4, 4]")
    d = np.linalg.norm(T[:, :3, 3] - np.asarray(world_from_cam)[:3, 3], axis=1)
    return int(np.argmin(d))


def interpolate_pose(ref_world_from_cam: np.ndarray, cand_world_from_cam: np.ndarray,
                     s: float) -> np.ndarray:
    """Pose a fraction ``s`` of the way from the reference to the candidate.

    ``s = 0`` returns the reference, ``s = 1`` the candidate; the centre moves on the straight
    line, the rotation by slerp (short arc).

    Args:
        ref_world_from_cam: ``[4, 4]``.
        cand_world_from_cam: ``[4, 4]``.
        s: fraction in [0, 1].
    Returns:
        ``[4, 4]`` world_from_cam.
    """
    A = np.asarray(ref_world_from_cam, dtype=np.float64)
    B = np.asarray(cand_world_from_cam, dtype=np.float64)
    q = slerp_wxyz(rotmat_to_quat_wxyz(A[:3, :3]), rotmat_to_quat_wxyz(B[:3, :3]), float(s))
    c = A[:3, 3] + float(s) * (B[:3, 3] - A[:3, 3])
    return make_pose(quat_wxyz_to_rotmat(q), c)


def rectification_poses(cand_world_from_cam: np.ndarray, ref_world_from_cam: np.ndarray,
                        cfg: PoseRectifyConfig | None = None) -> list[tuple[float, np.ndarray]]:
    """The poses stage 8 tries for one rejected candidate, in order.

    Args:
        cand_world_from_cam: ``[4, 4]`` the rejected candidate.
        ref_world_from_cam: ``[4, 4]`` its nearest training camera.
        cfg: steps and unit.
    Returns:
        ``[(step, world_from_cam [4, 4]), ...]`` with ``step`` in the configured unit; empty when
        rectification is disabled or (world unit) every step is too long.
    """
    cfg = cfg or PoseRectifyConfig()
    if not cfg.enabled:
        return []
    dist = float(np.linalg.norm(np.asarray(cand_world_from_cam)[:3, 3]
                                - np.asarray(ref_world_from_cam)[:3, 3]))
    out = []
    for step in cfg.steps:
        if cfg.step_unit == "fraction":
            frac = step
        else:
            if dist <= 0 or step >= dist:
                continue
            frac = step / dist
        if not 0.0 <= frac < 1.0:
            continue
        out.append((float(step), interpolate_pose(ref_world_from_cam, cand_world_from_cam, frac)))
    return out
