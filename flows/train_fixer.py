"""The ``train-fixer`` flow: train the fixer network across scenes from engine-made pairs
(``freescale_core.fixer``; issue 60).

All work is in :func:`freescale_core.fixer.train.train_fixer`; this flow runs it as one task
and reports to Prefect: the step / loss / patches-per-second / ETA lines as task logs, a
progress artifact (steps done / total) and, at the end, a markdown artifact with the numbers,
the loss curve and a before/after contact sheet (render | fixed | target | confidence, held-out
pairs) inlined as PNGs (the files are ``OUT/loss.png`` and ``OUT/contact.png`` beside
``OUT/fixer.pt``). Started again with ``resume=True`` a run continues from its last checkpoint
and ends with the weights an uninterrupted run of the same seed and config ends with.
"""

from __future__ import annotations

import base64
from pathlib import Path

from flows.step_progress import StepProgress
from prefect import flow, get_run_logger, task

from schemas.fixer import FixerTrainConfig

ARTIFACT_KEY = "freescale-train-fixer"


def _Progress(total: int, description: str, every: float = 5.0) -> StepProgress:
    return StepProgress(total, f"{ARTIFACT_KEY}-progress", description, every)


def _png_md(path: Path, title: str) -> list[str]:
    if not path.is_file():
        return []
    b64 = base64.b64encode(path.read_bytes()).decode()
    return [f"## {title}", "", f"![{title}](data:image/png;base64,{b64})", "", f"File: `{path}`", ""]


def run_markdown(m: dict) -> str:
    """Markdown of a finished run: numbers, per-pair scores, loss curve and contact sheet."""
    def f(v, nd):
        return "-" if v is None else f"{v:.{nd}f}"

    md = [f"# train-fixer: {m['out']}", "",
          f"pairs `{m['pairs_root']}` (data hash `{m['data_hash']}`), seed {m['seed']}, "
          f"{m['steps']} steps" + (f" (resumed at step {m['resumed_from']})"
                                   if m["resumed_from"] else "")
          + f", stopped by {m['stopped_by']}", "",
          "| train scenes | held-out scenes | train pairs | parameters | CPU s | final loss |",
          "|---|---|---|---|---|---|",
          f"| {', '.join(m['train_scenes'])} | {', '.join(m['holdout_scenes']) or '-'} | "
          f"{m['n_train_pairs']} | {m['n_params']:,} | {m['cpu_seconds']:.0f} | "
          f"{f(m['final_loss'], 4)} |", "",
          f"## Scored pairs ({m['eval_on']})", "",
          "| mean PSNR render | mean PSNR fixed | mean SSIM render | mean SSIM fixed |",
          "|---|---|---|---|",
          f"| {f(m['eval_psnr_render'], 2)} | {f(m['eval_psnr_fixed'], 2)} | "
          f"{f(m['eval_ssim_render'], 3)} | {f(m['eval_ssim_fixed'], 3)} |", ""]
    if m.get("eval_pairs"):
        md += ["| pair | scene | PSNR render | PSNR fixed | mean confidence |",
               "|---|---|---|---|---|"]
        md += [f"| {r['pair_id']} | {r['scene_id']} | {f(r['psnr_render'], 2)} | "
               f"{f(r['psnr_fixed'], 2)} | {f(r['conf_mean'], 3)} |" for r in m["eval_pairs"]]
        md.append("")
    md += _png_md(Path(m["loss_png"]), "Loss curve")
    md += _png_md(Path(m["contact_png"]),
                  "Before / after (render | fixed | target | confidence)")
    md.append(f"Checkpoint `{m['checkpoint']}`.")
    return "\n".join(md)


# the run folder's name in the task-run name, never its path (rich reads "[/a/path]" as markup)
@task(name="train-fixer-run", task_run_name="train-fixer[{run_name}]")
def train_fixer_task(pairs: str, out: str, cfg: FixerTrainConfig, holdout: list[str],
                     train_scenes: list[str] | None, resume: bool, run_name: str = "") -> dict:
    from freescale_core.fixer.train import train_fixer

    log = get_run_logger()
    progress = _Progress(cfg.steps, f"train-fixer {out}: steps")
    m = train_fixer(pairs, out, cfg, holdout_scenes=holdout, train_scenes=train_scenes,
                    progress=progress, resume=resume, log=log.info)
    progress(cfg.steps)
    return m


@flow(name="train-fixer", log_prints=True)
def train_fixer_flow(pairs: str, out: str, config: FixerTrainConfig | None = None,
                     holdout: list[str] | None = None, train_scenes: list[str] | None = None,
                     resume: bool = False) -> dict:
    """Train the fixer on the pairs of every scene but ``holdout``; checkpoints; artifacts.

    Args:
        pairs: a pairs folder (``<scene>/<fold>/`` folders, see freescale_core.fixer.data).
        out: run folder (``fixer.pt``, ``ckpt/last.pt``, ``loss.jsonl``, ``metrics.json``,
            ``loss.png``, ``contact.png``).
        config: :class:`schemas.fixer.FixerTrainConfig` (``seed``, ``steps``, ...).
        holdout: scene ids never trained on (scored at the end).
        train_scenes: None = every scene not held out.
        resume: continue the run in ``out`` from its last checkpoint (False: refuse when
            ``out`` already holds one).
    Returns:
        The run's ``metrics.json`` record.
    """
    cfg = config or FixerTrainConfig()
    m = train_fixer_task(pairs, out, cfg, list(holdout or []), train_scenes, resume,
                         run_name=Path(out).name)
    try:
        from prefect.artifacts import create_markdown_artifact

        create_markdown_artifact(markdown=run_markdown(m), key=ARTIFACT_KEY,
                                 description=f"train-fixer {out}")
    except Exception as e:  # noqa: BLE001 - artifacts are a convenience
        get_run_logger().warning("could not create the artifact: %s", e)
    return m
