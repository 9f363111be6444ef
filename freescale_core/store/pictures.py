"""Pictures of a scene's selection (METHOD.md stages 2-6), drawn with OpenCV.

* ``cameras.png``: top view (looking down the up axis) and side view of the scene box, the
  occupied voxels (grey), the training cameras (white), suppressed candidates (dark grey
  dots) and the free views coloured by trajectory mode, each with a short heading stroke.
* ``certainty_maxproj.png``: maximum projection of the certainty grid along x, y and z
  (log scale over 3 decades below the 99th percentile of the non-empty voxels; the box's
  aspect ratio is kept).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from schemas.select import TRAJECTORY_MODES

from freescale_core.geometry.cameras import Cameras

__all__ = ["save_selection_plots", "MODE_COLORS_BGR"]

MODE_COLORS_BGR: dict[str, tuple[int, int, int]] = {
    "orbit": (75, 25, 230), "spiral": (48, 130, 245), "lemniscate": (25, 225, 255),
    "interpolation": (60, 180, 75), "move_up": (240, 240, 70), "move_down": (200, 130, 0),
    "move_left": (180, 30, 145), "move_right": (230, 50, 240), "dolly_in": (195, 255, 170),
    "dolly_out": (128, 128, 255),
}
_PANEL = 520
_BG = (24, 24, 24)


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (e1, e2, up): e1, e2 horizontal, e1 the world axis most horizontal."""
    up = up / np.linalg.norm(up)
    ax = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = ax - (ax @ up) * up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def _panel(points2d: list[np.ndarray], title: str):
    """A canvas and a world->pixel mapping fitting all 2-D point sets."""
    allp = np.concatenate([p for p in points2d if len(p)], axis=0)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-9))
    s = (_PANEL - 60) / span
    mid = 0.5 * (lo + hi)

    def to_px(p):
        p = np.atleast_2d(p)
        x = (p[:, 0] - mid[0]) * s + _PANEL / 2
        y = _PANEL / 2 - (p[:, 1] - mid[1]) * s + 10
        return np.stack([x, y], axis=1).round().astype(np.int32)

    img = np.full((_PANEL, _PANEL, 3), _BG, np.uint8)
    cv2.putText(img, title, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (230, 230, 230), 1,
                cv2.LINE_AA)
    return img, to_px, s


def _draw_cams(img, to_px, c2, d2, color, radius, stroke):
    if len(c2) == 0:
        return
    p = to_px(c2)
    q = to_px(c2 + d2)
    for a, b in zip(p, q):
        if stroke:
            cv2.line(img, tuple(map(int, a)), tuple(map(int, b)), color, 1, cv2.LINE_AA)
        cv2.circle(img, tuple(map(int, a)), radius, color, -1, cv2.LINE_AA)


def _cameras_png(result, train_cams: Cameras, path: Path) -> Path:
    grid = result.grid
    e1, e2, up = _basis(np.asarray(result.up, dtype=np.float64))
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    corners = grid.bbox_min + corners * (grid.bbox_max - grid.bbox_min)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    _, vox, _ = grid.nonzero()
    if len(vox) > 20000:
        vox = vox[np.random.default_rng(0).choice(len(vox), 20000, replace=False)]
    T = result.n_train
    disp = result.disposition
    cand = result.candidates
    allc = np.concatenate([train_cams.centers, cand.centers])
    allf = np.concatenate([train_cams.forward, cand.forward])
    L = 0.04 * grid.diagonal
    panels = []
    for name, (a1, a2) in (("top view", (e1, e2)), ("side view", (e1, up))):
        P = lambda X: np.stack([X @ a1, X @ a2], axis=-1)  # noqa: E731
        img, to_px, _ = _panel([P(corners), P(allc[disp != "infeasible"])], name)
        for x, y in to_px(P(vox)):
            if 0 <= x < _PANEL and 0 <= y < _PANEL:
                img[y, x] = (90, 90, 90)
        cp = to_px(P(corners))
        for a, b in edges:
            cv2.line(img, tuple(map(int, cp[a])), tuple(map(int, cp[b])), (150, 150, 150), 1)
        sup = np.flatnonzero(disp == "suppressed")
        _draw_cams(img, to_px, P(allc[sup]), P(allf[sup]) * 0, (80, 80, 80), 1, False)
        for m in TRAJECTORY_MODES:
            sel = np.array([i for i in np.flatnonzero(disp == "free_view")
                            if result.modes[i - T] == m], dtype=np.int64)
            _draw_cams(img, to_px, P(allc[sel]), P(allf[sel]) * L, MODE_COLORS_BGR[m], 2, True)
        _draw_cams(img, to_px, P(allc[:T]), P(allf[:T]) * L, (255, 255, 255), 3, True)
        panels.append(img)
    legend = np.full((_PANEL, 190, 3), _BG, np.uint8)
    y = 24
    cv2.putText(legend, f"train ({T})", (10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    for m in TRAJECTORY_MODES:
        y += 22
        n = sum(1 for i in np.flatnonzero(disp == "free_view") if result.modes[i - T] == m)
        cv2.circle(legend, (16, y - 4), 5, MODE_COLORS_BGR[m], -1)
        cv2.putText(legend, f"{m} ({n})", (28, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    MODE_COLORS_BGR[m], 1)
    y += 22
    cv2.putText(legend, f"suppressed ({int(np.sum(disp == 'suppressed'))})", (10, y),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (120, 120, 120), 1)
    y += 22
    cv2.putText(legend, f"infeasible ({int(np.sum(disp == 'infeasible'))})", (10, y),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (120, 120, 120), 1)
    cv2.imwrite(str(path), np.concatenate(panels + [legend], axis=1))
    return path


def _maxproj_png(result, path: Path, decades: float = 3.0) -> Path:
    grid = result.grid
    C = grid.values
    nz = C[C > 0]
    ref = float(np.quantile(nz, 0.99)) if nz.size else 1.0
    ext = grid.bbox_max - grid.bbox_min
    panels = []
    for axis, (h, v) in zip(range(3), ((1, 2), (0, 2), (0, 1))):
        mx = C.max(axis=axis).astype(np.float64)  # [a, b]: the two remaining axes in order
        m = np.clip(np.log10(np.maximum(mx, 1e-30) / ref) / decades + 1.0, 0.0, 1.0)
        m[mx <= 0] = 0.0
        img = cv2.applyColorMap(np.ascontiguousarray((255 * m).astype(np.uint8).T[::-1]),
                                cv2.COLORMAP_INFERNO)
        side = _PANEL - 50
        sc = side / max(ext[h], ext[v])
        w, hh = max(1, int(round(ext[h] * sc))), max(1, int(round(ext[v] * sc)))
        img = cv2.resize(img, (w, hh), interpolation=cv2.INTER_NEAREST)
        canvas = np.full((_PANEL, _PANEL, 3), _BG, np.uint8)
        y0, x0 = 35 + (side - hh) // 2, 25 + (side - w) // 2
        canvas[y0:y0 + hh, x0:x0 + w] = img
        cv2.putText(canvas, f"max over {'xyz'[axis]} (right: {'xyz'[h]}, up: {'xyz'[v]}), "
                    f"{decades:g} decades", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (230, 230, 230), 1, cv2.LINE_AA)
        panels.append(canvas)
    cv2.imwrite(str(path), np.concatenate(panels, axis=1))
    return path


def save_selection_plots(result, train_cams: Cameras, out_dir: str | Path) -> list[Path]:
    """Write ``cameras.png`` and ``certainty_maxproj.png`` into ``out_dir``.

    Args:
        result: a :class:`~freescale_core.select.run.SelectionResult`.
        train_cams: the T training cameras the result was computed with.
        out_dir: folder (created if missing).
    Returns:
        the written paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [_cameras_png(result, train_cams, out / "cameras.png"),
            _maxproj_png(result, out / "certainty_maxproj.png")]


def save_contact_sheet(path: Path, fv, view_ids: np.ndarray,
                       thumb_w: int = 160, cols: int = 8) -> None:
    """Thumbnails of the final free views (rectified), labelled with view id and BRISQUE.

    ``fv`` is a :class:`~freescale_core.freeviews.run.FreeViewResult`."""
    recs = {r.candidate: r for r in fv.records}
    thumbs = []
    for k, im in enumerate(fv.rgb):
        h, w = im.shape[:2]
        th = max(1, int(round(h * thumb_w / w)))
        t = cv2.resize(im, (thumb_w, th), interpolation=cv2.INTER_AREA)
        r = recs[int(fv.final_candidates[k])]
        label = f"{int(view_ids[k])} q={r.brisque:.2f}"
        if math.isfinite(getattr(r, "pred_psnr", math.nan)):
            label += f" {r.pred_psnr:.0f}dB"  # the trust model's predicted PSNR
        cv2.putText(t, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 2, cv2.LINE_AA)
        cv2.putText(t, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA)
        thumbs.append(t)
    th = max(t.shape[0] for t in thumbs)
    rows = math.ceil(len(thumbs) / cols)
    sheet = np.full((rows * (th + 2), min(cols, len(thumbs)) * (thumb_w + 2), 3), 255, np.uint8)
    for k, t in enumerate(thumbs):
        y, x = (k // cols) * (th + 2), (k % cols) * (thumb_w + 2)
        sheet[y:y + t.shape[0], x:x + thumb_w] = t
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
