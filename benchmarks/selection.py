"""Benchmark of the selection core (METHOD.md stages 2-6): seconds per stage and peak memory.

Rows (each in its own subprocess, so peak memory is per row):

* ``room-2k-R128``: synthetic room, 300k Gaussians on surfaces (walls, floor, ceiling,
  furniture; flat anisotropic Gaussians, 2% large faint floaters), 200 training cameras on a
  walk through the room, 2,000 candidates (paper settings), R = 128. Target: <= 1.5 s total,
  < 1 GB peak on 2 cores.
* ``room-10k-R128``: the same with 10,000 candidates (50 trajectories per mode).
* ``room-2k-R64`` / ``room-2k-R256``: other grid resolutions.
* ``real-<scene>``: a real scene from ../shared/datasets, Gaussians = COLMAP sparse points
  (``Gaussians.from_points``), paper settings.

Timings: the best of ``--repeat`` runs after one warm-up run (numba kernels are compiled and
cached on first use; the warm-up's wall time is reported as ``first_call_seconds``). Peak
memory is the subprocess's ``ru_maxrss`` (whole process, including Python, numpy, numba).

``--overlap`` instead measures which visibility rule predicts real overlap better on the real
scenes: Spearman correlation, over all training pairs, between graph WIoU and the fraction
of SIFT matches between the two photos that agree with the known epipolar geometry.

    python -m benchmarks.selection            # table
    python -m benchmarks.selection --json     # one JSON object per row
    python -m benchmarks.selection --overlap  # frustum vs occlusion on real scenes
"""

from __future__ import annotations

import os
import sys

import argparse
import json
import resource
import subprocess
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from freescale_core.geometry.cameras import (Cameras, colmap_to_cam_from_world, invert_pose,
                                    look_at)
from freescale_core.scene.gaussians import Gaussians

DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))
REAL = ["kermit", "buddha", "llff_fern", "strecha_fountain-P11", "dtu_scan24"]
STAGES = ["grid", "candidates", "feasibility", "visibility", "nms", "graph", "total"]


# ---------------------------------------------------------------------- scenes
def synthetic_room(n_gaussians: int = 300_000, n_train: int = 200,
                   seed: int = 0) -> tuple[Gaussians, Cameras]:
    """A furnished room 10 x 8 x 3 m (z up) with Gaussians on its surfaces and a camera walk.

    Surfaces: floor, ceiling, 4 walls, a table (top + 4 legs), 6 boxes, 3 spheres; points are
    spread by area, Gaussians are flat (tangent sigma ~ 1-4 cm, normal sigma ~ 3 mm) with
    mostly high opacity; 2% are large faint floaters anywhere in the room.
    """
    rng = np.random.default_rng(seed)
    quads = []  # (origin, edge u, edge v)

    def box(lo, hi):
        lo, hi = np.array(lo, float), np.array(hi, float)
        d = hi - lo
        ex, ey, ez = np.array([d[0], 0, 0]), np.array([0, d[1], 0]), np.array([0, 0, d[2]])
        quads.extend([(lo, ex, ey), (lo + ez, ex, ey), (lo, ex, ez), (lo + ey, ex, ez),
                      (lo, ey, ez), (lo + ex, ey, ez)])

    box([-5, -4, 0], [5, 4, 3])  # the room
    box([-1, -0.6, 0.72], [1, 0.6, 0.78])  # table top
    for sx in (-0.9, 0.85):
        for sy in (-0.5, 0.45):
            box([sx, sy, 0], [sx + 0.05, sy + 0.05, 0.72])
    for _ in range(6):
        c = rng.uniform([-4, -3, 0], [4, 3, 0])
        s = rng.uniform([0.3, 0.3, 0.3], [1.2, 1.0, 1.5])
        box(c - s * [0.5, 0.5, 0], c + s * [0.5, 0.5, 1])
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in quads])
    spheres = [(rng.uniform([-3, -2, 0.5], [3, 2, 1.5]), rng.uniform(0.2, 0.5)) for _ in range(3)]
    s_areas = np.array([4 * np.pi * r * r for _, r in spheres])
    n_float = int(0.02 * n_gaussians)
    n_surf = n_gaussians - n_float
    w = np.concatenate([areas, s_areas])
    counts = rng.multinomial(n_surf, w / w.sum())
    pts, nrm = [], []
    for (o, u, v), n in zip(quads, counts[:len(quads)]):
        a, b = rng.random((n, 1)), rng.random((n, 1))
        pts.append(o + a * u + b * v)
        nn = np.cross(u, v)
        nrm.append(np.tile(nn / np.linalg.norm(nn), (n, 1)))
    for (c, r), n in zip(spheres, counts[len(quads):]):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts.append(c + r * d)
        nrm.append(d)
    P = np.concatenate(pts)
    Nn = np.concatenate(nrm)
    P = P + Nn * rng.normal(0, 0.004, size=(len(P), 1))
    log_s = np.log(np.stack([rng.lognormal(np.log(0.02), 0.4, len(P)),
                             rng.lognormal(np.log(0.02), 0.4, len(P)),
                             np.full(len(P), 0.003)], axis=1))
    # rotate (1,0,0),(0,1,0),(0,0,1) -> tangent, tangent, normal: quaternion from the normal
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, Nn)
    s = np.linalg.norm(axis, axis=1)
    ang = np.arctan2(s, Nn @ z)
    axis = np.where(s[:, None] > 1e-9, axis / np.maximum(s, 1e-12)[:, None], [1.0, 0, 0])
    q = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], axis=1)
    logit = rng.normal(2.0, 1.5, len(P))
    F = rng.uniform([-5, -4, 0], [5, 4, 3], size=(n_float, 3))
    means = np.concatenate([P, F])
    log_scales = np.concatenate([log_s, np.log(rng.uniform(0.05, 0.2, (n_float, 3)))])
    quats = np.concatenate([q, np.tile([1.0, 0, 0, 0], (n_float, 1))])
    logits = np.concatenate([logit, rng.normal(-2.0, 1.0, n_float)])
    sh = np.zeros((len(means), 1, 3), np.float32)
    g = Gaussians(means, log_scales, quats, logits, sh)
    # training cameras: a walk on an ellipse at eye height, looking inward with jitter
    t = np.linspace(0, 2 * np.pi, n_train, endpoint=False)
    eye = np.stack([3.2 * np.cos(t), 2.4 * np.sin(t), 1.6 + 0.1 * np.sin(5 * t)], axis=1)
    tgt = np.stack([0.8 * np.cos(t + 1.0), 0.6 * np.sin(t + 1.0), np.full(n_train, 0.9)], axis=1)
    tgt += rng.normal(0, 0.3, tgt.shape)
    cams = Cameras(look_at(eye, tgt, [0, 0, 1]), 600.0, 600.0, 480.0, 270.0, 960, 540)
    return g, cams


def load_real(name: str, root: Path = DATASETS):
    """``(Gaussians from the sparse points, cameras (distortion ignored), reconstruction)``."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(root / name / "sparse" / "0"))
    ids = sorted(rec.images, key=lambda i: rec.images[i].name)
    T, fx, fy, cx, cy, W, H = [], [], [], [], [], [], []
    for i in ids:
        im = rec.images[i]
        cam = rec.cameras[im.camera_id]
        r = im.cam_from_world()
        q = np.asarray(r.rotation.quat)  # xyzw
        cfw = colmap_to_cam_from_world(np.r_[q[3], q[:3]], np.asarray(r.translation))
        T.append(invert_pose(cfw))
        K = cam.calibration_matrix()
        fx.append(K[0, 0]); fy.append(K[1, 1]); cx.append(K[0, 2]); cy.append(K[1, 2])
        W.append(cam.width); H.append(cam.height)
    cams = Cameras(np.stack(T), fx, fy, cx, cy, W, H)
    pts = np.array([p.xyz for p in rec.points3D.values()])
    rgb = np.array([p.color for p in rec.points3D.values()]) / 255.0
    return Gaussians.from_points(pts, rgb), cams, rec, ids


# ---------------------------------------------------------------------- one row
def row_config(row: str):
    from schemas.select import SelectConfig

    cfg = SelectConfig()
    if "-10k" in row:
        cfg.candidates.n_traj = 50
    for R in (64, 256):
        if row.endswith(f"-R{R}"):
            cfg.grid.resolution = R
    return cfg


def run_row(row: str, repeat: int, visibility: str) -> dict:
    from freescale_core.select.run import run_selection

    t0 = time.perf_counter()
    if row.startswith("real-"):
        g, cams, _, _ = load_real(row[5:])
    else:
        g, cams = synthetic_room()
    t_scene = time.perf_counter() - t0
    cfg = row_config(row)
    cfg.visibility.mode = visibility
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    res = run_selection(g, cams, cfg, seed=0, scene_id=row)
    first = time.perf_counter() - t0
    best, best_cpu = None, None
    for _ in range(repeat):
        c0 = time.process_time()
        r = run_selection(g, cams, cfg, seed=0, scene_id=row)
        cpu = time.process_time() - c0
        if best is None or r.timings["total"] < best.timings["total"]:
            best, best_cpu = r, cpu
    c = best.counts
    return {
        "row": row, "n_gaussians": len(g), "n_train": len(cams), "n_candidates": c["n_candidates"],
        "n_feasible": c["n_feasible"], "n_selected": c["n_selected"], "R": best.grid.R,
        "R_adaptive": best.R_adaptive, "n_voxels": c["n_voxels_nonempty"],
        "n_edges": c["n_edges"], "visibility": visibility,
        **{f"{s}_seconds": round(best.timings.get(s, 0.0), 4) for s in STAGES},
        "cpu_seconds": round(best_cpu, 3), "load_avg_1min": round(os.getloadavg()[0], 2),
        "threads": {k: os.environ.get(k, "")
                    for k in ("OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")},
        **{k: v for k, v in best.counts.items() if k.startswith("nms_")},
        "first_call_seconds": round(first, 3), "scene_build_seconds": round(t_scene, 3),
        "rss_before_mb": round(rss_before, 1),
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "same_result_as_first": bool(np.array_equal(best.selected, res.selected)),
    }


# ---------------------------------------------------------------------- overlap study
def _sift_overlap(name: str, rec, ids, cams: Cameras, max_epi_px: float = 2.0) -> np.ndarray:
    """``[T, T]`` fraction of ratio-test SIFT matches consistent with the known epipolar
    geometry (symmetric epipolar distance < max_epi_px, after undistortion), divided by the
    smaller keypoint count."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=2000)
    kps, descs = [], []
    for i in ids:
        im = rec.images[i]
        cam = rec.cameras[im.camera_id]
        img = cv2.imread(str(DATASETS / name / "images" / im.name), cv2.IMREAD_GRAYSCALE)
        kp, d = sift.detectAndCompute(img, None)
        xy = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
        # pixel -> normalised camera coordinates with the model's distortion removed
        if len(xy):
            nxy = np.array(cam.cam_from_img(xy))
        else:
            nxy = np.zeros((0, 2))
        kps.append(nxy)
        descs.append(d if d is not None else np.zeros((0, 128), np.float32))
    T = len(ids)
    cfw = cams.cam_from_world
    f = float(np.median(cams.fx))
    bf = cv2.BFMatcher(cv2.NORM_L2)
    out = np.zeros((T, T))
    for a in range(T):
        for b in range(a + 1, T):
            if len(descs[a]) < 2 or len(descs[b]) < 2:
                continue
            m = bf.knnMatch(descs[a], descs[b], k=2)
            good = [p[0] for p in m if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
            if not good:
                continue
            xa = kps[a][[g.queryIdx for g in good]]
            xb = kps[b][[g.trainIdx for g in good]]
            rel = cfw[b] @ np.linalg.inv(cfw[a])  # cam_b <- cam_a
            Rr, tr = rel[:3, :3], rel[:3, 3]
            tx = np.array([[0, -tr[2], tr[1]], [tr[2], 0, -tr[0]], [-tr[1], tr[0], 0]])
            E = tx @ Rr
            ha = np.c_[xa, np.ones(len(xa))]
            hb = np.c_[xb, np.ones(len(xb))]
            la = ha @ E.T  # epipolar lines in b
            lb = hb @ E  # epipolar lines in a
            num = np.abs(np.sum(hb * la, axis=1))
            d1 = num / np.maximum(np.hypot(la[:, 0], la[:, 1]), 1e-12)
            d2 = num / np.maximum(np.hypot(lb[:, 0], lb[:, 1]), 1e-12)
            inl = np.sum(np.maximum(d1, d2) * f < max_epi_px)
            out[a, b] = out[b, a] = inl / max(1, min(len(kps[a]), len(kps[b])))
    return out


def overlap_study(Rs: list[int]) -> list[dict]:
    from scipy.stats import spearmanr

    from freescale_core.select.certainty import build_certainty_grid
    from freescale_core.select.view_graph import wiou_matrix
    from freescale_core.select.visibility import compute_visibility
    from schemas.select import GridConfig, VisibilityConfig

    rows = []
    for name in REAL:
        if not (DATASETS / name / "sparse" / "0").is_dir():
            print(f"skip {name}: not found under {DATASETS}", file=sys.stderr)
            continue
        g, cams, rec, ids = load_real(name)
        gt = _sift_overlap(name, rec, ids, cams)
        iu = np.triu_indices(len(cams), 1)
        for R in Rs:
            grid, _, _ = build_certainty_grid(g, GridConfig(resolution=R))
            row = {"scene": name, "n_train": len(cams), "n_pairs": len(iu[0]), "R": R,
                   "n_voxels": int(np.count_nonzero(grid.values))}
            for mode in ("frustum", "occlusion"):
                vis = compute_visibility(cams, grid, VisibilityConfig(mode=mode))
                W = wiou_matrix(vis, np.arange(len(cams)), np.float64)
                rho = spearmanr(W[iu], gt[iu]).statistic
                row[f"spearman_{mode}"] = round(float(rho), 3)
            rows.append(row)
    for R in Rs:
        rr = [r for r in rows if r["R"] == R]
        if rr:
            rows.append({"scene": "mean", "n_train": 0, "n_pairs": sum(r["n_pairs"] for r in rr),
                         "R": R, "n_voxels": 0,
                         **{f"spearman_{m}":
                            round(float(np.mean([r[f"spearman_{m}"] for r in rr])), 3)
                            for m in ("frustum", "occlusion")}})
    return rows


# ---------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--rows", default="room-2k-R128,room-10k-R128,room-2k-R64,room-2k-R256,"
                    "real-strecha_fountain-P11", help="comma-separated rows")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--visibility", default="frustum", choices=["frustum", "occlusion"])
    ap.add_argument("--overlap", action="store_true", help="frustum vs occlusion study")
    ap.add_argument("--overlap-R", default="64,128,256", help="grid resolutions, comma-separated")
    ap.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._child:
        print(json.dumps(run_row(a._child, a.repeat, a.visibility)))
        return
    if a.overlap:
        rows = overlap_study([int(x) for x in a.overlap_R.split(",")])
        for r in rows:
            print(json.dumps(r) if a.json else
                  f"{r['scene']:22s} R={r['R']:3d} T={r['n_train']:3d} pairs={r['n_pairs']:5d} "
                  f"voxels={r['n_voxels']:6d}  spearman frustum={r['spearman_frustum']:+.3f} "
                  f"occlusion={r['spearman_occlusion']:+.3f}")
        return
    results = []
    for row in a.rows.split(","):
        p = subprocess.run([sys.executable, "-m", "benchmarks.selection", "--_child", row,
                            "--repeat", str(a.repeat), "--visibility", a.visibility],
                           capture_output=True, text=True, cwd=REPO)
        if p.returncode != 0:
            print(f"row {row} failed:\n{p.stderr}", file=sys.stderr)
            continue
        r = json.loads(p.stdout.strip().splitlines()[-1])
        results.append(r)
        if a.json:
            print(json.dumps(r), flush=True)
    if not a.json:
        hdr = (f"{'row':28s} {'gauss':>7s} {'cand':>6s} {'R':>4s} {'vox':>7s} {'sel':>4s} "
               + " ".join(f"{s[:6]:>7s}" for s in STAGES)
               + f" {'cpu':>6s} {'peakMB':>7s} {'1st':>6s} {'load':>5s}")
        print(hdr)
        for r in results:
            print(f"{r['row']:28s} {r['n_gaussians']:7d} {r['n_candidates']:6d} {r['R']:4d} "
                  f"{r['n_voxels']:7d} {r['n_selected']:4d} "
                  + " ".join(f"{r[s + '_seconds']:7.3f}" for s in STAGES)
                  + f" {r['cpu_seconds']:6.2f} {r['peak_mb']:7.0f} {r['first_call_seconds']:6.2f}"
                  f" {r['load_avg_1min']:5.2f}")


if __name__ == "__main__":
    main()
