"""The ``refine-3dgs`` flow: per scene of a published store, train 3D Gaussians on the
captured views with and without free views as pseudo ground truth, and compare them on the
held-out views (METHOD.md "Downstream uses"; docs/REFINE.md).

The store must be made with ``--set recon_split=ood`` (free views from a reconstruction of the
first 70% of the capture; the last 30% published as ``heldout`` rows). All work is in
``freescale_core.downstream.refine``; this flow only orders one task per scene. Results go
beside each scene version (``STORE/scenes/<id>/refine/<version>/<config hash>/<arm>/seed<k>/``,
written atomically); re-running computes only the arms that are not there yet.
"""

from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact

from schemas.refine import RefineConfig


@task(name="refine-scene")
def refine_scene_task(store: str, scene_id: str, cfg: RefineConfig) -> dict:
    from freescale_core.downstream.refine import refine_scene
    from freescale_core.store.reader import FreeViewSet

    return refine_scene(FreeViewSet.open(store, scene_id), cfg, log=print)


def format_table(summaries: list[dict]) -> str:
    """Markdown table: one row per scene and refined arm; baseline and arm PSNR/SSIM are means
    over the seeds both have, dPSNR (std) the mean (spread) of the per-seed differences."""
    lines = ["| scene | arm | seeds | free views added | baseline PSNR | arm PSNR | dPSNR (std) "
             "| baseline SSIM | dSSIM | overhead | off-path dPSNR | d vs baseline+time (std) "
             "| post PSNR |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        rows = s["summary"]
        b = rows.get("baseline")
        for arm, r in rows.items():
            if arm == "baseline" or b is None or "dpsnr" not in r:
                continue
            off = f"{r['doffpath_psnr']:+.2f}" if "doffpath_psnr" in r else ""
            lines.append(
                f"| {s['scene']} | {arm} | {len(r['seeds'])} | {r['n_added']:.0f} | "
                f"{r.get('base_psnr', b['psnr']):.2f} | {r.get('arm_psnr', r['psnr']):.2f} | "
                f"{r['dpsnr']:+.2f} ({r['dpsnr_std']:.2f}) | "
                f"{r.get('base_ssim', b['ssim']):.3f} | {r['dssim']:+.3f} | "
                f"{100 * r['overhead']:+.0f}% | {off} | "
                + (f"{r['dpsnr_time']:+.2f} ({r['dpsnr_time_std']:.2f})" if "dpsnr_time" in r
                   else "")
                + (f" | {r['post_psnr']:.2f} |" if "post_psnr" in r else " | |"))
    return "\n".join(lines)


@flow(name="refine-3dgs", log_prints=True)
def refine_3dgs(store: str, scenes: list[str] | None = None,
                config: RefineConfig | None = None) -> list[dict]:
    """Refine every (or the named) published scene of ``store`` and compare the arms.

    Args:
        store: a store made with ``recon_split=ood``.
        scenes: scene ids (default: every scene with status ``ok``).
        config: :class:`schemas.refine.RefineConfig` (arms, seeds, budget, schedule, weights).
    Returns:
        One summary per scene (``summary.json`` of its refine folder).
    """
    from freescale_core.store.reader import open_scenes

    cfg = config or RefineConfig()
    log = get_run_logger()
    sets = open_scenes(store, scenes)
    log.info("refine-3dgs: %d scenes, arms %s, seeds %s, %d steps, free views join at %s",
             len(sets), cfg.arm_names(), cfg.seeds, cfg.recon.max_iterations, cfg.schedule())
    out = []
    for fvs in sets:  # one scene at a time: every arm already uses all cores
        from freescale_core.downstream.refine import summarize_scene

        out.append(summarize_scene(refine_scene_task(store, fvs.scene_id, cfg)))
    table = format_table(out)
    print(table)
    try:
        create_markdown_artifact(markdown=f"# refine-3dgs: {store}\n\n{table}",
                                 key="freescale-refine")
    except Exception as e:  # artifacts are a convenience
        log.warning("could not create the artifact: %s", e)
    return out
