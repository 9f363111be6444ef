"""Cross-scene training of the fixer on engine-made pairs (``freescale_core.fixer.data``).

:func:`train_fixer` trains a :class:`~freescale_core.fixer.model.FixerNet` on the pairs of
every scene under ``PAIRS`` except the held-out ones, on random patches, and writes::

    OUT/
      ckpt/last.pt   model, optimiser, scheduler, RNG states, step, CPU seconds (resume point,
                     written atomically every ``ckpt_every`` steps)
      loss.jsonl     the loss curve: one JSON object per ``log_every`` steps
      fixer.pt       the final checkpoint (:func:`~freescale_core.fixer.model.load_fixer`):
                     weights, model config, training config, training and held-out scenes,
                     data hash, pairs root, steps
      metrics.json   held-out (or, without held-out scenes, training) pairs scored raw vs fixed
      loss.png, contact.png   the loss curve and a before/after contact sheet

Loss (per patch batch, over the pairs' masks):

* image: ``(1 - lambda_ssim) L1 + lambda_ssim (1 - SSIM)`` of the corrected image against the
  target (the reconstruction's loss; SSIM by the fused numba kernel of
  :mod:`freescale_core.recon.fused_ssim`, the batch's patches stacked as channels);
* confidence: ``lambda_conf * BCE(conf, exp(-|e| / tau))`` with ``|e|`` the corrected pixel's
  mean absolute error over RGB, *detached*. So the confidence learns to predict the error
  (a calibrated "this pixel is within ~tau of the truth") without pulling the image towards
  where it is easy to be confident, which a heteroscedastic ``|e| / s + log s`` loss on the
  same graph would do.

Augmentations keep the geometry honest: a horizontal flip of every input channel and the
target together (the warps are in the view's own frame, so they flip with it) and a per-patch,
per-channel gain applied to the render, the warped photos and the target together (a whole
capture seen with another exposure / white balance); alpha, weights and mask never change. No
rotations or vertical flips: the cameras' "up" is a prior worth keeping.

Same seed, pairs and config -> the same weights; a run interrupted at any point (SIGKILL
included) and started again with ``resume=True`` ends with bit-identical weights.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from freescale_core.fixer.data import FixerSample, model_input, pair_folders, read_pair_folder
from freescale_core.fixer.model import CHECKPOINT_FORMAT, FixerNet, n_params
from freescale_core.recon.ssim_window import SSIM_WINDOW
from freescale_core.files import atomic_path, write_bytes_atomic, write_json_atomic
from schemas.fixer import FixerTrainConfig

__all__ = ["train_fixer", "fixer_loss", "data_hash", "RunExistsError", "ResumeMismatchError",
           "FIXER_NAME", "CKPT_NAME"]

FIXER_NAME = "fixer.pt"
CKPT_NAME = "last.pt"
# fields that do not change the weights: a resumed run may change them
_RESUME_FREE = ("max_cpu_seconds", "log_every", "eval_pairs")


class RunExistsError(RuntimeError):
    """``out`` already holds a run and the caller did not ask to resume."""


class ResumeMismatchError(ValueError):
    """The checkpoint in ``out`` was made from other pairs, data or config."""


# --------------------------------------------------------------------------- data
def data_hash(folders: Sequence[Path]) -> str:
    """sha256 over each folder's ``<scene>/<fold>`` name, ``done.json`` and ``pairs.parquet``
    bytes (sorted by name): changes when any pair folder is remade or added."""
    h = hashlib.sha256()
    for f in sorted(folders, key=lambda p: (p.parent.name, p.name)):
        h.update(f"{f.parent.name}/{f.name}\n".encode())
        for name in ("done.json", "pairs.parquet"):
            b = (f / name).read_bytes()
            h.update(f"{name} {len(b)}\n".encode())
            h.update(b)
    return h.hexdigest()[:16]


def _u8(a: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


class _Pool:
    """Training pairs as uint8 arrays: inputs ``[C, H, W]``, targets ``[3, H, W]``, masks."""

    def __init__(self, samples: list[FixerSample], k: int):
        self.x = [_u8(model_input(s.render, s.alpha, s.warps, s.warp_weight, k)) for s in samples]
        self.y = [_u8(np.moveaxis(s.target, -1, 0)) for s in samples]
        self.m = [np.asarray(s.mask, bool) for s in samples]
        scenes = [str(s.meta.get("scene_id")) for s in samples]
        self.scenes = sorted(set(scenes))
        self.by_scene = [np.array([i for i, sc in enumerate(scenes) if sc == name])
                         for name in self.scenes]
        self.k = k

    def __len__(self) -> int:
        return len(self.x)

    def min_side(self) -> int:
        return min(min(x.shape[1:]) for x in self.x)

    def batch(self, rng: np.random.Generator, n: int, P: int, flip: bool, jitter: float
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` patches ``P x P``: a scene uniformly, then one of its pairs, then a place."""
        C = self.x[0].shape[0]
        xs = np.empty((n, C, P, P), np.float32)
        ys = np.empty((n, 3, P, P), np.float32)
        ms = np.empty((n, P, P), bool)
        rgb = [0, 1, 2] + [c for i in range(self.k) for c in range(4 + 4 * i, 7 + 4 * i)]
        for b in range(n):
            idx = self.by_scene[int(rng.integers(len(self.scenes)))]
            i = int(idx[int(rng.integers(len(idx)))])
            H, W = self.x[i].shape[1:]
            y0, x0 = int(rng.integers(H - P + 1)), int(rng.integers(W - P + 1))
            f = bool(rng.random() < 0.5) if flip else False
            g = (1.0 + rng.uniform(-jitter, jitter, 3)).astype(np.float32) if jitter > 0 \
                else None
            xp = self.x[i][:, y0:y0 + P, x0:x0 + P].astype(np.float32) / 255.0
            yp = self.y[i][:, y0:y0 + P, x0:x0 + P].astype(np.float32) / 255.0
            mp = self.m[i][y0:y0 + P, x0:x0 + P]
            if f:
                xp, yp, mp = xp[:, :, ::-1], yp[:, :, ::-1], mp[:, ::-1]
            if g is not None:
                gains = np.tile(g, len(rgb) // 3)[:, None, None]
                xp = xp.copy()
                xp[rgb] = np.minimum(xp[rgb] * gains, 1.0)
                yp = np.minimum(yp * g[:, None, None], 1.0)
            xs[b], ys[b], ms[b] = xp, yp, mp
        return torch.from_numpy(xs), torch.from_numpy(ys), torch.from_numpy(ms)


# --------------------------------------------------------------------------- loss
def fixer_loss(fixed: torch.Tensor, conf: torch.Tensor, target: torch.Tensor,
               mask: torch.Tensor, lambda_ssim: float = 0.2, lambda_conf: float = 0.05,
               tau: float = 0.05) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of a batch (see the module docstring).

    Args:
        fixed, target: ``[B, 3, H, W]`` in [0, 1]; conf ``[B, 1, H, W]`` in (0, 1);
        mask: ``[B, H, W]`` bool, pixels that count.
    Returns:
        ``(loss, parts)`` with parts ``l1``, ``ssim``, ``conf`` (floats).
    """
    B, _, H, W = fixed.shape
    m = mask[:, None].to(fixed.dtype)
    n = m.sum().clamp_min(1.0)
    fm, tm = fixed * m, target * m  # outside the mask both are 0: no gradient, no influence
    l1 = (fm - tm).abs().sum() / (3.0 * n)
    loss = (1.0 - lambda_ssim) * l1
    s = torch.ones(())
    if lambda_ssim > 0 and min(H, W) >= SSIM_WINDOW:
        from freescale_core.recon.losses import ssim_map

        img = fm.permute(2, 3, 0, 1).reshape(H, W, B * 3)
        ref = tm.permute(2, 3, 0, 1).reshape(H, W, B * 3)
        smap = ssim_map(img, ref, impl="fused").reshape(B, 3, H - SSIM_WINDOW + 1,
                                                         W - SSIM_WINDOW + 1).mean(1)
        h = SSIM_WINDOW // 2
        mc = mask[:, h:H - h, h:W - h].to(fixed.dtype)
        s = (smap * mc).sum() / mc.sum().clamp_min(1.0)
        loss = loss + lambda_ssim * (1.0 - s)
    err = (fixed.detach() - target).abs().mean(1, keepdim=True)
    ct = torch.exp(-err / tau)
    bce = F.binary_cross_entropy(conf.clamp(1e-6, 1 - 1e-6), ct, reduction="none")
    lc = (bce * m).sum() / n
    if lambda_conf > 0:
        loss = loss + lambda_conf * lc
    return loss, {"l1": float(l1.detach()), "ssim": float(s.detach()), "conf": float(lc.detach())}


def _psnr(a: torch.Tensor, b: torch.Tensor, m: torch.Tensor) -> float:
    mm = m[:, None].expand_as(a)
    if not bool(mm.any()):
        return float("nan")
    mse = float(((a.double() - b.double())[mm] ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def lr_factor(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """Linear warmup to 1 over ``warmup`` steps, then cosine to ``min_ratio`` at ``total``."""
    warmup = min(warmup, max(total - 1, 0))
    if step < warmup:
        return (step + 1) / warmup
    t = (step - warmup) / max(total - warmup, 1)
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * min(t, 1.0)))


# --------------------------------------------------------------------------- outputs
def _fmt_time(s: float) -> str:
    s = int(max(s, 0))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def plot_loss(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6))
    s = [r["step"] for r in rows]
    a1.plot(s, [r["loss"] for r in rows], label="loss")
    a1.plot(s, [r["l1"] for r in rows], label="L1")
    a1.set(xlabel="step", ylabel="loss", yscale="log", title="fixer training loss")
    a2.plot(s, [r["psnr_render"] for r in rows], label="render (input)")
    a2.plot(s, [r["psnr_fixed"] for r in rows], label="fixed")
    a2.set(xlabel="step", ylabel="patch PSNR (dB)", title="training patches")
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=80)
    plt.close(fig)


def contact_sheet(rows: list[tuple[np.ndarray, ...]], path: Path, width: int = 160) -> None:
    """One row per pair: render | fixed | target | confidence (grey), each ``width`` wide."""
    from PIL import Image

    tiles = []
    for render, fixed, target, conf in rows:
        H, W = render.shape[:2]
        h = max(1, round(H * width / W))
        ims = [render, fixed, target, np.repeat(conf[..., None], 3, -1)]
        tiles.append(np.concatenate(
            [np.asarray(Image.fromarray(_u8(np.clip(im, 0, 1))).resize((width, h)))
             for im in ims], axis=1))
    sheet = np.concatenate(tiles, axis=0)
    with atomic_path(path) as tmp:
        Image.fromarray(sheet).save(tmp, format="PNG")


def _evaluate(model: FixerNet, samples: list[FixerSample], k: int) -> dict[str, Any]:
    """Whole-image masked PSNR / SSIM of render and fixed image against the target."""
    from freescale_core.fixer.infer import fix_samples
    from freescale_core.recon.losses import masked_psnr_ssim

    out, sheet = [], []
    for s, (f, c) in zip(samples, fix_samples(model, samples)):
        m = torch.from_numpy(np.asarray(s.mask, bool))
        t = torch.from_numpy(np.asarray(s.target, np.float32))
        pr, sr = masked_psnr_ssim(torch.from_numpy(np.asarray(s.render, np.float32)), t, m)
        pf, sf = masked_psnr_ssim(torch.from_numpy(f), t, m)
        out.append({"pair_id": s.meta.get("pair_id"), "scene_id": s.meta.get("scene_id"),
                    "psnr_render": pr, "psnr_fixed": pf, "ssim_render": sr, "ssim_fixed": sf,
                    "conf_mean": float(c[np.asarray(s.mask, bool)].mean()) if m.any() else None})
        sheet.append((s.render, f, s.target, c))
    return {"pairs": out, "sheet": sheet}


def _mean(xs) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else None


# --------------------------------------------------------------------------- training
def train_fixer(pairs_root: str | Path, out_dir: str | Path, cfg: FixerTrainConfig | None = None,
                holdout_scenes: Sequence[str] = (), train_scenes: Sequence[str] | None = None,
                progress: Callable[[int, int, dict], None] | None = None, *,
                resume: bool = False, log: Callable[[str], None] | None = print
                ) -> dict[str, Any]:
    """Train a fixer on the pairs under ``pairs_root`` (every scene but ``holdout_scenes``,
    or only ``train_scenes``) into ``out_dir``.

    Args:
        pairs_root: a pairs folder (``<scene>/<fold>/`` with ``done.json``).
        out_dir: run folder (see the module docstring).
        cfg: :class:`schemas.fixer.FixerTrainConfig` (default: its defaults).
        holdout_scenes: scenes never trained on; scored at the end.
        train_scenes: None = every scene not held out.
        progress: called after every step with ``(step, total_steps, record)`` (the record
            holds the loss and, on ``log_every`` steps, patches/s and ETA).
        resume: continue from ``out_dir/ckpt/last.pt``; False with a run present raises
            :class:`RunExistsError`.
        log: line logger for the console lines (None: silent).
    Returns:
        The ``metrics.json`` record.
    """
    cfg = cfg or FixerTrainConfig()
    say = log or (lambda _s: None)
    root = Path(pairs_root)
    out = Path(out_dir)
    ckpt_path, final_path = out / "ckpt" / CKPT_NAME, out / FIXER_NAME
    if not root.is_dir():
        raise FileNotFoundError(f"train-fixer: pairs folder not found: {root}")
    if (ckpt_path.is_file() or final_path.is_file()) and not resume:
        raise RunExistsError(f"{out} already holds a fixer run ({ckpt_path if ckpt_path.is_file() else final_path}); "
                             "resume it or pick another out folder")
    all_folders = pair_folders(root)
    scenes = sorted({f.parent.name for f in all_folders})
    if not scenes:
        raise FileNotFoundError(f"train-fixer: no complete pair folder (<scene>/<fold>/done.json) "
                                f"under {root}")
    holdout = sorted(set(holdout_scenes))
    for name in holdout + sorted(set(train_scenes or ())):
        if name not in scenes:
            raise ValueError(f"train-fixer: scene {name!r} has no pairs under {root} "
                             f"(scenes: {', '.join(scenes)})")
    tr_scenes = sorted(set(train_scenes) if train_scenes is not None else set(scenes))
    tr_scenes = [s for s in tr_scenes if s not in holdout]
    if not tr_scenes:
        raise ValueError(f"train-fixer: no training scene left under {root} after holding out "
                         f"{', '.join(holdout)}")
    tr_folders = [f for f in all_folders if f.parent.name in tr_scenes]
    dhash = data_hash(tr_folders)
    samples = [s for f in tr_folders for s in read_pair_folder(f)]
    if not samples:
        raise ValueError(f"train-fixer: the training scenes under {root} hold no pairs")
    k = cfg.model.k
    pool = _Pool(samples, k)
    P = min(cfg.patch, pool.min_side())
    if P < SSIM_WINDOW:
        raise ValueError(f"train-fixer: the smallest pair under {root} is {pool.min_side()} px; "
                         f"need >= {SSIM_WINDOW}")
    cfg_json = cfg.model_dump(mode="json")
    meta = {"pairs_root": str(root.resolve()), "data_hash": dhash, "train_scenes": tr_scenes,
            "holdout_scenes": holdout, "n_train_pairs": len(pool), "patch": P}

    torch.manual_seed(cfg.seed)
    model = FixerNet(cfg.model)
    if cfg.init_from:
        from freescale_core.fixer.model import load_fixer

        init, init_meta = load_fixer(cfg.init_from)
        if init.cfg != cfg.model:
            raise ValueError(f"train-fixer: init_from {cfg.init_from} has model config "
                             f"{init.cfg.model_dump()}, the run asks for "
                             f"{cfg.model.model_dump()}")
        model.load_state_dict(init.state_dict())
        model.train()
        meta["init_from"] = {"path": str(Path(cfg.init_from).resolve()),
                             "data_hash": init_meta.get("data_hash"),
                             "train_scenes": init_meta.get("train_scenes")}
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: lr_factor(s, cfg.warmup_steps, cfg.steps, cfg.min_lr_ratio))
    rng = np.random.default_rng([cfg.seed, 60])
    step0, cpu0 = 0, 0.0
    curve_path = out / "loss.jsonl"
    if resume and ckpt_path.is_file():
        st = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        _check_resume(st, ckpt_path, cfg_json, meta)
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        rng.bit_generator.state = st["np_rng"]
        torch.set_rng_state(st["torch_rng"])
        step0, cpu0 = int(st["step"]), float(st["cpu_seconds"])
        say(f"train-fixer: resumed from {ckpt_path} at step {step0}")
    elif resume and final_path.is_file():
        st = torch.load(final_path, map_location="cpu", weights_only=False)
        _check_resume(st, final_path, cfg_json, meta)
        raise RunExistsError(f"{out} holds a finished fixer run ({final_path}) and no resume "
                             "checkpoint; pick another out folder")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    if curve_path.is_file():  # keep the curve up to the resume point only
        rows = [r for r in (json.loads(line) for line in curve_path.read_text().splitlines()
                            if line.strip()) if r["step"] <= step0]
    write_bytes_atomic(curve_path, "".join(json.dumps(r) + "\n" for r in rows).encode())

    def checkpoint(step: int, cpu: float) -> None:
        with atomic_path(ckpt_path) as tmp:
            torch.save(dict(format=CHECKPOINT_FORMAT + "+resume", model=model.state_dict(),
                            optimizer=opt.state_dict(), scheduler=sched.state_dict(),
                            np_rng=rng.bit_generator.state, torch_rng=torch.get_rng_state(),
                            step=step, cpu_seconds=cpu, config=cfg_json, **meta), tmp)

    say(f"train-fixer: {len(pool)} pairs from {len(tr_scenes)} scenes "
        f"({', '.join(tr_scenes)}), held out {', '.join(holdout) or '-'}; "
        f"{n_params(model):,} parameters, patches {P}x{P} x {cfg.batch_size}, "
        f"{cfg.steps} steps" + (f" or {cfg.max_cpu_seconds:.0f} CPU s" if cfg.max_cpu_seconds
                                else ""))
    model.train()
    c_start, t_start = time.process_time(), time.perf_counter()
    t_last, n_last = t_start, 0
    step, stopped = step0, "steps"
    acc: dict[str, list[float]] = {}
    for step in range(step0, cfg.steps):
        x, y, m = pool.batch(rng, cfg.batch_size, P, cfg.flip, cfg.color_jitter)
        fixed, conf = model(x)
        loss, parts = fixer_loss(fixed, conf, y, m, cfg.lambda_ssim, cfg.lambda_conf,
                                 cfg.conf_tau)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        lr = opt.param_groups[0]["lr"]
        opt.step()
        sched.step()
        n_last += 1
        rec = {"step": step + 1, "loss": float(loss.detach()), **parts, "lr": lr,
               "psnr_render": _psnr(x[:, :3], y, m), "psnr_fixed": _psnr(fixed.detach(), y, m)}
        for kk in ("loss", "l1", "ssim", "conf", "psnr_render", "psnr_fixed"):
            acc.setdefault(kk, []).append(rec[kk])
        cpu = cpu0 + time.process_time() - c_start
        done = step + 1
        if done % cfg.log_every == 0 or done == cfg.steps:
            now = time.perf_counter()
            ps = n_last * cfg.batch_size / max(now - t_last, 1e-9)
            t_last, n_last = now, 0
            avg = {kk: float(np.mean([v for v in vs if math.isfinite(v)] or [float("nan")]))
                   for kk, vs in acc.items()}
            acc = {}
            eta = (cfg.steps - done) * cfg.batch_size / max(ps, 1e-9)
            row = {"step": done, **avg, "lr": lr, "patches_s": ps, "cpu_s": cpu}
            rows.append(row)
            with open(curve_path, "a") as fh:
                fh.write(json.dumps(row) + "\n")
            rec.update(patches_s=ps, eta_s=eta)
            say(f"step {done:6d}/{cfg.steps}  loss {avg['loss']:.4f}  patch PSNR "
                f"{avg['psnr_render']:.2f} -> {avg['psnr_fixed']:.2f} dB  {ps:.1f} patches/s  "
                f"ETA {_fmt_time(eta)}")
        if done % cfg.ckpt_every == 0 or done == cfg.steps:
            checkpoint(done, cpu)
        if progress is not None:
            progress(done, cfg.steps, rec)
        if cfg.max_cpu_seconds and cpu >= cfg.max_cpu_seconds and done < cfg.steps:
            checkpoint(done, cpu)
            stopped = "cpu_seconds"
            say(f"train-fixer: CPU budget {cfg.max_cpu_seconds:.0f} s used at step {done}")
            break
    else:
        step = cfg.steps - 1
    steps_done = step + 1 if cfg.steps > step0 else step0
    cpu_total = cpu0 + time.process_time() - c_start
    model.eval()
    final = dict(format=CHECKPOINT_FORMAT, model=model.state_dict(),
                 model_config=cfg.model.model_dump(mode="json"), config=cfg_json,
                 steps=steps_done, stopped_by=stopped, cpu_seconds=cpu_total,
                 n_params=n_params(model), **meta)
    with atomic_path(final_path) as tmp:
        torch.save(final, tmp)

    # score held-out pairs (or, with none held out, training pairs) as whole images
    ev_scenes = holdout or tr_scenes
    ev_samples = [s for f in all_folders if f.parent.name in ev_scenes
                  for s in read_pair_folder(f)]
    if cfg.eval_pairs and len(ev_samples) > cfg.eval_pairs:
        pick = np.linspace(0, len(ev_samples) - 1, cfg.eval_pairs).round().astype(int)
        ev_samples = [ev_samples[i] for i in sorted(set(pick.tolist()))]
    elif not cfg.eval_pairs:
        ev_samples = []
    ev = _evaluate(model, ev_samples, k) if ev_samples else {"pairs": [], "sheet": []}
    if rows:
        plot_loss(rows, out / "loss.png")
    if ev["sheet"]:
        contact_sheet(ev["sheet"][:4], out / "contact.png")
    p = ev["pairs"]
    metrics = {
        "out": str(out), "checkpoint": str(final_path), "steps": steps_done,
        "resumed_from": step0, "stopped_by": stopped, "seed": cfg.seed,
        "cpu_seconds": cpu_total, "wall_seconds": time.perf_counter() - t_start,
        "n_params": n_params(model), **meta,
        "eval_on": "holdout" if holdout else "train",
        "eval_psnr_render": _mean(r["psnr_render"] for r in p),
        "eval_psnr_fixed": _mean(r["psnr_fixed"] for r in p),
        "eval_ssim_render": _mean(r["ssim_render"] for r in p),
        "eval_ssim_fixed": _mean(r["ssim_fixed"] for r in p),
        "eval_pairs": p,
        "final_loss": rows[-1]["loss"] if rows else None,
        "loss_curve": str(curve_path), "loss_png": str(out / "loss.png"),
        "contact_png": str(out / "contact.png"),
    }
    write_json_atomic(out / "metrics.json", metrics)
    if p:
        say(f"train-fixer: {metrics['eval_on']} pairs ({len(p)}): PSNR "
            f"{metrics['eval_psnr_render']:.2f} -> {metrics['eval_psnr_fixed']:.2f} dB, SSIM "
            f"{metrics['eval_ssim_render']:.3f} -> {metrics['eval_ssim_fixed']:.3f}")
    say(f"train-fixer: wrote {final_path}")
    return metrics


def _check_resume(st: dict, path: Path, cfg_json: dict, meta: dict) -> None:
    if not isinstance(st, dict) or not str(st.get("format", "")).startswith(CHECKPOINT_FORMAT):
        raise ResumeMismatchError(f"{path} is not a fixer checkpoint; remove it or pick "
                                  "another out folder")
    if st.get("pairs_root") != meta["pairs_root"]:
        raise ResumeMismatchError(f"{path} was trained on pairs {st.get('pairs_root')}, not "
                                  f"{meta['pairs_root']}; pick another out folder")
    if st.get("holdout_scenes") != meta["holdout_scenes"]:
        raise ResumeMismatchError(f"{path} held out {st.get('holdout_scenes')}, not "
                                  f"{meta['holdout_scenes']}; pick another out folder")
    if st.get("data_hash") != meta["data_hash"] or st.get("train_scenes") != meta["train_scenes"]:
        raise ResumeMismatchError(f"{path}: the pairs under {meta['pairs_root']} changed since "
                                  f"the run started (data hash {st.get('data_hash')} -> "
                                  f"{meta['data_hash']}); pick another out folder")
    a = {kk: v for kk, v in (st.get("config") or {}).items() if kk not in _RESUME_FREE}
    b = {kk: v for kk, v in cfg_json.items() if kk not in _RESUME_FREE}
    if a != b:
        diff = sorted(kk for kk in set(a) | set(b) if a.get(kk) != b.get(kk))
        raise ResumeMismatchError(f"{path} was written with another config ({', '.join(diff)} "
                                  "differ); pick another out folder")
