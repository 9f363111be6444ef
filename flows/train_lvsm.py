"""The ``train-lvsm`` flow: train the feed-forward view-synthesis model (LVSM) from packed
training shards, with or without the free views (METHOD.md "Downstream uses"; docs/LVSM.md).

All work is in ``freescale_core.downstream.lvsm.from_shards``; this flow runs it as one task
and reports to Prefect: the loss / PSNR / it/s lines as task logs, a progress artifact
(steps done / total) and, at the end, a markdown artifact with the numbers, the held-out
evaluations and the loss-curve PNG (inlined; the file is ``OUT/loss.png`` beside
``OUT/ckpt/last.pt``). A run started again with ``resume=True`` continues from its last
checkpoint and ends where an uninterrupted run of the same seed and config ends.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

from flows.step_progress import StepProgress
from prefect import flow, get_run_logger, task

from schemas.lvsm import TrainLVSMShardsConfig

ARTIFACT_KEY = "freescale-train-lvsm"


def _Progress(total: int, description: str, every: float = 5.0) -> StepProgress:
    return StepProgress(total, f"{ARTIFACT_KEY}-progress", description, every)


def run_markdown(metrics: dict, history: dict | None = None) -> str:
    """Markdown of a finished run: numbers, held-out evaluations, the loss curve inlined."""
    def f(v, nd):
        return "-" if v is None else f"{v:.{nd}f}"

    m = metrics
    md = [f"# train-lvsm: {m['out']}", "",
          f"shards `{m['shards']}`, seed {m['seed']}, {m['steps']} steps"
          + (f" (resumed at step {m['resumed_from']})" if m["resumed_from"] else "")
          + f", free views {'used' if m['use_free_views'] else 'not used'}", "",
          ("| train scenes | held-out scenes | captured / free views | free target share "
           "| parameters |"), "|---|---|---|---|---|",
          f"| {len(m['train_scenes'])} | {', '.join(m['heldout_scenes']) or '-'}"
          + (f" + capture tails of {len(m['heldout_tail_scenes'])}" if m["heldout_tail_scenes"]
             else "")
          + f" | {m['n_captured_train']} / {m['n_free_train']} | {m['free_target_share']:.2f} "
          f"| {m['n_params']:,} |", "",
          ("| train loss | train PSNR | held-out loss | held-out PSNR | best held-out PSNR "
           "(step) | it/s | wall s |"), "|---|---|---|---|---|---|---|",
          (f"| {f(m['final_train_loss'], 5)} | {f(m['final_train_psnr'], 2)} | "
           f"{f(m['heldout_loss'], 5)} | {f(m['heldout_psnr'], 2)} | "
           f"{f(m['best_heldout_psnr'], 2)} ({m['best_heldout_step']}) | {f(m['it_s'], 2)} | "
           f"{m['wall_seconds']:.0f} |"), ""]
    ev = (history or {}).get("eval", [])
    if ev:
        md += ["## Held-out evaluations", "", "| step | loss | PSNR (dB) |", "|---|---|---|"]
        md += [f"| {r['step']} | {r['loss']:.5f} | {r['psnr']:.2f} |" for r in ev]
        md.append("")
    png = Path(m["loss_png"])
    if png.is_file():
        b64 = base64.b64encode(png.read_bytes()).decode()
        md += ["## Loss curve", "", f"![loss curve](data:image/png;base64,{b64})", "",
               f"File: `{png}`; checkpoint `{m['checkpoint']}`."]
    return "\n".join(md)


# the run folder's name, never its path: a "[/a/path]" in a task-run name reads as a closing
# markup tag to rich, and `prefect deployment run --watch` failed on it
@task(name="train-lvsm-run", task_run_name="train-lvsm[{run_name}]")
def train_lvsm_task(shards: str, out: str, cfg: TrainLVSMShardsConfig, seed: int,
                    resume: bool, run_name: str = "") -> dict:
    from freescale_core.downstream.lvsm.from_shards import train_from_shards

    log = get_run_logger()
    progress = _Progress(cfg.train.steps, f"train-lvsm {out}: steps")
    metrics = train_from_shards(shards, out, cfg, seed, resume=resume, log=log.info,
                                callback=progress)
    progress(cfg.train.steps)
    return metrics


@flow(name="train-lvsm", log_prints=True)
def train_lvsm_flow(shards: str, out: str | None = None, seed: int = 0,
                    config: TrainLVSMShardsConfig | None = None, resume: bool = False) -> dict:
    """Train an LVSM on packed shards; held-out loss / PSNR at intervals; checkpoints.

    Args:
        shards: a shard folder (``freescale shards pack STORE SHARDS``).
        out: run folder (None: ``<SHARDS>-lvsm/seed<seed>`` beside the shards).
        seed: model init and example draws.
        config: :class:`schemas.lvsm.TrainLVSMShardsConfig` (``train.*`` the run,
            ``heldout_*`` the split; ``train.sampler.use_free_views=false`` for captured only).
        resume: continue the run in ``out`` from its last checkpoint (False: refuse when
            ``out`` already holds one).
    Returns:
        The run's ``metrics.json`` record.
    """
    cfg = config or TrainLVSMShardsConfig()
    out = out or default_out(shards, seed)
    metrics = train_lvsm_task(shards, out, cfg, seed, resume, run_name=Path(out).name)
    hist_p = Path(out) / "history.json"
    history = json.loads(hist_p.read_text()) if hist_p.is_file() else None
    try:
        from prefect.artifacts import create_markdown_artifact

        create_markdown_artifact(markdown=run_markdown(metrics, history), key=ARTIFACT_KEY,
                                 description=f"train-lvsm {out}")
    except Exception as e:  # noqa: BLE001 - artifacts are a convenience
        get_run_logger().warning("could not create the artifact: %s", e)
    return metrics


def default_out(shards: str, seed: int) -> str:
    """``<SHARDS>-lvsm/seed<seed>``: beside the shard folder, never inside it."""
    from freescale_core.store.objstore import is_url, local_of

    if is_url(shards):
        raise ValueError(f"shards at a URL ({shards}): give the run folder with --out")
    p = Path(local_of(shards)).absolute()
    return str(p.parent / f"{p.name}-lvsm" / f"seed{seed}")
