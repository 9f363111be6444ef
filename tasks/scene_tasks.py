"""Prefect tasks, one per pipeline stage. Each is a thin wrapper over ``freescale_core``.

Tasks add only what orchestration needs: retries, store-backed caching (see
:mod:`tasks.stage`), status/timing records and persistence of the stage's output. They pass
small :class:`~tasks.stage.StageRef` records, never big arrays, so the same tasks run in
threads, in Dask worker processes on one machine, or across a cluster sharing the store.
"""

from __future__ import annotations

import pickle
import time
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from freescale_core.store.store import Store, write_bytes_atomic, write_json_atomic
from schemas.pipeline import PipelineConfig

from tasks.progress import StageReporter, recon_progress
from tasks.retry import RETRY_OPTS
from tasks.stage import StageRef, run_stage

# Caching is done by tasks.stage against the store; Prefect's own result cache is off so
# that it can never return a stale result for an output that was deleted from the store.
TASK_OPTS = dict(cache_policy=NO_CACHE, persist_result=False, **RETRY_OPTS)

# The entry points of each stage's ``compute`` (the modules it imports). The checkpoint key
# hashes every project module these reach, transitively (freescale_core.codekey), so no
# module list is typed by hand: an edit anywhere a stage reaches re-runs it and the stages
# after it (their keys hold the upstream keys).
STAGE_ROOTS: dict[str, tuple[str, ...]] = {
    "ingest": ("freescale_core.scene.io", "freescale_core.scene.fingerprint"),
    "reconstruct": ("freescale_core.scene.ply", "freescale_core.scene.ply_alignment",
                    "freescale_core.recon.trainer"),
    "select": ("freescale_core.scene.ply", "freescale_core.select.run"),
    "freeviews": ("freescale_core.scene.ply", "freescale_core.freeviews.run"),
    "publish": ("freescale_core.store.layout", "freescale_core.freeviews.explain"),
}


def code_keys() -> dict:
    """Each stage's code key and the dependency versions in them (recorded in every
    published version's ``config.json``)."""
    from freescale_core.codekey import code_key, dependency_versions

    return {"stages": {s: code_key(r) for s, r in STAGE_ROOTS.items()},
            "dependencies": dependency_versions()}


def _save_pickle(path: Path, obj) -> None:
    write_bytes_atomic(path, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def _load_pickle(path: Path):
    with open(path, "rb") as f:
        return pickle.load(f)


def load_stage_output(store_root: str, ref: StageRef, name: str):
    return _load_pickle(Store(store_root).work_dir(ref.scene_id) / name)


# --------------------------------------------------------------------------- ingest
@task(name="ingest", task_run_name="ingest[{scene_id}]", **TASK_OPTS)
def ingest(store_root: str, scene_id: str, scene_path: str, cfg: PipelineConfig) -> StageRef:
    """Read and pre-filter one scene (COLMAP, transforms.json or images + SfM)."""

    def compute(work: Path):
        from freescale_core.scene.io import load_scene

        scene = load_scene(scene_path, scene_id=scene_id, cache_dir=str(work / "cache"),
                           cfg=cfg.ingest)
        _save_pickle(work / "scene.pkl", scene)
        warn = [str(w) for w in scene.extras.get("warnings", [])]
        for w in warn:  # the Prefect task log; publish puts them in the manifest
            from prefect import get_run_logger

            get_run_logger().warning("scene '%s': %s", scene_id, w)
        return ["scene.pkl"], {
            "warnings": warn,
            "n_images": len(scene), "n_points": int(len(scene.points_xyz)),
            "camera_models": sorted(set(scene.camera_models)),
            "undistorted": bool(scene.undistorted), "format": scene.source_format,
            "masks": scene.extras.get("masks", "none"),  # mask_path, masks/ or none
        }

    from freescale_core.scene.fingerprint import input_fingerprint

    # keyed on the inputs' contents too: an edited image or model re-runs ingest (and so
    # every stage after it), with or without --force
    return run_stage(store_root, scene_id, "ingest", {"path": str(scene_path),
                                                      "inputs": input_fingerprint(scene_path),
                                                      **cfg.ingest.model_dump(mode="json")},
                     [], STAGE_ROOTS["ingest"], cfg.seed, compute)


# --------------------------------------------------------------------------- reconstruct
def user_ply(scene_path: str) -> Path | None:
    """A user-supplied Gaussian PLY in the scene folder, if any (used as is)."""
    root = Path(scene_path)
    def iteration(p: Path) -> int:  # iteration_30000 after iteration_7000 (numeric order)
        try:
            return int(p.parent.name.split("_", 1)[1])
        except (IndexError, ValueError):
            return -1

    its = sorted(root.glob("point_cloud/iteration_*/point_cloud.ply"), key=iteration)
    for cand in [root / "gaussians.ply", *its[-1:]]:
        if cand.is_file():
            return cand
    return None


@task(name="reconstruct", task_run_name="reconstruct[{ingest_ref.scene_id}]", **TASK_OPTS)
def reconstruct(store_root: str, ingest_ref: StageRef, scene_path: str,
                cfg: PipelineConfig) -> StageRef:
    """3D Gaussians for the scene: trained here on the CPU, or the user's own PLY."""
    sid = ingest_ref.scene_id
    given = user_ply(scene_path)

    def compute(work: Path):
        from freescale_core.scene.ply import read_background, read_ply, write_ply

        scene = load_stage_output(store_root, ingest_ref, "scene.pkl")
        if given is not None:
            g = read_ply(given, scene_id=sid)
            g.validate(sid, str(given))
            from freescale_core.scene.ply_alignment import check_alignment

            # a PLY in another frame (normalised world) would give 0 free views silently
            al = check_alignment(g, scene, given, background=cfg.recon.background,
                                 backend=cfg.recon.raster_backend)
            stats = {"n_gaussians": len(g), "recon_source": f"user PLY {given.name}",
                     "user_ply_psnr": round(al["psnr_median"], 2)}
        else:
            from freescale_core.recon.trainer import evaluate, reconstruct as train

            train_idx, test_idx = scene.split(cfg.recon_split)
            rep, cb = recon_progress(store_root, sid, cfg.recon)
            res = train(scene, cfg.recon, seed=cfg.seed, train_idx=train_idx, progress=cb)
            rep.finish()
            g = res.gaussians
            g.validate(sid)
            stats = dict(res.stats)
            stats["recon_source"] = "trained"
            stats["recon_split"] = cfg.recon_split  # "all": no held-out view, no test PSNR
            if len(test_idx):
                # at the training resolution and background, as the benchmark does
                ev = evaluate(g, scene, test_idx, scale=stats["train_scale"],
                              background=res.background,
                              backend=cfg.recon.raster_backend)
                stats["recon_test_psnr"] = float(ev["psnr_mean"])
                stats["recon_test_ssim"] = float(ev["ssim_mean"])
                stats["recon_test_on_masks"] = bool(ev.get("masked", False))  # object pixels
                stats["recon_test_views"] = {  # per held-out view, to the manifest as JSON
                    "views": [scene.image_names[i] for i in ev["views"]],
                    "psnr": [round(float(x), 3) for x in ev["psnr"]],
                    "ssim": [round(float(x), 4) for x in ev["ssim"]]}
        write_ply(work / "gaussians.ply", g, background=(  # its training colour, with it
            read_background(given, cfg.recon.background, sid) if given else res.background))
        return ["gaussians.ply"], stats

    ply_key = ({"user_ply": str(given), "mtime": given.stat().st_mtime,
                "size": given.stat().st_size} if given else {})
    return run_stage(store_root, sid, "reconstruct",
                     {"recon": cfg.recon.model_dump(mode="json"), "split": cfg.recon_split, **ply_key},
                     [ingest_ref], STAGE_ROOTS["reconstruct"], cfg.seed, compute)


# --------------------------------------------------------------------------- select
@task(name="select", task_run_name="select[{ingest_ref.scene_id}]", **TASK_OPTS)
def select(store_root: str, ingest_ref: StageRef, recon_ref: StageRef,
                 cfg: PipelineConfig) -> StageRef:
    """Certainty grid, candidate placement, feasibility, view graph and NMS (stages 2-6)."""
    sid = ingest_ref.scene_id

    def compute(work: Path):
        from freescale_core.scene.ply import read_ply
        from freescale_core.select.run import run_selection

        scene, _ = load_stage_output(store_root, ingest_ref, "scene.pkl").views_for(
            cfg.recon_split)
        g = read_ply(work / "gaussians.ply", scene_id=sid)
        sel = run_selection(g, scene.cameras, cfg.select, seed=cfg.seed, scene_id=sid,
                            capture_order=scene.capture_order, points=scene.points_xyz,
                            train_masks=scene.load_mask if scene.has_masks else None)
        _save_pickle(work / "selection.pkl", sel)
        result = {k: v for k, v in sel.counts.items()}
        result["grid_R"] = int(sel.grid.R)
        result["grid_R_adaptive"] = int(getattr(sel, "R_adaptive", sel.grid.R))
        result["timings"] = dict(sel.timings)
        return ["selection.pkl"], result

    return run_stage(store_root, sid, "select", cfg.select, [ingest_ref, recon_ref],
                     STAGE_ROOTS["select"], cfg.seed, compute)


# --------------------------------------------------------------------------- freeviews
@task(name="freeviews", task_run_name="freeviews[{ingest_ref.scene_id}]", **TASK_OPTS)
def freeviews(store_root: str, ingest_ref: StageRef, recon_ref: StageRef, select_ref: StageRef,
               scene_path: str, cfg: PipelineConfig) -> StageRef:
    """Render selected cameras, quality filter, pose + image rectification (stages 7-10)."""
    sid = ingest_ref.scene_id

    def compute(work: Path):
        from freescale_core.freeviews.run import run_free_view_stage

        scene, _ = load_stage_output(store_root, ingest_ref, "scene.pkl").views_for(
            cfg.recon_split)
        sel = load_stage_output(store_root, select_ref, "selection.pkl")
        from freescale_core.scene.ply import read_background, read_ply

        g = read_ply(work / "gaussians.ply", scene_id=sid)
        background = read_background(work / "gaussians.ply", cfg.recon.background, sid)
        fv = run_free_view_stage(scene, g, sel, cfg.freeview, seed=cfg.seed, scene_path=scene_path,
                                 train_scale=float(recon_ref.result.get("train_scale", 1.0)),
                                 background=background,
                                 backend=cfg.recon.raster_backend,
                                 progress=StageReporter(store_root, sid, "freeviews", None,
                                                        "views"))
        _save_pickle(work / "freeviews.pkl", fv)
        return ["freeviews.pkl"], dict(fv.counts)

    return run_stage(store_root, sid, "freeviews", cfg.freeview, [ingest_ref, recon_ref, select_ref],
                     STAGE_ROOTS["freeviews"], cfg.seed, compute)


# --------------------------------------------------------------------------- publish
@task(name="publish", task_run_name="publish[{ingest_ref.scene_id}]", **TASK_OPTS)
def publish(store_root: str, ingest_ref: StageRef, recon_ref: StageRef, select_ref: StageRef,
            fv_ref: StageRef | None, cfg: PipelineConfig, config_hash: str, source: str) -> dict:
    """Write views.parquet, view_graph.parquet, arrays.zarr and pictures as one new version."""
    from freescale_core.store.layout import write_scene_outputs
    from tasks.stage import NOOP_STAGES

    store = Store(store_root)
    sid = ingest_ref.scene_id
    if NOOP_STAGES:  # the orchestration benchmark's no-op mode (tasks/stage.py)
        store.update_status(sid, status="ok", error="", stage="done", config_hash=config_hash,
                            source=source)
        return {"scene_id": sid, "status": "ok"}
    work = store.work_dir(sid)
    scene, heldout = _load_pickle(work / "scene.pkl").views_for(cfg.recon_split)
    sel = _load_pickle(work / "selection.pkl")
    fv = _load_pickle(work / "freeviews.pkl") if fv_ref is not None else None
    store.update_status(sid, status="running", stage="publish")
    t0 = time.perf_counter()
    try:
        with store.publish(sid) as out:
            counts = write_scene_outputs(out, scene, sel, fv, work / "gaussians.ply", cfg.freeview,
                                         heldout=heldout)
            # the resolved config of this version (FreeViewSet.config(),
            # `freescale scenes show STORE SCENE --config`)
            write_json_atomic(out / "config.json", {"config_hash": config_hash,
                                                    "config": cfg.model_dump(mode="json"),
                                                    "code": code_keys()})
    except BaseException as e:
        from tasks.stage import mark_failed

        mark_failed(store, sid, "publish", e)
        raise
    # Scalars and the "why this size" reasons go to the manifest; histories stay in _work.
    info = {k: v for k, v in recon_ref.result.items()
            if not k.startswith("n_") and (isinstance(v, (int, float, str, bool))
                                           or k in ("reasons", "train_resolution",
                                                    "recon_test_views"))}
    info["scarce"] = bool(fv_ref.result.get("scarce", False)) if fv_ref is not None else False
    from freescale_core.freeviews.explain import empty_reason

    info["ingest_warnings"] = "; ".join(ingest_ref.result.get("warnings", []))

    # "" when the scene has free views; else which stage removed them, with the numbers
    info["empty_reason"] = empty_reason(sel.counts, fv) if not counts.get("n_free_views") else ""
    st = store.update_status(sid, status="ok", error="", error_type="", stage="done",
                             config_hash=config_hash, source=source, counts=counts,
                             version=store.current_version_dir(sid).name, info=info)
    from tasks.artifacts import publish_scene_artifact
    from tasks.progress import run_logger

    run_logger().info("%s: publish done in %.1f s (%s, %d free views, figures in %s)", sid,
                      time.perf_counter() - t0, st["version"], counts.get("n_free_views", 0),
                      store.current_version_dir(sid))
    publish_scene_artifact(store, sid)
    return {"scene_id": sid, "status": st["status"]}
