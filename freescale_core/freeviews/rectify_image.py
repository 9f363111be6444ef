"""Image rectification of kept free views (METHOD.md stage 10), pluggable.

Backends (``RectifierConfig.backend``), looked up in a registry (``register_rectifier`` adds
more):

* ``"none"``: identity.
* ``"reproject"`` (CPU, no weights): uses the chosen reference training view's *photo*
  and the reconstruction's depth at both poses.

  1. The reference's rendered depth (valid where its alpha >= ``alpha_min``) is forward-warped
     into the free view with a z-buffer (2x2 splat footprint, cracks of <= ``crack_px`` filled):
     ``D_fw``, the depth of the first surface the reference camera saw, per free-view pixel.
  2. Each free-view pixel is classified, with ``D_v`` its rendered depth (valid where alpha >=
     ``alpha_min``) and ``tol`` = ``depth_tol`` (relative):

     - *consistent*: ``|D_v - D_fw| <= tol D_fw``: the reference saw the same surface point;
       weight ``w_consistent``;
     - *carved* (floater): ``D_v < (1 - tol) D_fw`` **and** the free view's surface point
       projects inside the reference image where the reference's depth lies beyond it, i.e. the
       training camera saw through empty space where the render put something; weight
       ``w_carved``, warped through ``D_fw``;
     - *hole*: the render is unreliable (alpha < ``alpha_min``) but the reference saw a surface
       there; weight ``w_hole``, warped through ``D_fw``;
     - otherwise (the reference saw something in front: occlusion; or saw nothing): weight 0.
  3. The reference photo is sampled (``cv2.remap``, bilinear) at the projections of the free
     view's pixels lifted with the chosen depth. The weight is multiplied by an angle kernel
     of the triangulation angle (between the rays from the lifted point to the two camera
     centres): 1 up to ``angle_full_deg`` (5), linearly down to 0 at ``angle_zero_deg`` (30).
     An error in the rendered depth misplaces the warped photo by a parallax that grows with
     this angle; measured on the sample scene, the warp beats the render below ~40 deg and
     loses beyond (docs/FIDELITY.md).
  4. The weight map is smoothed edge-aware (``cv2.ximgproc.guidedFilter`` guided by the render)
     to avoid seams, then masked so it stays 0 wherever step 2 gave no evidence; the output is
     ``render + w (warp - render)``. Where ``w = 0`` the render is returned bit-for-bit: the
     rectifier never touches a pixel no reference information applies to.

  The rectified depth is the rendered depth, replaced by ``D_fw`` where a carved or hole pixel
  took a weight >= 0.5.
* ``"fixer"``: the engine's own trained fixer network (:mod:`freescale_core.fixer`): the
  render, its alpha and the ``k`` reference photos warped in by steps 1-3 above go through the
  network; the output is the corrected image, and the result's ``weight`` is its per-pixel
  confidence. ``params: {"checkpoint": PATH}`` names a ``fixer.pt`` (``freescale
  train-fixer``), else the checkpoint shipped in ``freescale_core/data/fixer.pt``; a missing
  or mismatched checkpoint fails naming the file.
* ``"difix"``: DIFIX3D (one-step diffusion) through ``diffusers``, behind the optional
  ``difix`` extra and a user-supplied local weights folder (``params: {"weights": PATH,
  "module": "pipeline_difix"}``; nothing is downloaded). When either is missing, building it
  raises :class:`RectifierUnavailable` with the reason; the free-view stage then falls back to
  ``none`` and records the message.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import cv2
import numpy as np

from schemas.freeview import RectifierConfig

from freescale_core.geometry.cameras import invert_pose
from freescale_core.errors import FreeScaleError, ShapeError

__all__ = [
    "RenderedView",
    "RectifyResult",
    "Rectifier",
    "RectifierUnavailable",
    "NoneRectifier",
    "ReprojectRectifier",
    "DifixRectifier",
    "FixerRectifier",
    "shipped_checkpoint",
    "RECTIFIERS",
    "register_rectifier",
    "make_rectifier",
    "forward_warp_depth",
    "backward_warp",
]


class RectifierUnavailable(FreeScaleError):
    """A rectifier backend cannot run here (missing package or weights); says why."""


@dataclass
class RenderedView:
    """An image with its camera (a render, or a photo with optional rendered depth).

    Attributes:
        rgb: ``[H, W, 3]`` float32 in [0, 1].
        depth: ``[H, W]`` float32 camera-z depth (world units), or None.
        alpha: ``[H, W]`` float32 accumulated opacity, or None (treated as all 1).
        world_from_cam: ``[4, 4]`` OpenCV axes.
        fx, fy, cx, cy: pinhole intrinsics in pixels (top-left pixel centre at 0.5, 0.5).
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    alpha: np.ndarray | None
    world_from_cam: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def hw(self) -> tuple[int, int]:
        return int(self.rgb.shape[0]), int(self.rgb.shape[1])


@dataclass
class RectifyResult:
    """Output of a rectifier for one free view.

    Attributes:
        rgb: ``[H, W, 3]`` float32 in [0, 1].
        depth: ``[H, W]`` float32.
        weight: ``[H, W]`` float32, how much reference content each pixel took (0 = render).
        info: backend facts (fractions of pixels per class, ...).
    """

    rgb: np.ndarray
    depth: np.ndarray
    weight: np.ndarray
    info: dict = field(default_factory=dict)


class Rectifier(Protocol):
    """A stage-10 backend: ``rectifier(view, ref_photo, ref_render) -> RectifyResult``."""

    name: str
    needs_reference: bool  # False: ref_photo / ref_render may be None and are not rendered

    def __call__(self, view: RenderedView, ref_photo: np.ndarray | None,
                 ref_render: RenderedView | None) -> RectifyResult: ...


# --------------------------------------------------------------------------- geometry
def _pixel_rays(h: int, w: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``[H, W, 3]`` camera-frame rays with z = 1 through pixel centres."""
    u = np.arange(w, dtype=np.float64) + 0.5
    v = np.arange(h, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid(u, v)
    return np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], axis=-1)


def _lift(view: RenderedView, depth: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` world points of a view's pixels at the given camera-z depth."""
    h, w = depth.shape
    X = _pixel_rays(h, w, view.fx, view.fy, view.cx, view.cy) * depth[..., None]
    T = np.asarray(view.world_from_cam, dtype=np.float64)
    return X @ T[:3, :3].T + T[:3, 3]


def _project(view: RenderedView, X_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points ``[..., 3]`` into a view: ``(u, v, z)`` (u, v in pixels)."""
    cfw = invert_pose(view.world_from_cam)
    Xc = X_world @ cfw[:3, :3].T + cfw[:3, 3]
    z = Xc[..., 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    return view.fx * Xc[..., 0] / zs + view.cx, view.fy * Xc[..., 1] / zs + view.cy, z


def _valid_depth(view: RenderedView, alpha_min: float) -> np.ndarray:
    d = view.depth
    ok = np.isfinite(d) & (d > 0)
    if view.alpha is not None:
        ok &= view.alpha >= alpha_min
    return ok


def forward_warp_depth(src: RenderedView, src_valid: np.ndarray, dst: RenderedView,
                       dst_hw: tuple[int, int], crack_px: int = 1) -> np.ndarray:
    """Z-buffered forward warp of ``src``'s depth into ``dst``'s image.

    Every valid source pixel is lifted to 3D and splatted onto the 2x2 destination pixels
    around its projection, keeping the nearest depth; remaining cracks up to ``crack_px`` wide
    are closed by a grey-level closing that only writes into empty pixels.

    Args:
        src: view with ``depth``.
        src_valid: ``[Hs, Ws]`` bool, which source depths to use.
        dst: destination camera (its rgb is not used).
        dst_hw: ``(H, W)`` of the destination image.
        crack_px: largest crack closed.
    Returns:
        ``[H, W]`` float64 camera-z depth in ``dst``; ``inf`` where nothing landed.
    """
    H, W = dst_hw
    out = np.full(H * W, np.inf)
    if not src_valid.any():
        return out.reshape(H, W)
    X = _lift(src, np.where(src_valid, src.depth, 0.0))[src_valid]
    u, v, z = _project(dst, X)
    keep = z > 1e-9
    u, v, z = u[keep] - 0.5, v[keep] - 0.5, z[keep]  # continuous index coordinates
    x0, y0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    for dx in (0, 1):
        for dy in (0, 1):
            x, y = x0 + dx, y0 + dy
            m = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            np.minimum.at(out, y[m] * W + x[m], z[m])
    out = out.reshape(H, W)
    if crack_px > 0:
        empty = ~np.isfinite(out)
        big = np.where(empty, 0.0, out).astype(np.float32)
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * crack_px + 1, 2 * crack_px + 1))
        # closing of the *inverse* depth fills a crack with its nearer neighbours' depth
        inv = np.where(empty, 0.0, 1.0 / np.where(empty, 1.0, big)).astype(np.float32)
        closed = cv2.morphologyEx(inv, cv2.MORPH_CLOSE, k)
        fill = empty & (closed > 0)
        out[fill] = 1.0 / closed[fill]
    return out


def backward_warp(photo: np.ndarray, ref: RenderedView, view: RenderedView, depth: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample the reference photo at the projections of the view's pixels lifted to ``depth``.

    Args:
        photo: ``[Hr, Wr, 3]`` float32 reference photo.
        ref: the reference camera.
        view: the free view's camera.
        depth: ``[H, W]`` camera-z depth in the free view (non-finite where unknown).
    Returns:
        ``(warped [H, W, 3] float32, in_bounds [H, W] bool, z_ref [H, W])``.
    """
    Hr, Wr = photo.shape[:2]
    finite = np.isfinite(depth) & (depth > 0)
    X = _lift(view, np.where(finite, depth, 1.0))
    u, v, z = _project(ref, X)
    mx, my = (u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32)
    inb = finite & (z > 1e-9) & (mx >= 0) & (mx <= Wr - 1) & (my >= 0) & (my <= Hr - 1)
    mx = np.where(inb, mx, -10.0).astype(np.float32)
    my = np.where(inb, my, -10.0).astype(np.float32)
    warped = cv2.remap(np.ascontiguousarray(photo, dtype=np.float32), mx, my,
                       interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=(0, 0, 0))
    return warped, inb, z


def triangulation_angle_deg(view: RenderedView, ref: RenderedView, depth: np.ndarray
                            ) -> np.ndarray:
    """``[H, W]`` angle (degrees) at each lifted free-view point between the rays to the two
    camera centres (NaN where ``depth`` is not finite and positive)."""
    finite = np.isfinite(depth) & (depth > 0)
    X = _lift(view, np.where(finite, depth, 1.0))
    a = X - np.asarray(view.world_from_cam, dtype=np.float64)[:3, 3]
    b = X - np.asarray(ref.world_from_cam, dtype=np.float64)[:3, 3]
    cos = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1),
                                       1e-300)
    return np.where(finite, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), np.nan)


def angle_weight(angle_deg: np.ndarray, full: float, zero: float) -> np.ndarray:
    """1 up to ``full`` degrees, linear down to 0 at ``zero`` (0 where the angle is NaN)."""
    a = np.asarray(angle_deg, dtype=np.float64)
    if zero <= full:
        w = (a <= full).astype(np.float64)
    else:
        w = np.clip((zero - a) / (zero - full), 0.0, 1.0)
    return np.where(np.isfinite(a), w, 0.0).astype(np.float32)


# --------------------------------------------------------------------------- backends
class NoneRectifier:
    """Identity: the render is the free view."""

    name = "none"
    needs_reference = False

    def __init__(self, **params: Any) -> None:
        if params:
            raise ValueError(f"rectifier 'none' takes no parameters, got {sorted(params)}")

    def __call__(self, view, ref_photo=None, ref_render=None) -> RectifyResult:
        h, w = view.hw
        depth = view.depth if view.depth is not None else np.zeros((h, w), np.float32)
        return RectifyResult(view.rgb.astype(np.float32, copy=True),
                             np.asarray(depth, dtype=np.float32).copy(),
                             np.zeros((h, w), np.float32), {})


class ReprojectRectifier:
    """Depth-guided reprojection of the reference photo (see the module docstring).

    Args:
        alpha_min: render alpha below this is unreliable (hole) and its depth unused.
        depth_tol: relative depth tolerance of the consistency and carving tests.
        w_consistent: weight of the warp where the reference saw the same surface point.
        w_carved: weight of the warp where the render put a floater in space the reference
            saw through.
        w_hole: weight of the warp where the render is empty and the reference saw a surface.
        crack_px: cracks of the forward-warped depth closed up to this width.
        guided_radius, guided_eps: ``cv2.ximgproc.guidedFilter`` smoothing of the weight map
            (radius 0 disables it).
        angle_full_deg, angle_zero_deg: the weight is multiplied by 1 where the triangulation
            angle (between the rays from the lifted point to the free and the reference
            camera centres) is at most ``angle_full_deg``, falling linearly to 0 at
            ``angle_zero_deg`` (``180, 180`` disables it). Measured on the sample scene, the
            warped photo is closer to the truth than the render on average below ~40 deg and
            worse beyond (docs/FIDELITY.md).
    """

    name = "reproject"
    needs_reference = True

    def __init__(self, alpha_min: float = 0.5, depth_tol: float = 0.03,
                 w_consistent: float = 1.0, w_carved: float = 1.0, w_hole: float = 1.0,
                 crack_px: int = 1, guided_radius: int = 4, guided_eps: float = 1e-3,
                 angle_full_deg: float = 5.0, angle_zero_deg: float = 30.0) -> None:
        self.alpha_min, self.depth_tol = float(alpha_min), float(depth_tol)
        self.w_consistent, self.w_carved, self.w_hole = map(float, (w_consistent, w_carved,
                                                                    w_hole))
        self.crack_px, self.guided_radius = int(crack_px), int(guided_radius)
        self.guided_eps = float(guided_eps)
        self.angle_full_deg, self.angle_zero_deg = float(angle_full_deg), float(angle_zero_deg)
        if not 0.0 <= self.angle_full_deg <= self.angle_zero_deg:
            raise ValueError("need 0 <= angle_full_deg <= angle_zero_deg, got "
                             f"{angle_full_deg}, {angle_zero_deg}")

    def warp(self, view: RenderedView, ref_photo: np.ndarray, ref_render: RenderedView
             ) -> dict:
        """Steps 1-3 of the module docstring: the reference photo warped into ``view``.

        Returns:
            dict with ``warped`` ``[H, W, 3]`` float32 (the sampled photo; meaningless where
            ``weight`` is 0), ``weight`` ``[H, W]`` float32 (evidence class weight x angle
            kernel, before feathering), ``angle`` ``[H, W]`` (triangulation angle in degrees,
            NaN without a lifted depth), ``depth_fw`` (``D_fw``), ``depth`` (the free view's
            rendered depth) and the boolean class maps ``consistent``, ``carved``, ``hole``,
            ``view_valid``.
        """
        H, W = view.hw
        if view.depth is None or view.depth.shape != (H, W):
            raise ShapeError("view.depth", getattr(view.depth, "shape", ()), f"[{H}, {W}]")
        if ref_render.depth is None:
            raise ValueError("reproject rectifier needs the reference's rendered depth")
        if ref_photo.shape[:2] != ref_render.depth.shape:
            raise ShapeError("ref_photo", ref_photo.shape,
                             f"[{ref_render.depth.shape[0]}, {ref_render.depth.shape[1]}, 3]")
        photo = _as_float_rgb(ref_photo)
        tol = self.depth_tol
        Dv = np.asarray(view.depth, dtype=np.float64)
        v_ok = _valid_depth(view, self.alpha_min)
        r_ok = _valid_depth(ref_render, self.alpha_min)

        # 1. what the reference saw, in the free view
        Dfw = forward_warp_depth(ref_render, r_ok, view, (H, W), self.crack_px)
        fw_ok = np.isfinite(Dfw)

        # 2. classify
        consistent = v_ok & fw_ok & (np.abs(Dv - Dfw) <= tol * Dfw)
        in_front = v_ok & fw_ok & (Dv < (1.0 - tol) * Dfw)
        carved = np.zeros_like(in_front)
        if in_front.any():
            # carving evidence: the render's point lies inside the reference image, in front
            # of the reference's own (valid) depth there
            Hr, Wr = ref_render.depth.shape
            u, v, z_ref = _project(ref_render, _lift(view, np.where(in_front, Dv, 1.0)))
            inb = (z_ref > 1e-9) & (u >= 0) & (u < Wr) & (v >= 0) & (v < Hr)
            iy = np.clip(np.floor(np.where(inb, v, 0)).astype(np.int64), 0, Hr - 1)
            ix = np.clip(np.floor(np.where(inb, u, 0)).astype(np.int64), 0, Wr - 1)
            d_ref = np.where(r_ok[iy, ix], ref_render.depth[iy, ix], -np.inf)
            carved = in_front & inb & (d_ref > (1.0 + tol) * z_ref)
        hole = ~v_ok & fw_ok

        w = np.zeros((H, W), np.float32)
        w[consistent] = self.w_consistent
        w[carved] = self.w_carved
        w[hole] = self.w_hole
        D_use = np.where(consistent, Dv, np.where(carved | hole, Dfw, np.nan))

        # 3. warp the photo (with an object mask as 4th channel: only its mask pixels)
        if ref_photo.shape[-1] >= 4:
            a = np.asarray(ref_photo[..., 3], np.float32)
            a = a / 255.0 if ref_photo.dtype == np.uint8 else a
            photo = np.concatenate([photo, a[..., None]], axis=-1)
        warped, inb, _ = backward_warp(photo, ref_render, view, D_use)
        if warped.shape[-1] >= 4:
            inb = inb & (warped[..., 3] >= 0.999)  # every bilinear tap inside the mask
            warped = warped[..., :3]
        w = np.where(inb, w, 0.0).astype(np.float32)
        # 3b. trust falls with the triangulation angle: a depth error misplaces the warp by
        # a parallax that grows with the angle between the two rays
        ang = None
        if self.angle_full_deg < 180.0 and w.any():
            ang = triangulation_angle_deg(view, ref_render, D_use)
            w *= angle_weight(ang, self.angle_full_deg, self.angle_zero_deg)
        return {"warped": warped, "weight": w, "angle": ang, "depth_fw": Dfw, "depth": Dv,
                "consistent": consistent, "carved": carved, "hole": hole, "view_valid": v_ok,
                "d_use": D_use}

    def blend(self, render: np.ndarray, warped: np.ndarray, w: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """Step 4: ``(render + w' (warped - render), w')`` with ``w'`` the weight feathered
        edge-aware (guided by the render), never spilling outside ``w > 0``."""
        evidence = w > 0
        if self.guided_radius > 0 and evidence.any() and not evidence.all():
            guide = np.ascontiguousarray(render, dtype=np.float32)
            wf = cv2.ximgproc.guidedFilter(guide=guide, src=np.asarray(w, np.float32),
                                           radius=self.guided_radius, eps=self.guided_eps)
            w = np.where(evidence, np.clip(wf, 0.0, w), 0.0).astype(np.float32)
        rgb = np.asarray(render, np.float32).copy()
        m = w > 0
        rgb[m] = rgb[m] + w[m, None] * (warped[m] - rgb[m])
        return rgb, w

    def __call__(self, view: RenderedView, ref_photo: np.ndarray,
                 ref_render: RenderedView) -> RectifyResult:
        H, W = view.hw
        e = self.warp(view, ref_photo, ref_render)
        warped, w, Dv, Dfw = e["warped"], e["weight"], e["depth"], e["depth_fw"]
        consistent, carved, hole, v_ok = e["consistent"], e["carved"], e["hole"], e["view_valid"]
        rgb, w = self.blend(view.rgb, warped, w)
        m = w > 0
        depth = Dv.astype(np.float32, copy=True)
        replace_d = (carved | hole) & (w >= 0.5)
        depth[replace_d] = Dfw[replace_d]
        n = float(H * W)
        info = {"frac_consistent": float(consistent.sum() / n),
                "frac_carved": float(carved.sum() / n),
                "frac_hole_filled": float((hole & m).sum() / n),
                "frac_hole": float((~v_ok).sum() / n), "mean_weight": float(w.mean())}
        return RectifyResult(np.clip(rgb, 0.0, 1.0), depth, w, info)


class DifixRectifier:
    """DIFIX3D one-step diffusion with a reference image (optional ``difix`` extra).

    Args:
        weights: local folder of a diffusers Difix pipeline (e.g. a copy of ``nvidia/difix_ref``
            the user downloaded); nothing is downloaded here.
        module: importable module that defines ``DifixPipeline`` (the Difix3D repository's
            ``src/pipeline_difix.py`` on ``PYTHONPATH``).
        prompt: the text prompt Difix was trained with.
        device: ``"cuda"`` (default when available) or ``"cpu"``.
    Raises:
        RectifierUnavailable: diffusers, the module or the weights are missing.
    """

    name = "difix"
    needs_reference = True

    def __init__(self, weights: str | None = None, module: str = "pipeline_difix",
                 prompt: str = "remove degradation", device: str | None = None) -> None:
        try:
            importlib.import_module("diffusers")
        except ImportError as e:
            raise RectifierUnavailable(
                "rectifier 'difix' needs the optional extra: pip install -e '.[difix]' "
                f"({e})") from e
        if not weights or not Path(weights).is_dir():
            raise RectifierUnavailable(
                "rectifier 'difix' needs params.weights = a local folder with the Difix "
                f"pipeline weights (got {weights!r}); nothing is downloaded at run time")
        try:
            mod = importlib.import_module(module)
            pipeline_cls = getattr(mod, "DifixPipeline")
        except (ImportError, AttributeError) as e:
            raise RectifierUnavailable(
                f"rectifier 'difix' needs a module {module!r} defining DifixPipeline "
                f"(Difix3D's src/pipeline_difix.py on PYTHONPATH): {e}") from e
        import torch

        self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
        self.pipe = pipeline_cls.from_pretrained(weights, local_files_only=True).to(self.device)
        self.prompt = prompt

    def __call__(self, view, ref_photo, ref_render=None) -> RectifyResult:  # pragma: no cover
        from PIL import Image

        H, W = view.hw
        img = Image.fromarray(_to_u8(view.rgb))
        ref = Image.fromarray(_to_u8(_as_float_rgb(ref_photo)))
        out = self.pipe(self.prompt, image=img, ref_image=ref, num_inference_steps=1,
                        timesteps=[199], guidance_scale=0.0).images[0]
        rgb = np.asarray(out.convert("RGB").resize((W, H)), dtype=np.float32) / 255.0
        depth = view.depth if view.depth is not None else np.zeros((H, W))
        return RectifyResult(rgb, np.asarray(depth, np.float32), np.ones((H, W), np.float32), {})


def shipped_checkpoint() -> Path:
    """The fixer checkpoint shipped with the package."""
    return Path(__file__).resolve().parents[1] / "data" / "fixer.pt"


class FixerRectifier:
    """Stage-10 backend running a trained fixer (see the module docstring).

    Args:
        checkpoint: path of a ``fixer.pt``; None = the shipped one.
        batch_size: views per forward pass when several are fixed at once.
        **warp: parameters of the reproject warp (``ReprojectRectifier``'s), as in training.
    """

    name = "fixer"
    needs_reference = True
    gives_confidence = True  # the result's weight is a per-pixel confidence

    def __init__(self, checkpoint: str | None = None, batch_size: int = 8,
                 **warp: Any) -> None:
        from freescale_core.fixer.model import load_fixer

        self.checkpoint = str(checkpoint or shipped_checkpoint())
        self.model, self.meta = load_fixer(self.checkpoint)
        self.k = int(self.model.cfg.k)
        self.n_references = max(1, self.k)  # the stage hands this many references
        self.batch_size = int(batch_size)
        self.warper = ReprojectRectifier(**warp)

    def warps(self, view: RenderedView, ref_photos: Sequence[np.ndarray | None],
              ref_renders: Sequence[RenderedView | None]) -> tuple[np.ndarray, np.ndarray]:
        """``(warps [k, H, W, 3], weight [k, H, W])``, zero where a warp gives no evidence."""
        H, W = view.hw
        warps = np.zeros((self.k, H, W, 3), np.float32)
        weight = np.zeros((self.k, H, W), np.float32)
        slot = 0
        for photo, ref in zip(ref_photos, ref_renders):
            if slot >= self.k:
                break
            if photo is None or ref is None:
                continue
            e = self.warper.warp(view, photo, ref)
            w = e["weight"]
            warps[slot] = np.where(w[..., None] > 0, e["warped"], 0.0)
            weight[slot] = w
            slot += 1
        return warps, weight

    def fix(self, views: Sequence[RenderedView], warps: np.ndarray, weight: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
        """Fix N views of one size: ``(fixed [N, H, W, 3], conf [N, H, W])``."""
        from freescale_core.fixer.infer import fix_views

        rgb = np.stack([np.asarray(v.rgb, np.float32) for v in views])
        alpha = np.stack([np.ones(v.hw, np.float32) if v.alpha is None
                          else np.asarray(v.alpha, np.float32) for v in views])
        return fix_views(self.model, rgb, alpha, warps, weight, batch_size=self.batch_size)

    def __call__(self, view: RenderedView, ref_photo, ref_render) -> RectifyResult:
        photos = ref_photo if isinstance(ref_photo, (list, tuple)) else [ref_photo]
        renders = ref_render if isinstance(ref_render, (list, tuple)) else [ref_render]
        warps, weight = self.warps(view, photos, renders)
        fixed, conf = self.fix([view], warps[None], weight[None])
        H, W = view.hw
        depth = (np.zeros((H, W), np.float32) if view.depth is None
                 else np.asarray(view.depth, np.float32).copy())
        info = {"mean_confidence": float(conf[0].mean()),
                "warp_coverage": float((weight.max(axis=0) > 0).mean()) if self.k else 0.0,
                "n_references": int(sum(p is not None for p in photos))}
        return RectifyResult(fixed[0], depth, conf[0].astype(np.float32), info)


# --------------------------------------------------------------------------- registry
RECTIFIERS: dict[str, Callable[..., Rectifier]] = {
    "none": NoneRectifier,
    "reproject": ReprojectRectifier,
    "difix": DifixRectifier,
    "fixer": FixerRectifier,
}


def register_rectifier(name: str, factory: Callable[..., Rectifier]) -> None:
    """Add a backend: ``factory(**params)`` returns a :class:`Rectifier`."""
    RECTIFIERS[name] = factory


def make_rectifier(cfg: RectifierConfig | None = None) -> Rectifier:
    """Build the configured backend.

    Raises:
        RectifierUnavailable: the backend cannot run here (the message says why).
        KeyError: unknown backend name.
    """
    cfg = cfg or RectifierConfig()
    if cfg.backend not in RECTIFIERS:
        raise KeyError(f"unknown rectifier {cfg.backend!r}; known: {sorted(RECTIFIERS)}")
    return RECTIFIERS[cfg.backend](**cfg.params)


def _as_float_rgb(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img[..., :3].astype(np.float32) / 255.0
    return np.asarray(img[..., :3], dtype=np.float32)


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
