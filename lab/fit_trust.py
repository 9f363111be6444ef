"""Fit the trust model (freescale_core.freeviews.trust.predict_psnr) on procedural scenes.

Two steps:

``collect``: for each seed, a sample scene (``write_sample_scene(seed=...)``: layout and
capture path follow the seed; ``--views`` frames) is reconstructed with the benchmark's
config (``fidelity.build_config``, ``--quick`` by default), the selection core runs, and up to
``--max-cands`` *feasible* candidates (NMS-selected or suppressed, a deterministic spread)
are rendered and scored like free views (``run_freeviews`` with every filter test off, no
pose rectification), then compared with the oracle's true image at the same pose. One JSON
row per render (``fidelity._record_rows``: every stage-7 and trust score, ``true_psnr``).

``fit``: ridge regression of ``true_psnr`` on ``trust.FEATURES`` (standardised, NaN imputed
with the mean), the penalty chosen by leave-one-scene-out CV; prints the per-score Spearman,
the CV error, the held-out error on ``--test`` files (scenes never used for fitting), and
the constants to paste into ``freescale_core/freeviews/trust.py``.

    python -m lab.fit_trust collect --seeds 10 11 12 13 14 15 --out train.jsonl
    python -m lab.fit_trust fit train.jsonl --test test.jsonl

Only procedural scenes are ever used for fitting (real scenes are the held-out check in
``benchmarks/fidelity.py``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.fidelity import (CachedRender, _log, _record_rows, _spearman,
                                 build_config, reconstruct_cached)
from freescale_core.freeviews.trust import FEATURES, predict_psnr, trust_features
from schemas.freeview import FreeViewConfig

ALPHAS = (0.1, 1.0, 3.0, 10.0, 30.0, 100.0)


def collect_seed(seed: int, cfg, n_views: int, width: int, height: int, max_cands: int,
                 tmp: Path, recon_cache: Path | None) -> list[dict]:
    """Rows of one seed's sample scene (see the module docstring)."""
    from freescale_core.eval.oracle import ground_truth_oracle
    from freescale_core.freeviews.run import run_freeviews
    from freescale_core.freeviews.run import make_render_fn
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene
    from freescale_core.select.run import run_selection

    d = write_sample_scene(tmp / f"s{seed}", n_views=n_views, width=width, height=height,
                           seed=seed)
    oracle = ground_truth_oracle(d)
    scene = load_scene(d)
    g, stats, t = reconstruct_cached(scene, cfg, seed, None, recon_cache)
    sel = run_selection(g, scene.cameras, cfg.select, seed=seed, scene_id=scene.scene_id,
                        capture_order=scene.capture_order)
    T = int(sel.n_train)
    disp = np.asarray(sel.disposition[T:])
    feas = np.flatnonzero(disp != "infeasible")
    if feas.size > max_cands:
        feas = feas[np.round(np.linspace(0, feas.size - 1, max_cands)).astype(np.int64)]
    fc = cfg.freeview.model_dump(mode="json")
    fc["quality"].update(black_ratio_max=1.0, brisque_max=1e9, depth_validity_min=0.0)
    fc["pose"]["enabled"] = False
    fc["rectifier"]["backend"] = "none"
    fc["trust"]["filter"] = "paper"
    fc["final"]["rank_by"] = "brisque"
    vc = FreeViewConfig.model_validate(fc)
    vc = vc.model_copy(update={"quality": vc.quality.model_copy(
        update={"depth_validity_min": -math.inf})})
    render = CachedRender(make_render_fn(g))
    fv = run_freeviews(scene.cameras, scene.load_image, sel.candidates, feas,
                       (sel.edges.src, sel.edges.dst, sel.edges.wiou), render, vc, seed=seed,
                       grid=sel.grid)
    true_cache = CachedRender(lambda *a: oracle.render(*a))

    def truth(r):
        rgb, depth = true_cache(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
        return rgb, depth > 0

    rows = _record_rows(f"sample-s{seed}-v{n_views}", fv.records, render, truth)
    for r in rows:
        r.update(seed=seed, views=n_views, nms_selected=bool(
            disp[r["candidate"]] == "free_view"), recon_train_psnr=stats.get(
            "recon_train_psnr"))
    _log(f"seed {seed}: {len(rows)} renders, recon {t:.0f} s, train PSNR "
         f"{stats.get('recon_train_psnr', math.nan):.2f}")
    return rows


def load_rows(paths) -> list[dict]:
    rows = []
    for p in paths:
        for line in Path(p).read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                if r.get("kind") == "record" and r.get("true_psnr") is not None:
                    rows.append(r)
    return rows


def design(rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(X [n, F], y [n], group [n])`` (group = scene name)."""
    def f(r, k):
        v = r.get(k)
        return math.nan if v is None else (math.inf if v == "inf" else float(v))
    X = np.stack([trust_features({k: f(r, k) for k in ("photo_psnr", "photo_support",
                                                          "certain_share", "beyond_share",
                                                          "depth_edges", "floaters",
                                                          "view_angle_deg")},
                                 f(r, "brisque"), f(r, "black_ratio"), f(r, "depth_validity"))
                  for r in rows])
    y = np.array([min(float(r["true_psnr"]), 60.0) for r in rows])
    return X, y, np.array([r["scene"] for r in rows])


def ridge(X: np.ndarray, y: np.ndarray, alpha: float) -> tuple:
    """Ridge on standardised features, NaN imputed with the mean:
    ``(mean, scale, coef, intercept)`` for ``trust.predict_psnr``."""
    mean = np.nanmean(X, axis=0)
    scale = np.nanstd(X, axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    Z = np.where(np.isfinite(X), (X - mean) / scale, 0.0)
    b = float(y.mean())
    A = Z.T @ Z + alpha * np.eye(Z.shape[1])
    coef = np.linalg.solve(A, Z.T @ (y - b))
    return mean, scale, coef, b


def cv_predictions(X, y, groups, alpha) -> np.ndarray:
    pred = np.full(y.shape, np.nan)
    for g in np.unique(groups):
        m = groups == g
        pred[m] = predict_psnr(X[m], *ridge(X[~m], y[~m], alpha))
    return pred


def _table(title, rows_by, X, y, pred_fn) -> None:
    print(f"\n## {title}")
    print(f"{'feature':<16}{'spearman':>10}")
    for k, name in enumerate(FEATURES):
        print(f"{name:<16}{_spearman(X[:, k], y):>10.3f}")
    p = pred_fn(X)
    print(f"{'pred_psnr':<16}{_spearman(p, y):>10.3f}   MAE {np.mean(np.abs(p - y)):.2f} dB, "
          f"bias {np.mean(p - y):+.2f} dB, n {len(y)}")


SUMMARY_SCORES = ("brisque", "black_ratio", "depth_validity", "photo_psnr", "photo_support",
                  "certain_share", "beyond_share", "depth_edges", "floaters",
                  "view_angle_deg", "pred_psnr")


def summary(files) -> int:
    """Per score: Spearman with the true PSNR in each scene (file x scene), their mean and
    spread, and pooled over all; predicted-PSNR MAE; the ``select`` rows' mean and spread.
    ``pred_psnr`` is recomputed from the stored scores with the frozen model (files written
    before the model was frozen hold another prediction)."""
    groups: dict[str, list[dict]] = {}
    select = []
    for p in files:
        for line in Path(p).read_text().splitlines():
            r = json.loads(line) if line.strip() else {}
            if r.get("kind") == "record" and r.get("true_psnr") is not None:
                r["pred_psnr"] = float(predict_psnr(design([r])[0][0]))  # the frozen model
                groups.setdefault(f"{Path(p).stem}:{r['scene']}", []).append(r)
            elif r.get("kind") == "select":
                select.append(r)

    def num(v):
        return math.nan if v is None else (math.inf if v == "inf" else float(v))
    print(f"# {len(groups)} scenes: " + ", ".join(f"{g} ({len(v)})" for g, v in groups.items()))
    print(f"{'score':<16}{'mean':>8}{'std':>8}{'min':>8}{'max':>8}{'pooled':>8}   per scene")
    for s in SUMMARY_SCORES:
        per, xs, ys = [], [], []
        for g, rows in groups.items():
            x = np.array([num(r.get(s)) for r in rows])
            y = np.array([min(num(r["true_psnr"]), 60.0) for r in rows])
            per.append(_spearman(x, y))
            xs.append(x)
            ys.append(y)
        v = np.array(per)
        pooled = _spearman(np.concatenate(xs), np.concatenate(ys))
        print(f"{s:<16}{np.nanmean(v):>8.3f}{np.nanstd(v):>8.3f}{np.nanmin(v):>8.3f}"
              f"{np.nanmax(v):>8.3f}{pooled:>8.3f}   " + " ".join(f"{x:.2f}" for x in v))
    p = np.concatenate([[num(r["pred_psnr"]) for r in rows] for rows in groups.values()])
    y = np.concatenate([[min(num(r["true_psnr"]), 60.0) for r in rows]
                        for rows in groups.values()])
    print(f"pred_psnr: MAE {np.nanmean(np.abs(p - y)):.2f} dB, bias {np.nanmean(p - y):+.2f} dB"
          f", n {np.isfinite(p).sum()}")
    if select:
        d_new = np.array([r["psnr_new"] - r["psnr_old"] for r in select])
        d_rr = np.array([r["psnr_rerank"] - r["psnr_old"] for r in select])
        print(f"\nselect ({len(select)} scenes): old {np.mean([r['psnr_old'] for r in select]):.2f}"
              f" dB, trust {np.mean([r['psnr_new'] for r in select]):.2f} dB (diff "
              f"{d_new.mean():+.2f} +- {d_new.std():.2f}, per scene "
              + " ".join(f"{x:+.2f}" for x in d_new) + f"), rerank diff {d_rr.mean():+.2f} "
              f"+- {d_rr.std():.2f}; n old/trust " + " ".join(
                  f"{r['n_old']}/{r['n_new']}" for r in select))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--seeds", type=int, nargs="+", required=True)
    c.add_argument("--views", type=int, nargs="+", default=[16],
                   help="frames per scene (cycled over the seeds)")
    c.add_argument("--width", type=int, default=128)
    c.add_argument("--height", type=int, default=96)
    c.add_argument("--max-cands", type=int, default=60)
    c.add_argument("--full", action="store_true", help="the fast preset instead of --quick")
    c.add_argument("--recon-cache", type=Path, default=None)
    c.add_argument("--out", type=Path, required=True, help="JSONL (appended)")
    sm = sub.add_parser("summary", help="Spearman per score over fidelity.py --out files "
                                         "(records), per scene file and pooled; select rows")
    sm.add_argument("files", nargs="+", type=Path)
    f = sub.add_parser("fit")
    f.add_argument("train", nargs="+", type=Path)
    f.add_argument("--test", nargs="*", type=Path, default=[])
    a = ap.parse_args(argv)

    if a.cmd == "collect":
        cfg = build_config("fast", quick=not a.full)
        with tempfile.TemporaryDirectory(prefix="fit-trust-") as tmp:
            for k, s in enumerate(a.seeds):
                rows = collect_seed(s, cfg, a.views[k % len(a.views)], a.width, a.height,
                                    a.max_cands, Path(tmp), a.recon_cache)
                with a.out.open("a") as fh:
                    for r in rows:
                        fh.write(json.dumps({k2: (None if isinstance(v, float) and math.isnan(v)
                                                  else (str(v) if isinstance(v, float)
                                                        and math.isinf(v) else v))
                                             for k2, v in r.items()}) + "\n")
        return 0

    if a.cmd == "summary":
        return summary(a.files)

    rows = load_rows(a.train)
    X, y, groups = design(rows)
    print(f"# train: {len(y)} renders from {len(np.unique(groups))} scenes")
    cv = {al: cv_predictions(X, y, groups, al) for al in ALPHAS}
    print("\n## leave-one-scene-out CV")
    for al, p in cv.items():
        print(f"alpha {al:>6}: spearman {_spearman(p, y):.3f}, MAE "
              f"{np.mean(np.abs(p - y)):.2f} dB")
    alpha = min(ALPHAS, key=lambda al: np.mean(np.abs(cv[al] - y)))
    mean, scale, coef, b = ridge(X, y, alpha)
    model = lambda Z: predict_psnr(Z, mean, scale, coef, b)  # noqa: E731
    _table(f"train (alpha {alpha}, in-sample)", rows, X, y, model)
    if a.test:
        trows = load_rows(a.test)
        Xt, yt, gt = design(trows)
        _table(f"test: {len(np.unique(gt))} unseen scenes", trows, Xt, yt, model)
        for g in np.unique(gt):
            m = gt == g
            p = model(Xt[m])
            print(f"  {g:<24} n {m.sum():>3}  spearman {_spearman(p, yt[m]):.3f}  MAE "
                  f"{np.mean(np.abs(p - yt[m])):.2f} dB")
    np.set_printoptions(precision=6, floatmode="maxprec", suppress=True, linewidth=96)
    print("\n# constants for freescale_core/freeviews/trust.py")
    print(f"_MEAN = np.array({np.array2string(mean, separator=', ')})")
    print(f"_SCALE = np.array({np.array2string(scale, separator=', ')})")
    print(f"_COEF = np.array({np.array2string(coef, separator=', ')})")
    print(f"_INTERCEPT = {b:.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
