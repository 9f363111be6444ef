"""Fidelity benchmark of the free views (METHOD.md stages 7-10, issue 4 item 8).

Question answered: are the free views *true*? Every number compares an image the engine makes
with the truth at the same pose:

1. **Sample scene** (``write_sample_scene`` into a temp folder; the scene has an exact oracle,
   :class:`freescale_core.scene.sample.SampleWorld`): ingest -> reconstruct (all views) ->
   ``run_selection`` -> free views, then each final free view is compared with the oracle's
   true image at the same pose and intrinsics: PSNR and SSIM of the render (*before*) and of
   the stored, image-rectified view (*after*). One reconstruction and one selection serve all
   variants (reference, rectifier) in ``VARIANTS``: ``graph`` (the graph rule with the WIoU at
   the final pose, the default), ``graph_stored`` (the graph rule on the stored top-k edges,
   the earlier behaviour) and ``pose``, with ``none`` and ``reproject``; only stages 7-10 run
   per variant (renders are memoised, so the variants share them). ``ref_cover`` is the
   reference's true coverage (``true_coverage``: the fraction of the free view's surface
   pixels the reference camera truly sees, from the oracle's depth at both cameras), a
   measure of the reference choice that does not depend on the rectifier; ``best_cover`` is
   the best training view's.
   ``psnr_fg_*`` is the PSNR over pixels whose true ray hits a surface (not sky): the
   reconstruction has no sky (black background), which dominates full-image PSNR on views
   that look up.
2. **Real scenes** (``../shared/datasets``, OOD split ``scene.split("ood")``: the first 70% in
   capture order train, the rest are held out): reconstruct on the train part only, then the
   held-out real cameras are the "free views": rendered at the training resolution, quality
   filtered and image-rectified through ``run_freeviews`` exactly like free views, and compared
   with the real photos (resized to the same size, area filter). The ``graph`` rule's WIoU at
   the final pose comes from ``TrainOverlap`` on the certainty grid of the train-only
   reconstruction; the stored view graph (``graph_stored`` and the fallback) is built with
   the selection core's machinery (certainty grid, visibility, WIoU matrix, top-k edges)
   over train + held-out cameras. Pose rectification is disabled here (a moved camera has
   no photo to compare with). Rows with ``filter=on`` keep only held-out views that pass the
   stage-7 filter (the product path); ``filter=off`` rectifies and scores all held-out
   views.
3. **Spearman correlation** between each stage-7 score (brisque, black_ratio, depth_validity)
   and the true PSNR of the render, over every rendered candidate of the sample scene
   (rejected ones included; each record's scores and pose belong together: the final pose
   for passing views, the original pose for rejected ones). A good score has a *negative*
   correlation for brisque and black_ratio (higher = worse) and a *positive* one for
   depth_validity.

Output: tables on stdout (progress on stderr); ``--json`` prints one JSON object per row
instead, with ``kind`` one of ``fidelity`` (at least scene, reference, rectifier, n_views,
psnr_before, psnr_after, ssim_before, ssim_after, ref_cover, best_cover), ``compare`` (each
graph rule minus pose, paired per view), ``spearman`` (scene, score, spearman, n),
``filter`` (true PSNR of passed vs rejected candidates) and, with ``--per-view``, ``view``.

    python -m benchmarks.fidelity                      # sample scene + buddha + fountain (fast)
    python -m benchmarks.fidelity --quick              # tiny run (a couple of minutes)
    python -m benchmarks.fidelity --json --per-view    # JSON lines
    python -m benchmarks.fidelity --scenes             # sample scene only
    python -m benchmarks.fidelity --no-sample --scenes dtu_scan24

The reconstruction preset is ``--preset fast`` (as ``make run``); ``--iterations`` and
``--long-side`` override its step count and training resolution.
"""

from __future__ import annotations

import os
import sys

import argparse
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from schemas.freeview import FreeViewConfig
from schemas.pipeline import PipelineConfig

DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))
DEFAULT_SCENES = ["buddha", "strecha_fountain-P11"]
# ``graph``: the graph rule with the WIoU at the final pose (default); ``graph_stored``: the
# graph rule on the stored top-k edges of the candidate's original pose (the earlier default)
VARIANTS: tuple[tuple[str, str], ...] = (("graph", "none"), ("graph", "reproject"),
                                        ("graph_stored", "reproject"),
                                        ("pose", "none"), ("pose", "reproject"))
GRAPH_RULES = ("graph", "graph_stored")
COVER_DEPTH_TOL = 0.02  # relative depth agreement of the true-coverage test
SCORES = ("brisque", "black_ratio", "depth_validity", "photo_psnr", "photo_support",
          "certain_share", "beyond_share", "depth_edges", "floaters", "view_angle_deg",
          "pred_psnr")

__all__ = ["CachedRender", "image_metrics", "true_coverage", "variant_config", "build_config",
           "run_sample", "run_real", "main"]


def _log(msg: str) -> None:
    print(f"# {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------- helpers
class CachedRender:
    """Memoising wrapper of a ``render_fn`` (same pose and intrinsics -> same arrays).

    The renderers are deterministic, so the variants of one scene share renders; ``hits`` and
    ``misses`` count calls.
    """

    def __init__(self, render_fn: Callable):
        self.render_fn = render_fn
        self.cache: dict[tuple, tuple] = {}
        self.hits = self.misses = 0

    def __call__(self, world_from_cam, fx, fy, cx, cy, width, height):
        pose = np.ascontiguousarray(world_from_cam, dtype=np.float64)
        key = (pose.tobytes(), float(fx), float(fy), float(cx), float(cy), int(width),
               int(height))
        if key in self.cache:
            self.hits += 1
        else:
            self.misses += 1
            self.cache[key] = self.render_fn(pose, fx, fy, cx, cy, int(width), int(height))
        return self.cache[key]


def image_metrics(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None
                  ) -> tuple[float, float, float]:
    """PSNR (dB), SSIM and masked PSNR of uint8 ``[H, W, 3]`` images.

    SSIM is :func:`freescale_core.recon.losses.ssim` (11x11 Gaussian window, as ``evaluate``);
    the masked PSNR uses the pixels where ``mask [H, W]`` is True (NaN when none or no mask).
    """
    import torch

    from freescale_core.recon.losses import ssim

    a = img.astype(np.float64) / 255.0
    b = ref.astype(np.float64) / 255.0
    se = (a - b) ** 2

    def _psnr(mse: float) -> float:
        return math.inf if mse == 0 else -10.0 * math.log10(mse)

    p = _psnr(float(se.mean()))
    s = (float(ssim(torch.from_numpy(a), torch.from_numpy(b))) if min(a.shape[:2]) >= 11
         else math.nan)
    pm = math.nan
    if mask is not None and mask.any():
        pm = _psnr(float(se[mask].mean()))
    return p, s, pm


def true_coverage(view_cam: tuple, view_depth: np.ndarray, ref_cam: tuple,
                  ref_depth: np.ndarray, depth_tol: float = COVER_DEPTH_TOL) -> float:
    """Fraction of a view's surface pixels that a reference camera truly sees.

    Each pixel with a surface (``view_depth > 0``, true camera-z depth) is lifted to 3D and
    projected into the reference; it counts as seen when it lands inside the reference image,
    in front of the camera, and one of the (up to 4) reference pixels around the projection
    has a true depth within ``depth_tol`` (relative) of the point's depth there, i.e. the
    reference's first surface along that ray is this point (not an occluder). Needs true depth
    at both cameras (the sample scene's oracle); independent of any rectifier.

    Args:
        view_cam, ref_cam: ``(world_from_cam [4, 4], fx, fy, cx, cy)``.
        view_depth: ``[H, W]`` true depth of the view (0 = no surface).
        ref_depth: ``[Hr, Wr]`` true depth of the reference (0 = no surface).
    Returns:
        The fraction in [0, 1] (NaN when the view has no surface pixel).
    """
    from freescale_core.freeviews.rectify_image import RenderedView, _lift, _project

    surf = np.asarray(view_depth) > 0
    if not surf.any():
        return math.nan
    v = RenderedView(None, None, None, *view_cam)
    r = RenderedView(None, None, None, *ref_cam)
    X = _lift(v, np.where(surf, view_depth, 1.0).astype(np.float64))[surf]
    u, w, z = _project(r, X)
    Hr, Wr = ref_depth.shape
    seen = np.zeros(X.shape[0], bool)
    for dx in (-0.5, 0.5):
        for dy in (-0.5, 0.5):
            ix, iy = np.floor(u + dx).astype(np.int64), np.floor(w + dy).astype(np.int64)
            inb = (z > 1e-9) & (ix >= 0) & (ix < Wr) & (iy >= 0) & (iy < Hr)
            d = ref_depth[np.clip(iy, 0, Hr - 1), np.clip(ix, 0, Wr - 1)].astype(np.float64)
            seen |= inb & (d > 0) & (np.abs(d - z) <= depth_tol * d)
    return float(seen.mean())


def _mean(xs) -> float:
    xs = [x for x in xs if x is not None and not math.isnan(x)]
    return float(np.mean(xs)) if xs else math.nan


def _resize(img: np.ndarray, w: int, h: int) -> np.ndarray:
    import cv2

    if img.shape[:2] == (h, w):
        return img
    return cv2.resize(img, (int(w), int(h)), interpolation=cv2.INTER_AREA)


def variant_config(base: FreeViewConfig, reference: str, rectifier: str) -> FreeViewConfig:
    """``base`` with ``reference.rule`` and ``rectifier.backend`` replaced (``reference``
    ``"graph_stored"`` is the graph rule with ``overlap = "stored_graph"``, ``"graph"`` with
    ``"final_pose"``)."""
    d = base.model_dump(mode="json")
    d["reference"]["rule"] = "graph" if reference in GRAPH_RULES else reference
    if reference in GRAPH_RULES:
        d["reference"]["overlap"] = "stored_graph" if reference == "graph_stored" else "final_pose"
    d["rectifier"]["backend"] = rectifier
    return FreeViewConfig.model_validate(d)


def build_config(preset: str = "fast", iterations: int | None = None,
                 long_side: int | None = None, quick: bool = False) -> PipelineConfig:
    """Pipeline config of the benchmark: a preset, optionally shortened.

    ``quick`` caps training at 80 steps on images of long side 96 with <= 2,000 Gaussians.
    """
    rec: dict = {}
    if quick:
        rec.update(max_iterations=80, min_iterations=40, densify_until=70, max_long_side=96,
                   cap_gaussians=2_000)
    if iterations is not None:
        rec["max_iterations"] = int(iterations)
    if long_side is not None:
        rec["max_long_side"] = int(long_side)
    cfg = PipelineConfig.from_preset(preset)  # type: ignore[arg-type]
    if rec:
        if "max_iterations" in rec:
            n = rec["max_iterations"]
            rec.setdefault("min_iterations", min(cfg.recon.min_iterations, n))
            rec.setdefault("densify_until", min(cfg.recon.densify_until, max(0, n - 10)))
        cfg = PipelineConfig.from_preset(preset, {"recon": rec})  # type: ignore[arg-type]
    return cfg


def reconstruct_cached(scene, cfg: PipelineConfig, seed: int = 0, train_idx=None,
                       cache_dir: str | Path | None = None):
    """``freescale_core.recon.trainer.reconstruct``, memoised as PLY + stats JSON in ``cache_dir``.

    The key hashes the cameras, sparse points, image names and file sizes, the recon config,
    the seed and the training indices (None or no cache dir: always reconstruct).
    Returns ``(gaussians, stats, seconds_spent_here)``.
    """
    import hashlib

    from freescale_core.scene.ply import read_ply
    from freescale_core.recon.trainer import reconstruct

    t0 = time.perf_counter()
    path = None
    if cache_dir is not None:
        h = hashlib.sha256()
        c = scene.cameras
        for arr in (c.world_from_cam, c.fx, c.fy, c.cx, c.cy, c.width, c.height,
                    scene.points_xyz, scene.points_rgb,
                    np.array([] if train_idx is None else train_idx, np.int64)):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(json.dumps([scene.scene_id, list(scene.image_names),
                             [p.stat().st_size for p in scene.image_paths],
                             cfg.recon.model_dump(mode="json"), int(seed)],
                            sort_keys=True).encode())
        path = Path(cache_dir) / f"{scene.scene_id}-{h.hexdigest()[:16]}.ply"
        if path.is_file() and path.with_suffix(".json").is_file():
            stats = json.loads(path.with_suffix(".json").read_text())
            _log(f"{scene.scene_id}: reconstruction read from {path}")
            return read_ply(path, scene.scene_id), stats, time.perf_counter() - t0
    rec = reconstruct(scene, cfg.recon, seed=seed, train_idx=train_idx)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.write_ply(path)  # with its background colour
        path.with_suffix(".json").write_text(json.dumps(rec.stats, default=str))
    return rec.gaussians, rec.stats, time.perf_counter() - t0


def _fidelity_row(scene: str, split: str, flt: str, ref: str, rect: str, views: list[dict],
                  fv, seconds: float) -> dict:
    rules: dict[str, int] = {}
    for v in views:
        if v["reference_rule"]:
            rules[v["reference_rule"]] = rules.get(v["reference_rule"], 0) + 1
    return {
        "kind": "fidelity", "scene": scene, "split": split, "filter": flt, "reference": ref,
        "rectifier": rect, "n_views": len(views),
        "psnr_before": _mean(v["psnr_before"] for v in views),
        "psnr_after": _mean(v["psnr_after"] for v in views),
        "ssim_before": _mean(v["ssim_before"] for v in views),
        "ssim_after": _mean(v["ssim_after"] for v in views),
        "psnr_fg_before": _mean(v["psnr_fg_before"] for v in views),
        "psnr_fg_after": _mean(v["psnr_fg_after"] for v in views),
        "n_improved": int(sum(v["psnr_after"] > v["psnr_before"] + 1e-9 for v in views)),
        "n_worse": int(sum(v["psnr_after"] < v["psnr_before"] - 1e-9 for v in views)),
        "rect_weight": _mean(v["rect_weight"] for v in views),
        "ref_cover": _mean(v["ref_cover"] for v in views),
        "best_cover": _mean(v["best_cover"] for v in views),
        "reference_rules": ",".join(f"{k}:{n}" for k, n in sorted(rules.items())),
        "n_candidates": int(fv.counts["candidates"]), "n_passed": int(fv.counts["passed"]),
        "warnings": "; ".join(fv.warnings), "seconds": seconds,
    }


def _compare_rows(scene: str, split: str, flt: str, per_variant: dict) -> list[dict]:
    """Graph minus pose reference, paired per view, for each rectifier that uses a reference."""
    out = []
    for ref, rect in sorted({(a, r) for a, r in per_variant if a in GRAPH_RULES}):
        g, p = per_variant.get((ref, rect)), per_variant.get(("pose", rect))
        if g is None or p is None or rect == "none":
            continue
        pv = {v["candidate"]: v for v in p}
        pairs = [(v, pv[v["candidate"]]) for v in g if v["candidate"] in pv]
        d = [a["psnr_after"] - b["psnr_after"] for a, b in pairs]
        ds = [a["ssim_after"] - b["ssim_after"] for a, b in pairs]
        diff_ref = [(a, b) for a, b in pairs if a["reference_view"] != b["reference_view"]]
        dd = [a["psnr_after"] - b["psnr_after"] for a, b in diff_ref]
        dc = [a["ref_cover"] - b["ref_cover"] for a, b in pairs]
        out.append({
            "kind": "compare", "scene": scene, "split": split, "filter": flt,
            "rectifier": rect, "compare": f"{ref}-pose", "reference": ref, "n": len(pairs),
            "mean_dpsnr": _mean(d), "mean_dssim": _mean(ds), "mean_dcover": _mean(dc),
            "n_diff_reference": len(diff_ref), "mean_dpsnr_diff_reference": _mean(dd),
            "graph_wins": int(sum(x > 1e-9 for x in d)),
            "pose_wins": int(sum(x < -1e-9 for x in d)),
            "graph_wins_cover": int(sum(x > 1e-9 for x in dc if not math.isnan(x))),
            "pose_wins_cover": int(sum(x < -1e-9 for x in dc if not math.isnan(x))),
        })
    return out


def _view_rows(scene: str, fv, truth: Callable[[object], tuple[np.ndarray, np.ndarray | None]],
               cover: Callable[[object], tuple[float, float]] | None = None) -> list[dict]:
    """Per final view: metrics of the render and of the stored image against the truth;
    ``cover(record) -> (ref_cover, best_cover)`` (true coverage of the chosen reference and
    the best over all training views; NaN when absent or no reference)."""
    recs = {r.candidate: r for r in fv.records}
    rows = []
    for k, c in enumerate(fv.final_candidates):
        r = recs[int(c)]
        true_rgb, mask = truth(r)
        pb, sb, fb = image_metrics(fv.rgb_render[k], true_rgb, mask)
        pa, sa, fa = image_metrics(fv.rgb[k], true_rgb, mask)
        rc, bc = cover(r) if cover is not None and r.reference_view >= 0 else (math.nan,
                                                                                 math.nan)
        rows.append({
            "kind": "view", "scene": scene, "candidate": int(c), "reference_view":
            int(r.reference_view), "reference_rule": r.reference_rule, "rectifier": r.rectifier,
            "rect_weight": float(r.rect_weight), "brisque": float(r.brisque),
            "n_rect_steps": int(r.n_rect_steps), "psnr_before": pb, "psnr_after": pa,
            "ssim_before": sb, "ssim_after": sa, "psnr_fg_before": fb, "psnr_fg_after": fa,
            "ref_cover": rc, "best_cover": bc,
        })
    return rows


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    from scipy.stats import spearmanr

    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return math.nan
    return float(spearmanr(x[ok], y[ok]).statistic)


def _record_rows(scene: str, recs, render, truth) -> list[dict]:
    """One row per rendered candidate (``kind = "record"``): every stage-7 and trust score of
    the render at the record's pose and its true PSNR (full and foreground)."""
    from freescale_core.freeviews.quality import to_uint8

    out = []
    for r in recs:
        rgb, _, _ = render(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
        true_rgb, mask = truth(r)
        p, s, pf = image_metrics(to_uint8(rgb), true_rgb, mask)
        out.append({"kind": "record", "scene": scene, "candidate": int(r.candidate),
                    "passed": bool(r.passed), "final": bool(r.final), "true_psnr": p,
                    "true_ssim": s, "true_psnr_fg": pf,
                    **{k: float(getattr(r, k)) for k in SCORES}})
    return out


def _score_rows(scene: str, recs, records: list[dict]) -> tuple[list[dict], list[dict]]:
    """Spearman of each score with the true PSNR over ``records``, and the filter row."""
    psnr = np.array([r["true_psnr"] for r in records])
    psnr_fg = np.array([r["true_psnr_fg"] for r in records], dtype=np.float64)
    spear = []
    for s in SCORES:
        x = np.array([r[s] for r in records], dtype=np.float64)
        pred = x if s == "pred_psnr" else None
        spear.append({"kind": "spearman", "scene": scene, "score": s,
                      "spearman": _spearman(x, psnr), "spearman_fg": _spearman(x, psnr_fg),
                      "n": int(np.isfinite(x).sum()),
                      "mae_db": _mean(np.abs(pred - psnr)) if pred is not None else math.nan,
                      "bias_db": _mean(pred - psnr) if pred is not None else math.nan})
    passed = np.array([r.passed for r in recs])
    final = np.array([r.final for r in recs])
    filt = [{"kind": "filter", "scene": scene, "n_candidates": len(recs),
             "n_passed": int(passed.sum()), "n_rejected": int((~passed).sum()),
             "n_final": int(final.sum()),
             "psnr_passed": _mean(psnr[passed]), "psnr_rejected": _mean(psnr[~passed]),
             "psnr_fg_passed": _mean(psnr_fg[passed]),
             "psnr_fg_rejected": _mean(psnr_fg[~passed])}]
    return spear, filt


def _select_rows(scene: str, records: list[dict], run, base_cfg: FreeViewConfig,
                 truth) -> list[dict]:
    """Mean true PSNR of the stored free views (renders): the paper's filter and final
    selection vs the trust filter and ranking at the same number of views.

    ``old``: a full run (``run(cfg)``) with ``trust.filter = "paper"``,
    ``final.rank_by = "brisque"`` (n final views); ``trust``: a full run with
    ``trust.filter = "trust"``, ``final.rank_by = "trust"``, ``target = n`` and
    ``cap_to_target`` (fewer than n when fewer pass); ``rerank``: among the rendered
    ``records`` (every candidate at its pose), the top n by predicted PSNR (no re-rendering,
    isolates the ranking); ``oracle``: the top n by true PSNR."""
    def cfg_with(**kw):
        d = base_cfg.model_dump(mode="json")
        d["trust"]["filter"] = kw.pop("filter")
        d["final"].update(kw)
        return FreeViewConfig.model_validate(d)

    def psnrs(fv):
        recs = {r.candidate: r for r in fv.records}
        return [image_metrics(fv.rgb_render[k], truth(recs[int(c)])[0])[0]
                for k, c in enumerate(fv.final_candidates)]

    old = psnrs(run(cfg_with(filter="paper", rank_by="brisque")))
    n = len(old)
    if n == 0:
        return []
    new = psnrs(run(cfg_with(filter="trust", rank_by="trust", target=n, cap_to_target=True)))
    ok = [r for r in records if np.isfinite(r["pred_psnr"])]
    top = sorted(ok, key=lambda r: -r["pred_psnr"])[:n]
    best = sorted(records, key=lambda r: -r["true_psnr"])[:n]
    return [{"kind": "select", "scene": scene, "n_old": n, "psnr_old": _mean(old),
             "n_new": len(new), "psnr_new": _mean(new), "n_rerank": len(top),
             "psnr_rerank": _mean([r["true_psnr"] for r in top]),
             "psnr_oracle": _mean([r["true_psnr"] for r in best]),
             "n_records": len(records)}]


# ---------------------------------------------------------------------- sample scene
def run_sample(scene_dir: str | Path, cfg: PipelineConfig, seed: int = 0,
               variants=VARIANTS, recon_cache: str | Path | None = None) -> dict:
    """Part 1 and 3 on a written sample scene.

    Args:
        scene_dir: a folder written by ``write_sample_scene`` (has ``scene.json``).
        cfg: pipeline config (recon, select, freeview are used).
        seed: seed of reconstruction and selection.
        variants: ``(reference rule, rectifier backend)`` pairs.
        recon_cache: optional folder memoising the reconstruction (``reconstruct_cached``).
    Returns:
        ``{"rows", "compare", "spearman", "filter", "views", "info"}`` (lists of dicts; info
        a dict).
    """
    from freescale_core.freeviews.run import run_freeviews
    from freescale_core.scene.io import load_scene
    from freescale_core.eval.oracle import ground_truth_oracle
    from freescale_core.freeviews.run import make_overlap_fn, make_render_fn
    from freescale_core.select.run import run_selection

    scene_dir = Path(scene_dir)
    oracle = ground_truth_oracle(scene_dir)
    if oracle is None:
        raise ValueError(f"{scene_dir} has no scene.json: not a sample scene")
    scene = load_scene(scene_dir)
    name = "sample"
    g, stats, t_rec = reconstruct_cached(scene, cfg, seed, None, recon_cache)
    _log(f"{name}: reconstructed {len(g)} Gaussians in {t_rec:.0f} s "
         f"(train PSNR {stats.get('recon_train_psnr', math.nan):.2f} dB)")
    t0 = time.perf_counter()
    sel = run_selection(g, scene.cameras, cfg.select, seed=seed,
                        scene_id=scene.scene_id, capture_order=scene.capture_order)
    t_sel = time.perf_counter() - t0
    _log(f"{name}: selection kept {len(sel.selected)} of {len(sel.candidates)} candidates "
         f"in {t_sel:.1f} s")
    T = int(sel.n_train)
    cand = np.asarray(sel.selected, dtype=np.int64) - T
    edges = (sel.edges.src, sel.edges.dst, sel.edges.wiou)
    render = CachedRender(make_render_fn(g))
    true_cache = CachedRender(lambda *a: oracle.render(*a))

    def truth(r):
        rgb, depth = true_cache(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
        return rgb, depth > 0

    cover_cache: dict[tuple, np.ndarray] = {}

    def cover(r):
        """True coverage of the record's reference, and the best over the training views
        (the training cameras at the record's render scale)."""
        key = (r.world_from_cam.tobytes(), r.fx, r.width)
        if key not in cover_cache:
            _, d_v = true_cache(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
            tc = scene.cameras.scaled(r.fx / float(sel.candidates.fx[r.candidate]))
            cov = []
            for t in range(T):
                args = (tc.world_from_cam[t], tc.fx[t], tc.fy[t], tc.cx[t], tc.cy[t])
                _, d_t = true_cache(*args, tc.width[t], tc.height[t])
                cov.append(true_coverage((r.world_from_cam, r.fx, r.fy, r.cx, r.cy), d_v,
                                         args, d_t))
            cover_cache[key] = np.array(cov)
        cov = cover_cache[key]
        return float(cov[r.reference_view]), float(np.nanmax(cov))

    rows, views_all, per_variant, first_fv = [], [], {}, None
    for ref, rect in variants:
        t0 = time.perf_counter()
        vc = variant_config(cfg.freeview, ref, rect)
        fv = run_freeviews(scene.cameras, scene.load_image, sel.candidates, cand, edges, render,
                           vc, seed=seed, overlap_fn=make_overlap_fn(sel, scene.cameras, vc),
                           grid=sel.grid)
        views = _view_rows(name, fv, truth, cover)
        for v in views:
            v["reference"] = ref
        per_variant[(ref, rect)] = views
        views_all += views
        rows.append(_fidelity_row(name, "all", "on", ref, rect, views, fv,
                                  time.perf_counter() - t0))
        _log(f"{name}: {ref}/{rect}: {len(views)} views, PSNR {rows[-1]['psnr_before']:.2f} -> "
             f"{rows[-1]['psnr_after']:.2f} dB")
        first_fv = first_fv or fv

    # part 3: every rendered candidate (records), score vs true PSNR at the record's pose
    spear, filt, records, select = [], [], [], []
    if first_fv is not None and first_fv.records:
        recs = first_fv.records
        records = _record_rows(name, recs, render, truth)
        spear, filt = _score_rows(name, recs, records)
        # part 4: old filter (paper, BRISQUE) vs trust at the same number of kept views
        select = _select_rows(name, records, lambda vc: run_freeviews(
            scene.cameras, scene.load_image, sel.candidates, cand, edges, render, vc,
            seed=seed, overlap_fn=make_overlap_fn(sel, scene.cameras, vc), grid=sel.grid),
            variant_config(cfg.freeview, "graph", "none"), truth)
    info = {"scene": name, "n_train": T, "n_candidates": len(sel.candidates),
            "n_selected": int(len(sel.selected)), "n_gaussians": len(g),
            "recon_seconds": t_rec, "select_seconds": t_sel,
            "recon_train_psnr": stats.get("recon_train_psnr"),
            "train_resolution": stats.get("train_resolution"),
            "selection_counts": dict(sel.counts),
            "renders": render.misses, "render_cache_hits": render.hits}
    return {"rows": rows, "compare": _compare_rows(name, "all", "on", per_variant),
            "spearman": spear, "filter": filt, "views": views_all, "info": info,
            "records": records, "select": select}


# ---------------------------------------------------------------------- real scenes
def heldout_graph(gaussians, cams, cfg: PipelineConfig, scene_id: str, return_grid: bool = False
                  ) -> tuple:
    """View graph over ``cams`` (train then held-out) with the selection core's machinery.

    Certainty grid of ``gaussians`` (stage 2), visibility of its non-empty voxels in every
    camera (stage 5), WIoU matrix (Eq. 3) and top-k edges above the edge threshold.
    Returns ``(src, dst, wiou)`` over node ids ``0 .. len(cams) - 1`` (and the certainty
    grid as a fourth item with ``return_grid``).
    """
    from freescale_core.select.certainty import build_certainty_grid
    from freescale_core.select.view_graph import edges_from_matrix, wiou_matrix
    from freescale_core.select.visibility import compute_visibility

    sc = cfg.select
    grid, _, _ = build_certainty_grid(gaussians, sc.grid, scene_id)
    vis = compute_visibility(cams, grid, sc.visibility)
    nodes = np.arange(len(cams))
    gdt = np.float32 if sc.graph.gemm_dtype == "float32" else np.float64
    W = wiou_matrix(vis, nodes, gdt)
    edges = edges_from_matrix(W, nodes, sc.graph.edge_threshold, sc.graph.top_k)
    return (*edges, grid) if return_grid else edges


def run_real(scene_dir: str | Path, cfg: PipelineConfig, seed: int = 0, variants=VARIANTS,
             cache_dir: str | Path | None = None, recon_cache: str | Path | None = None
             ) -> dict:
    """Part 2 on one real scene (OOD split): held-out photos as the truth.

    Returns:
        ``{"rows", "compare", "views", "info"}``.
    """
    from freescale_core.freeviews.run import run_freeviews
    from freescale_core.scene.io import load_scene
    from freescale_core.freeviews.run import make_render_fn

    scene = load_scene(scene_dir, cache_dir=cache_dir)
    name = scene.scene_id
    train_idx, test_idx = scene.split("ood")
    g, stats, t_rec = reconstruct_cached(scene, cfg, seed, train_idx, recon_cache)
    scale = float(stats["train_scale"])
    _log(f"{name}: reconstructed on {len(train_idx)} views ({len(test_idx)} held out), "
         f"{len(g)} Gaussians, {t_rec:.0f} s")
    train_native = scene.cameras.subset(train_idx)
    test_native = scene.cameras.subset(test_idx)
    from freescale_core.geometry.cameras import Cameras

    from freescale_core.freeviews.references import TrainOverlap

    src, dst, wiou, grid = heldout_graph(g, Cameras.concat([train_native, test_native]),
                                         cfg, name, return_grid=True)
    overlap = TrainOverlap(grid, train_native, cfg.select.visibility,
                           cfg.freeview.reference.overlap_angle_deg)
    T, H = len(train_idx), len(test_idx)
    train_cams, test_cams = train_native.scaled(scale), test_native.scaled(scale)

    def train_images(i: int) -> np.ndarray:
        return _resize(scene.load_image(int(train_idx[i])), int(train_cams.width[i]),
                       int(train_cams.height[i]))

    photos = {j: _resize(scene.load_image(int(test_idx[j])), int(test_cams.width[j]),
                         int(test_cams.height[j])) for j in range(H)}

    def truth(r):
        return photos[int(r.candidate)], None

    render = CachedRender(make_render_fn(g))
    base = cfg.freeview.model_dump(mode="json")
    base["render_scale"] = 1.0  # cameras are already at the training resolution
    base["pose"]["enabled"] = False  # a moved camera has no photo to compare with
    base_cfg = FreeViewConfig.model_validate(base)
    # filter off: thresholds no score can fail (model_copy does not validate, on purpose)
    q_off = base_cfg.quality.model_copy(update={"black_ratio_max": math.inf,
                                                "brisque_max": math.inf,
                                                "depth_validity_min": -math.inf})
    rows, views_all, compare, records, spear = [], [], [], [], []
    n_graph_edges_heldout = int(np.sum((np.maximum(src, dst) >= T) & (np.minimum(src, dst) < T)))
    for flt in ("on", "off"):
        per_variant = {}
        for ref, rect in variants:
            t0 = time.perf_counter()
            vc = variant_config(base_cfg, ref, rect)
            if flt == "off":
                vc = vc.model_copy(update={"quality": q_off})
            fv = run_freeviews(train_cams, train_images, test_cams, np.arange(H),
                               (src, dst, wiou), render, vc, seed=seed, overlap_fn=overlap,
                               grid=grid)
            if flt == "off" and not records:  # every held-out view, scored as a free view
                records = _record_rows(name, fv.records, render, truth)
                spear, _ = _score_rows(name, fv.records, records)
            views = _view_rows(name, fv, truth)
            for v in views:
                v.update(reference=ref, filter=flt, photo=scene.image_names[int(test_idx[
                    v["candidate"]])])
            per_variant[(ref, rect)] = views
            views_all += views
            rows.append(_fidelity_row(name, "ood", flt, ref, rect, views, fv,
                                      time.perf_counter() - t0))
            _log(f"{name}: filter {flt} {ref}/{rect}: {len(views)}/{H} views, PSNR "
                 f"{rows[-1]['psnr_before']:.2f} -> {rows[-1]['psnr_after']:.2f} dB")
        compare += _compare_rows(name, "ood", flt, per_variant)
    info = {"scene": name, "n_train": T, "n_heldout": H, "n_gaussians": len(g),
            "recon_seconds": t_rec, "train_resolution": stats.get("train_resolution"),
            "recon_train_psnr": stats.get("recon_train_psnr"),
            "n_graph_edges": int(len(src)), "n_train_heldout_edges": n_graph_edges_heldout}
    return {"rows": rows, "compare": compare, "views": views_all, "info": info,
            "records": records, "spearman": spear}


# ---------------------------------------------------------------------- output
def _clean(v):
    if isinstance(v, float):
        return None if math.isnan(v) else (round(v, 4) if math.isfinite(v) else str(v))
    if isinstance(v, (np.floating,)):
        return _clean(float(v))
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def _fmt(v, w: int, d: int = 2) -> str:
    if isinstance(v, float):
        return f"{v:>{w}.{d}f}"
    return f"{v!s:>{w}}"


def print_tables(rows, compare, spear, filt, infos, out=sys.stdout, select=()) -> None:
    p = lambda s="": print(s, file=out)  # noqa: E731
    p("## Fidelity: mean over views of PSNR (dB) / SSIM against the truth, before -> after "
      "image rectification")
    hdr = (f"{'scene':<22}{'split':>6}{'filter':>7}{'ref':>13}{'rectifier':>10}{'n':>4}"
           f"{'psnr_b':>8}{'psnr_a':>8}{'dpsnr':>7}{'ssim_b':>8}{'ssim_a':>8}{'fg_b':>7}"
           f"{'fg_a':>7}{'up/dn':>7}{'w':>6}{'cover':>7}{'best':>6}  reference rules")
    p(hdr)
    for r in rows:
        p(f"{r['scene']:<22}{r['split']:>6}{r['filter']:>7}{r['reference']:>13}"
          f"{r['rectifier']:>10}{r['n_views']:>4}{_fmt(r['psnr_before'], 8)}"
          f"{_fmt(r['psnr_after'], 8)}{_fmt(r['psnr_after'] - r['psnr_before'], 7)}"
          f"{_fmt(r['ssim_before'], 8, 3)}{_fmt(r['ssim_after'], 8, 3)}"
          f"{_fmt(r['psnr_fg_before'], 7)}{_fmt(r['psnr_fg_after'], 7)}"
          f"{str(r['n_improved']) + '/' + str(r['n_worse']):>7}{_fmt(r['rect_weight'], 6)}"
          f"{_fmt(r['ref_cover'], 7, 3)}{_fmt(r['best_cover'], 6, 2)}  {r['reference_rules']}")
    if compare:
        p()
        p("## Reference rule: graph minus pose, paired per view (after rectification; "
          "dcover: true coverage of the reference, sample scene only)")
        p(f"{'scene':<22}{'filter':>7}{'graph rule':>13}{'rectifier':>10}{'n':>4}{'dpsnr':>8}"
          f"{'dssim':>8}{'n_diff_ref':>11}{'dpsnr|diff':>11}{'g_wins':>7}{'p_wins':>7}"
          f"{'dcover':>8}{'g/p cover wins':>15}")
        for c in compare:
            p(f"{c['scene']:<22}{c['filter']:>7}{c['reference']:>13}{c['rectifier']:>10}"
              f"{c['n']:>4}{_fmt(c['mean_dpsnr'], 8, 3)}{_fmt(c['mean_dssim'], 8, 4)}"
              f"{c['n_diff_reference']:>11}{_fmt(c['mean_dpsnr_diff_reference'], 11, 3)}"
              f"{c['graph_wins']:>7}{c['pose_wins']:>7}{_fmt(c['mean_dcover'], 8, 3)}"
              f"{str(c['graph_wins_cover']) + '/' + str(c['pose_wins_cover']):>15}")
    if spear:
        p()
        p("## Spearman correlation of each quality score with the true PSNR of the render "
          "(all rendered candidates)")
        p(f"{'scene':<22}{'score':>16}{'n':>5}{'spearman':>10}{'spearman_fg':>12}"
          f"{'mae_db':>8}{'bias_db':>8}")
        for s in spear:
            p(f"{s['scene']:<22}{s['score']:>16}{s['n']:>5}{_fmt(s['spearman'], 10, 3)}"
              f"{_fmt(s['spearman_fg'], 12, 3)}{_fmt(s.get('mae_db', math.nan), 8)}"
              f"{_fmt(s.get('bias_db', math.nan), 8)}")
    if select:
        p()
        p("## Stored free views: mean true PSNR (dB) of the renders, paper filter (BRISQUE) vs "
          "trust, same number of views (rerank: top-n of the same records by predicted PSNR; "
          "oracle: top-n by true PSNR)")
        for r in select:
            p(f"{r['scene']:<22} old {r['n_old']:>3}: {r['psnr_old']:.2f}   trust "
              f"{r['n_new']:>3}: {r['psnr_new']:.2f}   rerank {r['n_rerank']:>3}: "
              f"{r['psnr_rerank']:.2f}   oracle {r['psnr_oracle']:.2f}   "
              f"({r['n_records']} records)")
    if filt:
        p()
        p("## Quality filter: mean true PSNR (dB) of passed vs rejected candidates")
        for f in filt:
            p(f"{f['scene']:<22} passed {f['n_passed']:>3}: {f['psnr_passed']:.2f} "
              f"(fg {f['psnr_fg_passed']:.2f})   rejected {f['n_rejected']:>3}: "
              f"{f['psnr_rejected']:.2f} (fg {f['psnr_fg_rejected']:.2f})   final "
              f"{f['n_final']}")
    if infos:
        p()
        for i in infos:
            p("# " + json.dumps(_clean_dict(i)))


def _clean_dict(d: dict) -> dict:
    return {k: _clean(v) for k, v in d.items()}


# ---------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="*", default=None,
                    help=f"real scenes under {DATASETS} (default: {' '.join(DEFAULT_SCENES)}; "
                         "give the flag alone for none)")
    ap.add_argument("--no-sample", action="store_true", help="skip the sample scene")
    ap.add_argument("--views", type=int, default=None, help="sample scene frames (default 36)")
    ap.add_argument("--width", type=int, default=None, help="sample scene width (default 256)")
    ap.add_argument("--height", type=int, default=None, help="sample scene height (default 192)")
    ap.add_argument("--preset", default="fast", choices=["fast", "paper"])
    ap.add_argument("--iterations", type=int, default=None, help="recon max_iterations")
    ap.add_argument("--long-side", type=int, default=None, help="recon max_long_side")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true",
                    help="tiny run: 16-frame 128x96 sample scene, 80 recon steps at 96 px; "
                         "one real scene (buddha) unless --scenes is given")
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--per-view", action="store_true", help="also per-view rows (JSON)")
    ap.add_argument("--recon-cache", type=Path, default=None,
                    help="folder memoising reconstructions (PLY + stats) across runs")
    ap.add_argument("--out", type=Path, default=None,
                    help="also write every JSON row (per-view rows included) to this file")
    a = ap.parse_args(argv)

    n_views = a.views or (16 if a.quick else 36)
    width = a.width or (128 if a.quick else 256)
    height = a.height or (96 if a.quick else 192)
    scenes = a.scenes if a.scenes is not None else (DEFAULT_SCENES[:1] if a.quick
                                                     else DEFAULT_SCENES)
    cfg = build_config(a.preset, a.iterations, a.long_side, a.quick)
    rows, compare, spear, filt, views, infos = [], [], [], [], [], []
    records, select = [], []
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fidelity-") as tmp:
        if not a.no_sample:
            from freescale_core.scene.sample import write_sample_scene

            d = write_sample_scene(Path(tmp) / "sample", n_views=n_views, width=width,
                                   height=height, seed=a.seed)
            res = run_sample(d, cfg, a.seed, recon_cache=a.recon_cache)
            rows += res["rows"]
            compare += res["compare"]
            spear += res["spearman"]
            filt += res["filter"]
            views += res["views"]
            records += [{**r, "seed": a.seed} for r in res["records"]]
            select += res["select"]
            infos.append({**res["info"], "views": n_views, "size": [width, height]})
        if scenes:
            if not DATASETS.is_dir():
                _log(f"{DATASETS} is absent: real scenes skipped")
                scenes = []
            for s in scenes:
                d = DATASETS / s
                if not (d / "sparse" / "0").is_dir():
                    _log(f"{s}: no COLMAP model under {d}; skipped")
                    continue
                res = run_real(d, cfg, a.seed, cache_dir=Path(tmp) / "cache",
                               recon_cache=a.recon_cache)
                rows += res["rows"]
                compare += res["compare"]
                views += res["views"]
                spear += res["spearman"]
                records += [{**r, "seed": a.seed} for r in res["records"]]
                infos.append(res["info"])
    infos.append({"total_seconds": time.perf_counter() - t_all, "preset": a.preset,
                  "quick": a.quick, "recon_max_iterations": cfg.recon.max_iterations,
                  "recon_max_long_side": cfg.recon.max_long_side})
    lines = [json.dumps(_clean_dict(r)) for r in rows + compare + spear + filt + select]
    view_lines = [json.dumps(_clean_dict(r)) for r in views + records]
    info_lines = [json.dumps({"kind": "info", **_clean_dict(i)}) for i in infos]
    if a.out is not None:
        a.out.write_text("\n".join(lines + view_lines + info_lines) + "\n")
    if a.json:
        print("\n".join(lines + (view_lines if a.per_view else []) + info_lines))
    else:
        print_tables(rows, compare, spear, filt, infos, select=select)
    return 0


if __name__ == "__main__":
    sys.exit(main())
