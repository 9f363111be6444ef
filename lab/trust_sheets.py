"""Contact sheets of one real scene's stored free views: the paper's filter (BRISQUE) vs the
trust filter and ranking (issue 19), at the same number of views.

The scene is reconstructed on all its views (``--preset fast``), the selection core runs,
then stages 7-10 (``run_free_view_stage``) twice: ``trust.filter = "paper"``,
``final.rank_by = "brisque"`` (n views), and ``trust.filter = "trust"``,
``final.rank_by = "trust"`` capped to the same n. Each thumbnail is labelled with its view
id, BRISQUE/100 and predicted PSNR. Prints per-run means of the trust scores.

    python -m lab.trust_sheets --scene llff_fern --out docs/img
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.fidelity import DATASETS, build_config, reconstruct_cached
from schemas.freeview import FreeViewConfig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="llff_fern")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    ap.add_argument("--thumb", type=int, default=96)
    ap.add_argument("--recon-cache", type=Path, default=None)
    a = ap.parse_args(argv)

    from freescale_core.freeviews.run import run_free_view_stage
    from freescale_core.scene.io import load_scene
    from freescale_core.select.run import run_selection
    from freescale_core.store.pictures import save_contact_sheet

    scene = load_scene(DATASETS / a.scene)
    cfg = build_config(a.preset)
    g, stats, _ = reconstruct_cached(scene, cfg, 0, None, a.recon_cache)
    sel = run_selection(g, scene.cameras, cfg.select, seed=0, scene_id=scene.scene_id,
                        capture_order=scene.capture_order)
    T = int(sel.n_train)
    base = cfg.freeview.model_dump(mode="json")
    out = {}
    for name in ("paper", "trust"):
        d = {**base, "trust": {**base["trust"]}, "final": {**base["final"]}}
        if name == "paper":
            d["trust"]["filter"], d["final"]["rank_by"] = "paper", "brisque"
        else:
            n = out["paper"].n_final
            d["trust"]["filter"] = "trust"
            d["final"].update(rank_by="trust", target=max(n, 1), cap_to_target=True)
        fv = run_free_view_stage(scene, g, sel, FreeViewConfig.model_validate(d), seed=0,
                                 train_scale=float(stats["train_scale"]),
                                 background=cfg.recon.background,
                                 backend=cfg.recon.raster_backend)
        out[name] = fv
        a.out.mkdir(parents=True, exist_ok=True)
        path = a.out / f"trust_{a.scene}_{name}.png"
        if fv.n_final:
            save_contact_sheet(path, fv, T + fv.final_candidates, thumb_w=a.thumb, cols=6)
        fin = [r for r in fv.records if r.final]
        m = lambda k: float(np.nanmean([getattr(r, k) for r in fin])) if fin else float("nan")  # noqa: E731
        print(f"{a.scene} {name:>6}: {fv.n_final:>3} views of {len(fv.records)} rendered; "
              f"mean pred_psnr {m('pred_psnr'):.2f} dB, photo_psnr {m('photo_psnr'):.2f} dB, "
              f"photo_support {m('photo_support'):.3f}, brisque {m('brisque'):.3f} -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
