"""The ``evaluate-engine`` flow: speed against accuracy over named knobs and scenes (issue 16;
docs/EVALUATION.md).

All work is in ``freescale_core.eval.sweep``; this flow hands it the pipeline: every point is
one ``generate-dataset`` run (the flow ``freescale run`` uses) of one scene into the point's own
store under ``OUT/points/<key>/store``, one point at a time (each run already uses every
core, and per-stage CPU seconds and peak memory are only the point's own that way). Points
are cached by key (scene fingerprint, resolved config, code version): a re-run computes only
new points. Results: ``OUT/results.parquet``, ``OUT/results.csv``, ``OUT/pareto*.png`` (+
``.json`` sidecars), ``OUT/tables.md``, and two Prefect artifacts (a table of the points, a
markdown summary with the chart inlined).
"""

from __future__ import annotations

import base64
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from schemas.evaluate import EvaluateConfig
from schemas.pipeline import PipelineConfig


def run_point_with_flow(scene: Path, store: Path, cfg: PipelineConfig) -> None:
    """One point: ``generate-dataset`` on one scene into ``store`` (failures stay in the
    store's status; the evaluation scores them as failed)."""
    from flows.generate_dataset import generate_dataset

    generate_dataset(scenes=[str(scene)], store=str(store), config=cfg, n_workers=1,
                     return_state=True)


def summary_markdown(res, out: Path, skipped: list[str]) -> str:
    from freescale_core.eval.scenes import describe
    from freescale_core.eval.tables import (downstream_table, points_table, sizing_table,
                                            stability_table)

    md = [f"# evaluate-engine: {out}", "",
          f"{len(res.rows)} points: {len(res.computed)} computed, {len(res.cached)} from the "
          "cache.", ""]
    if skipped:
        md += ["Skipped scenes:", ""] + [f"- {s}" for s in skipped] + [""]
    md += ["## Points", "", "Held-out PSNR: every point scored at the same size per scene "
           "(long side <= `eval_long_side`, the `eval_width` x `eval_height` columns), "
           "whatever its training resolution.", "", points_table(res.rows), ""]
    if any("refine_gain_db" in r for r in res.rows):
        md += ["## Downstream: 3DGS refinement with vs without the free views", "",
               "Same seed and steps for both arms; held-out PSNR at the refinement's own "
               "training size (the same for every point of a scene).", "",
               downstream_table(res.rows), ""]
    if any(r["group"] == "sizing" for r in res.rows):
        md += ["## Sizing (adaptive vs half vs double)", "", sizing_table(res.rows), ""]
    base = [r for r in res.rows if r["group"] == "base"]
    if base:
        def how(name):
            try:
                return describe(name)
            except KeyError:
                return "real scene"

        md += ["## Stability (base point per scene)", "", stability_table(base, how), ""]
    return "\n".join(md)


@flow(name="evaluate-engine", log_prints=True)
def evaluate_engine(scenes: list[str], out: str = "data/eval",
                    config: EvaluateConfig | None = None) -> dict:
    """Sweep ``config``'s knobs over ``scenes`` and chart seconds per scene against accuracy.

    Args:
        scenes: scene folders, ``proc:NAME`` (procedural, with an exact oracle; groups
            ``proc:sizes``, ``proc:failures``) or ``real:NAME`` / ``real:all`` (the shared
            datasets; skipped with the reason when absent), or real-scene stability variants
            ``real:NAME@FAMILY`` / ``real:failures`` (``freescale_core.eval.real_variants``).
        out: output folder (cache of points, tables, charts).
        config: :class:`schemas.evaluate.EvaluateConfig`.
    Returns:
        ``{"out", "files", "computed", "cached", "skipped", "n_points"}``.
    """
    from freescale_core.eval.scenes import resolve_scenes
    from freescale_core.eval.sweep import run_sweep

    cfg = config or EvaluateConfig()
    log = get_run_logger()
    outp = Path(out)
    paths, skipped = resolve_scenes(scenes, outp)
    for s in skipped:
        log.warning("scene skipped: %s", s)
    res = run_sweep(paths, cfg, outp, run_point_with_flow, log=log.info)
    md = summary_markdown(res, outp, skipped)
    (outp / "tables.md").write_text(md + "\n")
    try:
        keep = ("label", "scene", "status", "accuracy", "wall_total", "cpu_total", "peak_rss_mb",
                "fv_true_share", "heldout_psnr", "n_free_views", "scarce", "refine_gain_db")
        create_table_artifact(table=[{k: r.get(k) for k in keep} for r in res.rows],
                              key="freescale-evaluate", description=f"evaluate-engine: {out}")
        chart = res.files.get("pareto")
        img = ""
        if chart:
            b64 = base64.b64encode(Path(chart).read_bytes()).decode()
            img = f"![Pareto chart](data:image/png;base64,{b64})\n\n"
        create_markdown_artifact(markdown=img + md, key="freescale-evaluate-summary")
    except Exception as e:  # artifacts are a convenience
        log.warning("could not create the artifacts: %s", e)
    return {"out": str(outp), "files": res.files, "computed": res.computed,
            "cached": res.cached, "skipped": skipped, "n_points": len(res.rows)}
