"""Downstream gain of a sweep point: 3DGS refinement with its free views (issue 16).

Opt-in (``EvaluateConfig.downstream = ["refine"]``, ``freescale evaluate --downstream
refine``). After a point's ``generate-dataset`` run, :func:`refine_point` runs the project's
refinement comparison (:func:`freescale_core.downstream.refine.refine_scene`, the work of the
``refine-3dgs`` flow; docs/REFINE.md) on the point's store with a small fixed budget: the
real-views-only ``baseline`` arm and one arm with the point's free views (default ``wiou``:
lowest WIoU to the training views first, the paper's order), same seed, same steps, scored on
the same held-out views. Per point:

* ``refine_gain_db`` = held-out PSNR(free-view arm) - held-out PSNR(baseline), mean over the
  seeds; ``refine_base_psnr``, ``refine_fv_psnr`` (the two arms' PSNR, means over the seeds),
  ``refine_gain_std`` (spread over seeds), ``refine_n_added`` (free views that joined),
  ``refine_offpath_gain_db`` (procedural scenes: the same difference at off-path poses
  against the oracle);
* ``refine_cpu_seconds`` / ``refine_wall_seconds`` of the comparison (both arms, the warm-up
  and the scoring), ``refine_steps``, ``refine_arm``, ``refine_long_side`` (the arms' training
  long side: the refinement config's own, the same for every point of a scene, so the arms'
  PSNRs are comparable across points).

Every point of a sweep uses the same refinement config; the result is cached with the point
(``OUT/points/<key>/refine_<hash>.json``; the arms themselves under the point's store, as
``freescale refine`` writes them), so re-running a sweep does not recompute it and adding
``--downstream refine`` to computed points runs only the refinement. A point that failed, has
no free view or no held-out view is not refined: its gain is NaN with ``refine_note``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

from schemas.evaluate import EvaluateConfig
from schemas.pipeline import _deep_merge
from schemas.refine import RefineConfig, refine_recon_config


def refine_config(ecfg: EvaluateConfig) -> RefineConfig:
    """The sweep's refinement comparison: the refine flow's budget (the fast reconstruction
    preset, fixed steps) cut to ``refine_steps`` with its densification schedule scaled, the
    arms ``baseline`` + ``refine_arm``, ``refine_seeds``, then ``refine_overrides``."""
    rc = refine_recon_config()
    n = int(ecfg.refine_steps)
    f = n / rc.max_iterations
    recon = {"max_iterations": n, "min_iterations": n,
             "densify_from": max(1, int(rc.densify_from * f)),
             "densify_until": max(2, int(rc.densify_until * f)),
             "densify_every": max(1, int(rc.densify_every * f)),
             "plateau_window": max(5, int(rc.plateau_window * f))}
    over = _deep_merge({"recon": {**rc.model_dump(mode="json"), **recon},
                        "arms": ["baseline", ecfg.refine_arm], "seeds": list(ecfg.refine_seeds)},
                       ecfg.refine_overrides)
    return RefineConfig.model_validate(over)


def refine_part_name(rcfg: RefineConfig) -> str:
    """File name of a point's cached refinement result under this config."""
    from freescale_core.store.store import config_hash

    from freescale_core.codekey import code_key

    return (f"refine_{config_hash(rcfg.model_dump(mode='json'))[:12]}_"
            f"{code_key(('freescale_core.eval.downstream',))[:12]}.json")


def _nan_row(rcfg: RefineConfig, note: str) -> dict:
    return {"refine_gain_db": math.nan, "refine_base_psnr": math.nan,
            "refine_fv_psnr": math.nan, "refine_gain_std": math.nan, "refine_n_added": math.nan,
            "refine_offpath_gain_db": math.nan, "refine_cpu_seconds": 0.0,
            "refine_wall_seconds": 0.0, "refine_steps": rcfg.recon.max_iterations,
            "refine_arm": rcfg.arm_names()[-1], "refine_long_side": math.nan,
            "refine_note": note}


def refine_point(store: str | Path, scene_id: str, source: str | Path, row: dict,
                 rcfg: RefineConfig, log: Callable[[str], None] = print) -> dict:
    """The refinement comparison on one point's store (see the module doc); ``row`` is the
    point's pipeline row (status, free views), ``source`` the scene folder (oracle)."""
    from freescale_core.downstream.refine import refine_scene, summarize_scene
    from freescale_core.store.reader import FreeViewSet

    if row.get("status") != "ok":
        return _nan_row(rcfg, "point not ok: not refined")
    if not (row.get("n_free_views") or 0) > 0:
        return _nan_row(rcfg, "no free views: not refined")
    if not Path(store).is_dir():
        return _nan_row(rcfg, "the point's store is gone: not refined")
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        out = refine_scene(FreeViewSet.open(store, scene_id), rcfg, source=source, log=log)
    except Exception as e:  # noqa: BLE001 - e.g. no held-out views (recon_split=all)
        return _nan_row(rcfg, f"refinement failed: {type(e).__name__}: {e}"[:300])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    summ = summarize_scene(out)["summary"]
    arm = rcfg.arm_names()[-1]
    r, b = summ.get(arm, {}), summ.get("baseline", {})
    d = _nan_row(rcfg, "")
    seeds = out["arms"].get("baseline", {})
    res = next(iter(seeds.values()), {}).get("train_resolution") if seeds else None
    d.update(refine_gain_db=r.get("dpsnr", math.nan),
             refine_base_psnr=r.get("base_psnr", b.get("psnr", math.nan)),
             refine_fv_psnr=r.get("arm_psnr", r.get("psnr", math.nan)),
             refine_gain_std=r.get("dpsnr_std", math.nan),
             refine_n_added=r.get("n_added", math.nan),
             refine_offpath_gain_db=r.get("doffpath_psnr", math.nan),
             refine_cpu_seconds=cpu, refine_wall_seconds=wall,
             refine_long_side=float(max(res)) if res else math.nan,
             refine_arms_reused=len(out["reused"]))  # arms found on disk: not in the seconds
    log(f"refine {scene_id}: baseline {d['refine_base_psnr']:.2f} dB, {arm} "
        f"{d['refine_fv_psnr']:.2f} dB, gain {d['refine_gain_db']:+.2f} dB "
        f"({cpu:.0f} CPU s)")
    return d
