"""Train the decoder-only LVSM on in-memory scenes (METHOD.md "Downstream uses": LVSM).

:func:`train_lvsm` runs AdamW with a linear warm-up to the peak lr then a cosine decay, global
grad-norm clipping, optional bf16 autocast (off on CPU), batches of ``batch_size`` examples
drawn by :class:`ViewSampler` (its curriculum step is set every step) from
:class:`SceneTensors` scenes, the sampler's per-target loss weights (and, with
``confidence_weight``, the scenes' per-pixel confidence), held-out evaluation at
intervals, checkpoints and a JSON history plus a loss-curve PNG.

Checkpoints (``out_dir/ckpt/last.pt``, written atomically) hold model, optimiser, scheduler,
numpy and torch RNG states, the step and the history; a new call with the same ``out_dir``
resumes from it and reaches the same parameters as an uninterrupted run (same seed, same
scenes, same torch thread count).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freescale_core.downstream.lvsm.data import SceneTensors, collate
from freescale_core.downstream.lvsm.model import LVSM
from freescale_core.downstream.lvsm.model import loss as lvsm_loss
from freescale_core.downstream.lvsm.model import psnr as lvsm_psnr
from freescale_core.downstream.lvsm.sampler import ViewSampler
from freescale_core.store.store import atomic_path, write_json_atomic
from schemas.lvsm import LVSMSamplerConfig, TrainLVSMConfig

__all__ = [
    "TrainResult",
    "evaluate_loss",
    "lr_factor",
    "plot_history",
    "predict",
    "train_lvsm",
]

CKPT_NAME = "last.pt"


def lr_factor(step: int, warmup: int, total: int, min_ratio: float = 0.0) -> float:
    """lr / peak at ``step`` (0-based, the step about to be taken): linear warm-up from
    ``1 / warmup`` to 1 over ``warmup`` steps, then cosine from 1 to ``min_ratio`` at
    ``total``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    span = max(1, total - warmup)
    t = min(1.0, (step - warmup) / span)
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * t))


@dataclass
class TrainResult:
    """What :func:`train_lvsm` returns."""

    model: LVSM
    history: dict[str, Any]
    out_dir: Path
    resumed_from: int  # step loaded from a checkpoint (0 = fresh start)


def predict(model: LVSM, batch: dict[str, torch.Tensor], device: str = "cpu",
            bf16: bool = False) -> torch.Tensor:
    """Model output ``[B, Vt, 3, H, W]`` float32 for a :func:`collate` batch."""
    dev = torch.device(device)
    use_bf16 = bf16 and dev.type == "cuda"
    with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=use_bf16):
        out = model(batch["images"].to(dev), batch["in_c2w"].to(dev), batch["in_K"].to(dev),
                    batch["tgt_c2w"].to(dev), batch["tgt_K"].to(dev))
    return out.float()


def evaluate_loss(model: LVSM, scenes: list[SceneTensors], sampler_cfg: LVSMSamplerConfig,
                  n_samples: int, batch_size: int, seed: int = 12345, device: str = "cpu"
                  ) -> dict[str, float]:
    """Mean loss and PSNR on ``n_samples`` fixed examples (captured views only, the
    sampler's frame branch after its curriculum; same seed -> same examples)."""
    sampler = ViewSampler(sampler_cfg, use_free_views=False)
    rng = np.random.default_rng([seed, 99])
    step = sampler_cfg.warmup_steps
    items = []
    for k in range(n_samples):
        sc = scenes[k % len(scenes)]
        items.append((sc, sampler.sample(sc.views, rng, step=step)))
    was = model.training
    model.eval()
    losses, psnrs = [], []
    with torch.no_grad():
        for i in range(0, len(items), batch_size):
            b = collate(items[i:i + batch_size])
            pred = predict(model, b, device)
            tgt = b["target"].to(pred.device)
            losses.append(float(lvsm_loss(pred, tgt)) * len(pred))
            psnrs.extend(lvsm_psnr(pred, tgt).flatten().tolist())
    model.train(was)
    return {"loss": sum(losses) / len(items), "psnr": float(np.mean(psnrs))}


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def plot_history(history: dict[str, Any], path: str | Path) -> None:
    """Loss and PSNR curves (train, held-out) as a PNG (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr, ev = history.get("train", []), history.get("eval", [])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    if tr:
        s = [r["step"] for r in tr]
        a1.plot(s, [r["loss"] for r in tr], lw=0.8, alpha=0.6, label="train")
        a2.plot(s, [r["psnr"] for r in tr], lw=0.8, alpha=0.6, label="train")
    if ev:
        s = [r["step"] for r in ev]
        a1.plot(s, [r["loss"] for r in ev], "o-", label="held-out")
        a2.plot(s, [r["psnr"] for r in ev], "o-", label="held-out")
    a1.set(xlabel="step", ylabel="MSE loss", yscale="log", title="loss")
    a2.set(xlabel="step", ylabel="PSNR (dB)", title="PSNR")
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)


def train_lvsm(train_scenes: list[SceneTensors], cfg: TrainLVSMConfig | None = None,
               seed: int = 0, out_dir: str | Path | None = None,
               eval_scenes: list[SceneTensors] | None = None, *, resume: bool = True,
               log: Callable[[str], None] | None = print,
               callback: Callable[[int, dict[str, Any]], None] | None = None,
               plot: bool = True) -> TrainResult:
    """Train an LVSM from scratch (or resume) on ``train_scenes``.

    Args:
        train_scenes: scenes to draw examples from (each needs >= n_input + n_target
            captured views).
        cfg: run settings (default ``TrainLVSMConfig()``).
        seed: model init, example draws; same seed + scenes + config -> same parameters.
        out_dir: where ``ckpt/last.pt``, ``history.json`` and ``loss.png`` go; None = no files
            (no checkpoints, no resume).
        eval_scenes: held-out scenes evaluated every ``eval_every`` steps and at the end.
        resume: continue from ``out_dir/ckpt/last.pt`` when it exists.
        log: line logger (None = silent).
        callback: called after each step with ``(step, record)`` (tests interrupt runs here).
        plot: write ``loss.png`` at the end.

    Returns:
        :class:`TrainResult` (model in eval mode, history dict).
    """
    cfg = cfg or TrainLVSMConfig()
    if not train_scenes:
        raise ValueError("train_lvsm: no training scenes")
    say = log or (lambda _s: None)
    dev = torch.device(cfg.device)
    use_bf16 = cfg.bf16 and dev.type == "cuda"
    out = Path(out_dir) if out_dir is not None else None
    ckpt_path = out / "ckpt" / CKPT_NAME if out is not None else None

    torch.manual_seed(seed)
    model = LVSM(cfg.model()).to(dev)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas,
                            weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: lr_factor(s, cfg.warmup_steps, cfg.steps, cfg.min_lr_ratio))
    sampler = ViewSampler(cfg.sampler)
    rng = np.random.default_rng([seed, 7])
    cfg_json = cfg.model_dump(mode="json")
    history: dict[str, Any] = {"config": cfg_json, "seed": seed,
                               "scenes": [s.scene_id for s in train_scenes],
                               "train": [], "eval": []}
    step0 = 0
    if ckpt_path is not None and resume and ckpt_path.is_file():
        st = torch.load(ckpt_path, map_location=dev, weights_only=False)
        if st["config"] != cfg_json or st["seed"] != seed:
            raise ValueError(f"checkpoint {ckpt_path} was written by another config or seed; "
                             "remove it or pick another out_dir")
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        rng.bit_generator.state = st["np_rng"]
        torch.set_rng_state(st["torch_rng"])
        history = st["history"]
        step0 = int(st["step"])
        say(f"resumed from {ckpt_path} at step {step0}")

    def checkpoint(step: int) -> None:
        if ckpt_path is None:
            return
        _save_checkpoint(ckpt_path, dict(
            model=model.state_dict(), optimizer=opt.state_dict(), scheduler=sched.state_dict(),
            np_rng=rng.bit_generator.state, torch_rng=torch.get_rng_state(), step=step,
            history=history, config=cfg_json, seed=seed))
        write_json_atomic(out / "history.json", history)

    def run_eval(step: int) -> None:
        if not eval_scenes:
            return
        m = evaluate_loss(model, eval_scenes, cfg.sampler, cfg.eval_samples, cfg.batch_size,
                          device=cfg.device)
        history["eval"].append({"step": step, **m})
        say(f"step {step:6d}  held-out loss {m['loss']:.5f}  psnr {m['psnr']:.2f} dB")

    model.train()
    t_last, n_last = time.perf_counter(), 0
    for step in range(step0, cfg.steps):
        sampler.set_step(step)
        items = []
        for _ in range(cfg.batch_size):
            sc = train_scenes[int(rng.integers(len(train_scenes)))]
            items.append((sc, sampler.sample(sc.views, rng)))
        batch = collate(items)
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=use_bf16):
            pred = predict(model, batch, cfg.device, cfg.bf16)
        target = batch["target"].to(dev)
        pw = batch.get("confidence") if cfg.confidence_weight else None
        l = lvsm_loss(pred, target, batch["weight"].to(dev),
                      None if pw is None else pw.to(dev))
        opt.zero_grad(set_to_none=True)
        l.backward()
        gnorm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip))
        lr = opt.param_groups[0]["lr"]
        opt.step()
        sched.step()
        n_last += 1
        rec = {"step": step + 1, "loss": float(l.detach()),
               "psnr": float(lvsm_psnr(pred.detach(), target).mean()), "lr": lr,
               "grad_norm": gnorm,
               "n_free_targets": int(sum(int(sc.views.is_free[s.target_ids].sum())
                                         for sc, s in items))}
        if (step + 1) % cfg.log_every == 0 or step + 1 == cfg.steps:
            now = time.perf_counter()
            rec["it_s"] = n_last / max(now - t_last, 1e-9)
            t_last, n_last = now, 0
            say(f"step {step + 1:6d}  loss {rec['loss']:.5f}  psnr {rec['psnr']:.2f} dB  "
                f"lr {lr:.2e}  {rec['it_s']:.2f} it/s")
        history["train"].append(rec)
        if (step + 1) % cfg.eval_every == 0 and step + 1 != cfg.steps:
            run_eval(step + 1)
        if (step + 1) % cfg.ckpt_every == 0:
            checkpoint(step + 1)
        if callback is not None:
            callback(step + 1, rec)
    if step0 < cfg.steps or not history["eval"]:
        run_eval(cfg.steps)
    if out is not None:
        checkpoint(cfg.steps)
        if plot and history["train"]:
            plot_history(history, out / "loss.png")
    model.eval()
    return TrainResult(model, history, out if out is not None else Path("."), step0)
