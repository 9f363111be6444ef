"""Where does a warped reference photo beat the render? Error by triangulation angle.

Sample scene only (it has an exact oracle). Reconstruct and select as
``benchmarks/fidelity.py`` does, run stages 7-9, then for every final free view and *every*
training view as the reference, run the ``reproject`` rectifier with the angle kernel and the
feathering switched off, and compare, on the pixels it blends, the squared error against the
true image of (a) the render and (b) the warped reference photo. Pixels are binned by the
triangulation angle (between the rays from the lifted point to the free and the reference
camera centres). This is the measurement behind the rectifier's angle kernel
(``angle_full_deg``, ``angle_zero_deg``) and the reference rules' view-direction kernel
(docs/FIDELITY.md).

    python -m lab.reproject_angle            # seed 0, fast preset (~1 min)
    python -m lab.reproject_angle --seed 1 --json
"""

from __future__ import annotations

import sys

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

BINS = (0.0, 2.0, 5.0, 10.0, 20.0, 30.0, 40.0, 180.0)


def _fidelity():
    from benchmarks import fidelity

    return fidelity


def angle_table(scene_dir: str | Path, seed: int = 0, preset: str = "fast",
                recon_cache: str | Path | None = None, bins=BINS) -> list[dict]:
    """Rows ``{lo, hi, n_pixels, mse_render, mse_warp}`` per angle bin (degrees)."""
    from freescale_core.freeviews.run import _reference, run_freeviews
    from freescale_core.scene.io import load_scene
    from freescale_core.eval.oracle import ground_truth_oracle
    from freescale_core.freeviews.run import make_render_fn
    from freescale_core.freeviews.rectify_image import (RenderedView, ReprojectRectifier, backward_warp,
                                              triangulation_angle_deg)
    from freescale_core.select.run import run_selection

    fid = _fidelity()
    scene = load_scene(scene_dir)
    oracle = ground_truth_oracle(scene_dir)
    cfg = fid.build_config(preset)
    g, _, _ = fid.reconstruct_cached(scene, cfg, seed, None, recon_cache)
    sel = run_selection(g, scene.cameras, cfg.select, seed=seed, scene_id=scene.scene_id,
                        capture_order=scene.capture_order)
    T = int(sel.n_train)
    render = fid.CachedRender(make_render_fn(g))
    fv = run_freeviews(scene.cameras, scene.load_image, sel.candidates,
                       np.asarray(sel.selected) - T, None, render,
                       fid.variant_config(cfg.freeview, "pose", "none"), seed=seed)
    tcams = scene.cameras.scaled(cfg.freeview.render_scale)
    rect = ReprojectRectifier(guided_radius=0, angle_full_deg=180.0, angle_zero_deg=180.0)
    nb = len(bins) - 1
    se_r, se_w, cnt = np.zeros(nb), np.zeros(nb), np.zeros(nb, np.int64)
    refs = {}
    recs = {r.candidate: r for r in fv.records}
    for c in fv.final_candidates:
        r = recs[int(c)]
        true = oracle.render(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width,
                             r.height)[0].astype(np.float32) / 255.0
        rgb, dep, al = render(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
        view = RenderedView(rgb, dep, al, r.world_from_cam, r.fx, r.fy, r.cx, r.cy)
        e_r = ((rgb - true) ** 2).mean(-1)
        for t in range(T):
            if t not in refs:
                refs[t] = _reference(t, scene.cameras, tcams, scene.load_image, render)
            photo, ref = refs[t]
            out = rect(view, photo, ref)
            m = out.weight > 0
            if not m.any():
                continue
            # the blended colour is the warp where the weight is 1 (no feathering here)
            warped, _, _ = backward_warp(photo.astype(np.float32) / 255.0, ref, view,
                                         np.where(m, out.depth, np.nan).astype(np.float64))
            e_w = ((warped - true) ** 2).mean(-1)
            ang = triangulation_angle_deg(view, ref, out.depth.astype(np.float64))
            k = np.clip(np.digitize(ang, bins) - 1, 0, nb - 1)
            for i in range(nb):
                mm = m & (k == i) & np.isfinite(ang)
                se_r[i] += e_r[mm].sum()
                se_w[i] += e_w[mm].sum()
                cnt[i] += int(mm.sum())
    return [{"lo": bins[i], "hi": bins[i + 1], "n_pixels": int(cnt[i]),
             "mse_render": float(se_r[i] / cnt[i]) if cnt[i] else float("nan"),
             "mse_warp": float(se_w[i] / cnt[i]) if cnt[i] else float("nan"),
             "n_views": int(len(fv.final_candidates)), "n_train": T} for i in range(nb)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default="fast", choices=["fast", "paper"])
    ap.add_argument("--recon-cache", type=Path, default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from freescale_core.scene.sample import write_sample_scene

    with tempfile.TemporaryDirectory(prefix="reproject-angle-") as tmp:
        d = write_sample_scene(Path(tmp) / "sample", n_views=36, width=256, height=192,
                               seed=a.seed)
        rows = angle_table(d, a.seed, a.preset, a.recon_cache)
    if a.json:
        print("\n".join(json.dumps(r) for r in rows))
        return 0
    print(f"# sample seed {a.seed}: {rows[0]['n_views']} final views x {rows[0]['n_train']} "
          "training views as reference; blended pixels only")
    print(f"{'angle (deg)':>12}{'pixels':>10}{'mse_render':>12}{'mse_warp':>10}  better")
    for r in rows:
        better = "warp" if r["mse_warp"] < r["mse_render"] else "render"
        print(f"{r['lo']:>5.0f}-{r['hi']:<6.0f}{r['n_pixels']:>10}{r['mse_render']:>12.5f}"
              f"{r['mse_warp']:>10.5f}  {better}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
