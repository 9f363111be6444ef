"""The ``make-fixer-pairs`` flow: fixer training pairs for scene folders, one task per scene.

The work is :func:`freescale_core.eval.fixer_pairs.make_scene_pairs` (leave-out reconstructions
rendered at the cameras they never saw, the nearest photos warped in, the held-out photo as
target; docs/FIXER.md). Each scene is a task named ``fixer-pairs[<scene>]``; a scene with bad
input fails alone, the others go on. Folds whose key (config, code, inputs, seed) is unchanged
are kept, so a re-run after a failure makes only what is missing.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task

from schemas.fixer_pairs import PairsConfig


@task(name="fixer-pairs", task_run_name="fixer-pairs[{scene_id}]", retries=0)
def scene_pairs_task(scene: str, out: str, cfg: PairsConfig, seed: int, force: bool,
                     scene_id: str = "") -> list[dict]:
    from freescale_core.eval.fixer_pairs import make_scene_pairs

    log = get_run_logger()
    return make_scene_pairs(scene, out, cfg, seed=seed, force=force, log=log.info)


@flow(name="make-fixer-pairs", log_prints=True)
def make_fixer_pairs(scenes: list[str], out: str, config: PairsConfig | None = None,
                     seed: int = 0, force: bool = False) -> dict:
    """Pairs for each scene folder under ``out/<scene>/<fold>/``.

    Returns:
        ``{"folds": [...], "failed": {scene: error}}``.
    """
    cfg = config or PairsConfig()
    futures = {s: scene_pairs_task.submit(s, out, cfg, seed, force, scene_id=Path(s).name)
               for s in scenes}
    folds, failed = [], {}
    for s, fut in futures.items():
        try:
            folds += fut.result()
        except Exception as e:  # noqa: BLE001 - one scene's failure never stops the others
            failed[s] = str(e).splitlines()[0]
            get_run_logger().error("scene %s: %s", s, failed[s])
    try:
        from prefect.artifacts import create_table_artifact

        create_table_artifact(key="freescale-fixer-pairs", table=[
            {k: r.get(k) for k in ("scene_id", "fold", "kept", "n_pairs", "seconds")}
            for r in folds], description=f"fixer pairs in {out}")
    except Exception:  # noqa: BLE001 - artifacts are a convenience
        pass
    return {"folds": folds, "failed": failed}
