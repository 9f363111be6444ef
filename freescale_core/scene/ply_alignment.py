"""Does a user's Gaussian PLY live in the scene's frame? (A check before it is used as is.)

Frame contract: a PLY placed in the scene folder (``gaussians.ply`` or
``point_cloud/iteration_*/point_cloud.ply``) must be in the world of the scene's cameras:
COLMAP's world for a COLMAP scene, the transforms.json world (after undoing
``applied_transform``) for a nerfstudio scene. Trainers that normalise the world (gsplat's
``normalize_world_space``, nerfstudio's dataparser ``transform`` + ``scale``) save PLYs in
*their* frame; used as is, such a PLY is seen by no camera and the scene ends with 0 free
views.

:func:`check_alignment` renders a few training views from the PLY (small, ~96 px) and
compares them with the photos (on the object-mask pixels when the scene has masks); below
``min_psnr`` it raises a :class:`PlyFrameError` that
says what was found: the PSNR, and the ratio of the Gaussians' extent (5-95% quantiles) to
the cameras' and the distance between their centres, in camera-extent units.
"""

from __future__ import annotations

import numpy as np

from freescale_core.errors import SceneError

__all__ = ["PlyFrameError", "check_alignment", "alignment_stats"]


class PlyFrameError(SceneError):
    """A user PLY does not reproduce the scene's photos: most likely another frame."""


def alignment_stats(g, scene, n_views: int = 3, max_side: int = 96,
                    background=(0.0, 0.0, 0.0), backend: str = "auto") -> dict:
    from freescale_core.raster import render_gaussians
    from freescale_core.scene.images import psnr_u8
    from freescale_core.scene.images import resize_area as _resize

    cams = scene.cameras
    N = len(cams)
    idx = np.unique(np.linspace(0, N - 1, min(n_views, N)).round().astype(int))
    psnrs = []
    for i in idx:
        s = min(1.0, max_side / float(max(cams.width[i], cams.height[i])))
        c = cams.subset([int(i)]).scaled(s) if s < 1.0 else cams.subset([int(i)])
        rgb, _, _ = render_gaussians(g, c.world_from_cam[0], float(c.fx[0]), float(c.fy[0]),
                                     float(c.cx[0]), float(c.cy[0]), int(c.width[0]),
                                     int(c.height[0]), background=tuple(background),
                                     backend=backend)
        photo = _resize(scene.load_image(int(i)), int(c.width[0]), int(c.height[0]))
        r8 = np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if getattr(scene, "has_masks", False):  # an object capture: the object's pixels only
            from freescale_core.scene.io.masks import resize_mask

            mk = resize_mask(scene.load_mask(int(i)), int(c.width[0]), int(c.height[0]))
            mse = float(np.mean((r8[mk].astype(np.float64) - photo[mk]) ** 2)) / 255.0**2 \
                if mk.any() else 0.0
            psnrs.append(float("inf") if mse == 0 else -10.0 * float(np.log10(mse)))
            continue
        psnrs.append(float(psnr_u8(r8, photo)))
    m = np.asarray(g.means, np.float64)
    glo, ghi = np.quantile(m, 0.05, axis=0), np.quantile(m, 0.95, axis=0)
    c = cams.centers
    ref = np.concatenate([c, scene.points_xyz]) if len(scene.points_xyz) else c
    clo, chi = np.quantile(ref, 0.05, axis=0), np.quantile(ref, 0.95, axis=0)
    cext = float(np.linalg.norm(chi - clo)) or 1.0
    return {"psnr": psnrs, "views": [scene.image_names[i] for i in idx],
            "extent_ratio": float(np.linalg.norm(ghi - glo)) / cext,
            "centre_offset": float(np.linalg.norm(0.5 * (glo + ghi) - 0.5 * (clo + chi))) / cext}


def check_alignment(g, scene, ply_path, min_psnr: float = 12.0, **kw) -> dict:
    """Raise :class:`PlyFrameError` when the PLY's renders do not match the photos."""
    st = alignment_stats(g, scene, **kw)
    med = float(np.median(st["psnr"]))
    st["psnr_median"] = med
    if med < min_psnr:
        raise PlyFrameError(
            scene.scene_id, f"the user PLY does not reproduce the photos: median PSNR "
            f"{med:.1f} dB over training views {st['views']} (threshold {min_psnr:g} dB); its "
            f"Gaussians span {st['extent_ratio']:.3g}x the cameras' extent, centred "
            f"{st['centre_offset']:.3g} camera-extents away. Likely it is in another frame "
            "(gsplat normalize_world_space, nerfstudio's dataparser transform/scale): export "
            "it in the scene's camera frame, or remove it to reconstruct here",
            ply_path)
    return st
