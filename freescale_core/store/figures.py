"""Figures of one published scene version, drawn with matplotlib (Agg, no display needed).

Written into the version folder by :func:`save_figures` (called from
``layout.write_scene_outputs``); shown inline by the Prefect per-scene artifact and by
``freescale report``. Every figure has axes with units, a legend or a colour bar:

* ``funnel.png``: candidates -> feasible -> NMS-selected -> passed the quality filter -> free
  views, in total (log scale, with the counts) and per trajectory mode.
* ``scores.png``: histograms of the selection score f (selected vs not) and of the three
  quality scores of the rendered views, with the thresholds they were judged by.
* ``cameras.png``: top and side views (scene units) of the scene box, the occupied voxels,
  the training path in capture order, suppressed candidates and the free views by mode.
* ``certainty.png``: maximum projection of the certainty grid along each axis, log colour
  scale with a colour bar, axes in scene units.
* ``contact_sheet.png``: each free view (mode, view id, BRISQUE) beside the nearest training
  photo and its rendered depth (at most ``max_views``, evenly spaced).
"""

from __future__ import annotations

import threading

from pathlib import Path

import numpy as np

from schemas.select import TRAJECTORY_MODES

__all__ = ["save_figures", "FIGURE_NAMES", "MODE_COLORS"]

FIGURE_NAMES = ("funnel.png", "scores.png", "cameras.png", "certainty.png", "contact_sheet.png")

# colour-blind-friendly-ish, distinct on white (tab10)
MODE_COLORS = {m: c for m, c in zip(TRAJECTORY_MODES, (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
    "#bcbd22", "#17becf"))}
DPI = 100
# matplotlib (pyplot's figure registry, rcParams, the mathtext parser) is not thread-safe, and
# scenes publish concurrently in threads: one scene's figures at a time (a race gave a
# mathtext ParseException in publish while two scenes drew at once).
_MPL_LOCK = threading.Lock()


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "figure.dpi": DPI,
                         "axes.grid": True, "grid.alpha": 0.25, "savefig.bbox": "tight"})
    return plt


def _save(fig, path: Path, colours: int | None = None) -> Path:
    """Save ``fig``; with ``colours`` as a palette PNG of that many colours (photos make
    true-colour PNGs large: a 16-view contact sheet is ~1.9 MB true colour, ~0.5 MB at 256)."""
    if colours is None:
        fig.savefig(path, dpi=DPI, facecolor="white")
    else:
        import io

        from PIL import Image

        buf = io.BytesIO()
        fig.savefig(buf, dpi=DPI, facecolor="white", format="png")
        im = Image.open(buf).convert("RGB").quantize(colours, dither=Image.Dither.NONE)
        im.save(path, optimize=True)
    _plt().close(fig)
    return path


# --------------------------------------------------------------------------- funnel
def funnel_counts(cols: dict) -> dict[str, dict[str, int]]:
    """``stage -> {mode: count}`` from the views-table columns (candidates only)."""
    kind = np.asarray(cols["kind"])
    mode = np.asarray(cols["mode"])
    disp = np.asarray(cols["disposition"])
    passed = np.asarray(cols.get("passed", np.zeros(len(kind), bool)), bool)
    cand = kind == "candidate"
    sel = cand & np.isin(disp, ["free_view", "rejected"])
    masks = {"candidates": cand, "feasible": cand & (disp != "infeasible"),
             "selected": sel, "passed filter": sel & passed, "free views": disp == "free_view"}
    rendered = np.isfinite(np.asarray(cols.get("brisque", np.full(len(kind), np.nan)), float))
    if not rendered.any():  # no free-view stage: nothing was rendered, filtered or kept
        masks["passed filter"] = masks["free views"] = np.zeros(len(kind), bool)
    return {k: {m: int(np.sum(v & (mode == m))) for m in TRAJECTORY_MODES}
            for k, v in masks.items()}


def _funnel(cols: dict, path: Path, scene_id: str) -> Path:
    plt = _plt()
    fc = funnel_counts(cols)
    stages = list(fc)
    tot = [sum(fc[s].values()) for s in stages]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [1, 1.5]})
    bars = a.bar(range(len(stages)), [max(t, 0.8) for t in tot], color="#4c72b0")
    a.set_yscale("log")
    a.set_xticks(range(len(stages)), stages, rotation=20, ha="right")
    a.set_ylabel("views (log scale)")
    a.set_title(f"{scene_id}: selection funnel")
    for r, t in zip(bars, tot):
        a.annotate(f"{t:,}", (r.get_x() + r.get_width() / 2, max(t, 0.8)), ha="center",
                   va="bottom", fontsize=9, xytext=(0, 2), textcoords="offset points")
    a.set_ylim(0.7, max(tot + [1]) * 3)
    show = ["feasible", "selected", "free views"]
    y = np.arange(len(TRAJECTORY_MODES))
    h = 0.8 / len(show)
    for k, s in enumerate(show):
        v = [fc[s][m] for m in TRAJECTORY_MODES]
        b.barh(y + (k - 1) * h, v, height=h, label=s,
               color=("#c6dbef", "#6baed6", "#08519c")[k])
    b.set_yticks(y, TRAJECTORY_MODES)
    for lab, m in zip(b.get_yticklabels(), TRAJECTORY_MODES):
        lab.set_color(MODE_COLORS[m])
    b.invert_yaxis()
    b.set_xscale("symlog", linthresh=1)
    b.set_xlabel("views per trajectory mode (symlog)")
    b.set_title("by mode")
    b.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------- scores
def _scores(cols: dict, path: Path, scene_id: str) -> Path:
    plt = _plt()
    kind = np.asarray(cols["kind"])
    disp = np.asarray(cols["disposition"])
    score = np.asarray(cols["score_f"], float)
    fig, axs = plt.subplots(1, 4, figsize=(14, 3.3))
    cand = (kind == "candidate") & np.isfinite(score)
    sel = cand & np.isin(disp, ["free_view", "rejected"])
    ax = axs[0]
    if cand.any():
        bins = np.histogram_bin_edges(score[cand], bins=30)
        ax.hist(score[cand & ~sel], bins=bins, color="#bbbbbb", label="not selected")
        ax.hist(score[sel], bins=bins, color="#08519c", alpha=0.85, label="NMS-selected")
        ax.legend(fontsize=8)
    ax.set_xlabel("selection score f (Eq. 3)")
    ax.set_ylabel("candidates")
    ax.set_title(f"{scene_id}: selection score")
    specs = (("brisque", "thr_brisque", "BRISQUE (lower is better)", "pass if <"),
             ("black_ratio", "thr_black_ratio", "black-pixel ratio", "pass if <="),
             ("depth_validity", "thr_depth_validity", "depth validity", "pass if >"))
    free = disp == "free_view"
    for ax, (col, thr, label, rule) in zip(axs[1:], specs):
        v = np.asarray(cols.get(col, []), float)
        ok = np.isfinite(v)
        if ok.any():
            bins = np.histogram_bin_edges(v[ok], bins=25)
            ax.hist(v[ok & ~free], bins=bins, color="#e6550d", alpha=0.8, label="rejected")
            ax.hist(v[ok & free], bins=bins, color="#31a354", alpha=0.8, label="free view")
            t = np.asarray(cols.get(thr, []), float)
            t = t[np.isfinite(t)]
            if t.size:
                ax.axvline(float(t[0]), color="k", ls="--", lw=1.2,
                           label=f"threshold {float(t[0]):.3g} ({rule})")
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no rendered views", ha="center", va="center",
                    transform=ax.transAxes)
        ax.set_xlabel(label)
        ax.set_ylabel("rendered views")
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------- cameras
def _basis(up: np.ndarray):
    up = np.asarray(up, float)
    up = up / np.linalg.norm(up)
    ax = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = ax - (ax @ up) * up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def _cameras(scene, sel, cols: dict, path: Path, scene_id: str) -> Path:
    plt = _plt()
    grid = sel.grid
    e1, e2, up = _basis(getattr(sel, "up", np.array([0.0, 0.0, 1.0])))
    wfc = np.asarray(cols["world_from_cam"], float).reshape(-1, 4, 4)
    centers, fwd = wfc[:, :3, 3], wfc[:, :3, 2]
    disp = np.asarray(cols["disposition"])
    mode = np.asarray(cols["mode"])
    T = int(sel.n_train)
    order = np.asarray(getattr(scene, "capture_order", np.arange(T)), int)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    corners = grid.bbox_min + corners * (grid.bbox_max - grid.bbox_min)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    try:
        _, vox, _ = grid.nonzero()
        vox = np.asarray(vox, float)
    except Exception:  # noqa: BLE001
        vox = np.zeros((0, 3))
    if len(vox) > 8000:
        vox = vox[np.random.default_rng(0).choice(len(vox), 8000, replace=False)]
    L = 0.04 * float(np.linalg.norm(grid.bbox_max - grid.bbox_min))
    fig, axs = plt.subplots(1, 2, figsize=(12, 5.4))
    for ax, (name, a1, a2, l1, l2) in zip(axs, (
            ("top view (looking down)", e1, e2, "e1", "e2"),
            ("side view", e1, up, "e1", "up"))):
        P = lambda X: np.stack([X @ a1, X @ a2], axis=-1)  # noqa: E731
        if len(vox):
            pv = P(vox)
            ax.scatter(pv[:, 0], pv[:, 1], s=1, c="#d9d9d9", lw=0, label="occupied voxels",
                       rasterized=True)
        pc = P(corners)
        for a, b in edges:
            ax.plot(pc[[a, b], 0], pc[[a, b], 1], color="#636363", lw=0.8)
        sup = np.flatnonzero(disp == "suppressed")
        if len(sup):
            ps = P(centers[sup])
            ax.scatter(ps[:, 0], ps[:, 1], s=2, c="#969696", lw=0,
                       label=f"suppressed ({len(sup)})")
        pt = P(centers[:T][order])
        ax.plot(pt[:, 0], pt[:, 1], "-", color="k", lw=0.8, alpha=0.6)
        ax.scatter(pt[:, 0], pt[:, 1], s=10, c="k", label=f"training path ({T})", zorder=3)
        for m in TRAJECTORY_MODES:
            idx = np.flatnonzero((disp == "free_view") & (mode == m))
            if not len(idx):
                continue
            p, d = P(centers[idx]), P(fwd[idx]) * L
            ax.quiver(p[:, 0], p[:, 1], d[:, 0], d[:, 1], angles="xy", scale_units="xy",
                      scale=1, color=MODE_COLORS[m], width=0.003, zorder=4)
            ax.scatter(p[:, 0], p[:, 1], s=14, color=MODE_COLORS[m], zorder=4,
                       label=f"{m} ({len(idx)})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{l1} (scene units)")
        ax.set_ylabel(f"{l2} (scene units)")
        ax.set_title(f"{scene_id}: {name}")
    h, lab = axs[0].get_legend_handles_labels()
    fig.legend(h, lab, loc="center right", fontsize=8, markerscale=1.5, frameon=False)
    fig.tight_layout(rect=(0, 0, 0.83, 1))
    return _save(fig, path)


# --------------------------------------------------------------------------- certainty
def _certainty(sel, path: Path, scene_id: str, decades: float = 3.0) -> Path:
    plt = _plt()
    from matplotlib.colors import LogNorm

    grid = sel.grid
    C = np.asarray(grid.values, float)
    nz = C[C > 0]
    vmax = float(np.quantile(nz, 0.99)) if nz.size else 1.0
    vmin = vmax * 10 ** (-decades)
    lo, hi = np.asarray(grid.bbox_min, float), np.asarray(grid.bbox_max, float)
    fig, axs = plt.subplots(1, 3, figsize=(13, 4.2))
    im = None
    for ax, axis, (h, v) in zip(axs, range(3), ((1, 2), (0, 2), (0, 1))):
        mx = C.max(axis=axis)
        mx = np.where(mx > 0, np.clip(mx, vmin, None), np.nan)
        im = ax.imshow(mx.T, origin="lower", extent=(lo[h], hi[h], lo[v], hi[v]),
                       norm=LogNorm(vmin=vmin, vmax=vmax), cmap="inferno",
                       interpolation="nearest")
        ax.set_facecolor("#202020")
        ax.set_xlabel(f"{'xyz'[h]} (scene units)")
        ax.set_ylabel(f"{'xyz'[v]} (scene units)")
        ax.set_title(f"max along {'xyz'[axis]}")
        ax.grid(False)
    fig.suptitle(f"{scene_id}: certainty grid C (Eq. 1), R={grid.values.shape[0]}, "
                 f"log scale over {decades:g} decades below the 99th percentile")
    fig.tight_layout(rect=(0, 0, 0.92, 0.95))
    cax = fig.add_axes((0.93, 0.15, 0.012, 0.7))
    fig.colorbar(im, cax=cax, label="certainty (max projection)")
    return _save(fig, path)


# --------------------------------------------------------------------------- contact sheet
def _fit(img: np.ndarray, h: int) -> np.ndarray:
    """``img`` (uint8 RGB) resized to height ``h`` (aspect kept)."""
    from PIL import Image

    w = max(1, int(round(img.shape[1] * h / img.shape[0])))
    return np.asarray(Image.fromarray(img).resize((w, h), Image.BILINEAR))


def _contact_sheet(scene, fv, cols: dict, view_ids: np.ndarray, path: Path, scene_id: str,
                   max_views: int = 12, cell_h: int = 120, per_row: int = 2) -> Path:
    """One mosaic image (one axes: fast) with a label band above every cell."""
    plt = _plt()
    from matplotlib import colormaps

    from freescale_core.freeviews.rectify_pose import nearest_training_camera

    N = len(fv.rgb)
    pick = np.unique(np.linspace(0, N - 1, min(N, max_views)).round().astype(int))
    recs = {int(r.candidate): r for r in fv.records}
    T = len(scene.cameras)
    mode = np.asarray(cols["mode"])
    cmap = colormaps["viridis"]
    band, gap = 34, 6
    cells, labels = [], []
    for k in pick:
        rec = recs[int(fv.final_candidates[k])]
        vid = int(view_ids[k])
        m = str(mode[vid])
        ref = int(rec.reference_view) if getattr(rec, "reference_view", -1) >= 0 else \
            nearest_training_camera(scene.cameras.world_from_cam, rec.world_from_cam)
        render = _fit(np.asarray(fv.rgb[k], np.uint8), cell_h)
        try:
            photo = _fit(np.asarray(scene.load_image(ref), np.uint8), cell_h)
        except Exception:  # noqa: BLE001 - a missing photo must not stop the figure
            photo = np.full_like(render, 200)
        d = np.asarray(fv.depth[k], float)
        ok = d > 0
        lo, hi = (float(d[ok].min()), float(d[ok].max())) if ok.any() else (0.0, 1.0)
        dn = np.where(ok, (d - lo) / max(hi - lo, 1e-9), np.nan)
        dep = (255 * cmap(np.nan_to_num(dn, nan=0.0))[..., :3]).astype(np.uint8)
        dep[~ok] = 255
        dep = _fit(dep, cell_h)
        name = scene.image_names[ref] if ref < T else str(ref)
        cells.append((render, photo, dep))
        labels.append((f"#{vid} {m}  BRISQUE {rec.brisque:.2f}", MODE_COLORS.get(m, "k"),
                       f"nearest photo {name}", f"depth {lo:.2g}-{hi:.2g}"))
    cw = max(max(c.shape[1] for c in trip) for trip in cells)
    rows = int(np.ceil(len(cells) / per_row))
    W = per_row * 3 * (cw + gap)
    H = rows * (cell_h + band)
    mosaic = np.full((H, W, 3), 255, np.uint8)
    fig_w = W / DPI
    fig = plt.figure(figsize=(fig_w, H / DPI + 0.35))
    ax = fig.add_axes((0, 0, 1, H / (H + 0.35 * DPI)))
    for n, (trip, lab) in enumerate(zip(cells, labels)):
        r, c = divmod(n, per_row)
        y0 = r * (cell_h + band) + band
        for j, im in enumerate(trip):
            x0 = (c * 3 + j) * (cw + gap)
            mosaic[y0:y0 + im.shape[0], x0:x0 + im.shape[1]] = im
        x = c * 3 * (cw + gap)
        ax.text(x, y0 - 19, lab[0], color=lab[1], fontsize=8, fontweight="bold", va="bottom")
        ax.text(x + cw + gap, y0 - 4, lab[2], fontsize=7, va="bottom")
        ax.text(x + 2 * (cw + gap), y0 - 4, lab[3] + " (scene units)", fontsize=7,
                va="bottom")
        ax.text(x, y0 - 4, "render", fontsize=7, va="bottom")
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.axis("off")
    fig.suptitle(f"{scene_id}: {len(pick)} of {N} free views (render | nearest training photo "
                 "| depth, near = dark)", fontsize=9, y=0.999, va="top")
    return _save(fig, path, colours=256)


def save_figures(out_dir: str | Path, scene, sel, fv, cols: dict,
                 view_ids: np.ndarray | None = None) -> list[Path]:
    """Write the figures of one scene version into ``out_dir``; returns the written paths.

    ``cols`` are the ``views.parquet`` columns (``layout.build_views_table``); ``fv`` may be
    None (no free-view stage): then there is no contact sheet.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sid = str(getattr(scene, "scene_id", "") or getattr(sel, "scene_id", ""))
    with _MPL_LOCK:
        paths = [_funnel(cols, out / "funnel.png", sid), _scores(cols, out / "scores.png", sid),
                 _cameras(scene, sel, cols, out / "cameras.png", sid),
                 _certainty(sel, out / "certainty.png", sid)]
        if fv is not None and len(fv.rgb) and view_ids is not None:
            paths.append(_contact_sheet(scene, fv, cols, view_ids, out / "contact_sheet.png",
                                        sid))
    return paths
