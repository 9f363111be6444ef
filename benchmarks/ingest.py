"""Benchmark of scene ingestion: ``inspect_scene`` and ``load_scene`` on the shared real scenes.

Per scene: ``inspect`` (model only), ``load cold`` (empty cache: undistortion of distorted
scenes, every image decoded once), ``load warm`` (cache reused; images still decoded once for
the pre-filter), ``warm nocheck`` (``check_images=False``: headers only). Times are the best of
``--repeat`` runs (cold: each repeat uses a fresh cache folder). Imports are warmed first.
``--sfm`` adds SfM on N images of strecha_fountain-P11 (cold and cached).

    python -m benchmarks.ingest            # table
    python -m benchmarks.ingest --json     # one JSON object per row
    python -m benchmarks.ingest --sfm 8
"""

from __future__ import annotations

import os

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from freescale_core.scene.describe import inspect_scene
from freescale_core.scene.io import load_scene
from schemas.ingest import IngestConfig

DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))
REAL = ["kermit", "buddha", "llff_fern", "strecha_fountain-P11", "dtu_scan24"]


def best(fn, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts)


def bench_scene(name: str, repeat: int) -> dict:
    d = DATASETS / name
    tmp = Path(tempfile.mkdtemp(prefix="fs_bench_"))
    try:
        t_inspect = best(lambda: inspect_scene(d), repeat)
        colds = []
        for r in range(repeat):
            t = time.perf_counter()
            s = load_scene(d, cache_dir=tmp / f"cold{r}")
            colds.append(time.perf_counter() - t)
        warm = best(lambda: load_scene(d, cache_dir=tmp / "cold0"), repeat)
        nocheck = best(lambda: load_scene(d, cache_dir=tmp / "cold0",
                                          cfg=IngestConfig(check_images=False)), repeat)
        return {"scene": name, "n_images": len(s), "model": s.camera_models[0],
                "undistorted": s.undistorted, "inspect_s": t_inspect, "load_cold_s": min(colds),
                "load_warm_s": warm, "warm_nocheck_s": nocheck}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench_sfm(n: int) -> dict:
    src = DATASETS / "strecha_fountain-P11" / "images"
    tmp = Path(tempfile.mkdtemp(prefix="fs_bench_sfm_"))
    try:
        folder = tmp / "imgs"
        folder.mkdir()
        for p in sorted(src.iterdir())[:n]:
            shutil.copy(p, folder / p.name)
        t = time.perf_counter()
        s = load_scene(folder, cache_dir=tmp / "cache")
        cold = time.perf_counter() - t
        t = time.perf_counter()
        load_scene(folder, cache_dir=tmp / "cache")
        warm = time.perf_counter() - t
        return {"scene": f"sfm-fountain-{n}", "n_images": n, "model": s.camera_models[0],
                "undistorted": s.undistorted, "n_registered": s.extras["n_registered"],
                "load_cold_s": cold, "load_warm_s": warm}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sfm", type=int, default=0, help="also time SfM on N fountain images")
    ap.add_argument("--scenes", nargs="*", default=REAL)
    a = ap.parse_args()
    load_scene(DATASETS / "buddha")  # warm imports (pycolmap, cv2)
    rows = [bench_scene(s, a.repeat) for s in a.scenes if (DATASETS / s).is_dir()]
    if a.sfm:
        rows.append(bench_sfm(a.sfm))
    if a.json:
        for r in rows:
            print(json.dumps(r))
        return
    cols = ["scene", "n_images", "model", "inspect_s", "load_cold_s", "load_warm_s",
            "warm_nocheck_s"]
    print(" | ".join(f"{c:>20}" if i == 0 else f"{c:>14}" for i, c in enumerate(cols)))
    for r in rows:
        cells = []
        for i, c in enumerate(cols):
            v = r.get(c, "")
            v = f"{v:.3f}" if isinstance(v, float) else str(v)
            cells.append(f"{v:>20}" if i == 0 else f"{v:>14}")
        print(" | ".join(cells))


if __name__ == "__main__":
    main()
