"""Train an LVSM from packed training shards (``freescale shards pack``): the ``train-lvsm``
flow's work, with no Prefect (METHOD.md "Downstream uses": LVSM).

:func:`load_shard_scenes` reads every scene of a shard folder through the store's
:class:`~freescale_core.store.dataset.ShardReader` into :class:`SceneTensors` (via
:func:`from_shard_record`, images resized from the shards' R x R to the model's side);
:func:`split_heldout` sets the held-out scenes and views aside (config
:class:`schemas.lvsm.TrainLVSMShardsConfig`); :func:`train_from_shards` runs
:func:`~freescale_core.downstream.lvsm.train.train_lvsm` on the rest and writes, in ``out``::

    ckpt/last.pt     model, optimiser, scheduler, RNG states, step, history (resume point)
    history.json     per-step train loss / PSNR / lr / it/s, held-out loss / PSNR
    loss.png         loss and PSNR curves (train, held-out)
    metrics.json     final and best numbers, scenes, timings
    split.json       which scenes and views were trained on and held out

A run killed at any point resumes from its last checkpoint (``resume=True``) and ends with
the same parameters and numbers as an uninterrupted run of the same seed and config.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freescale_core.downstream.lvsm.data import (
    SceneTensors,
    from_shard_record,
    resize_views,
)
from freescale_core.downstream.lvsm.sampler import SceneViews
from freescale_core.store.shards import manifest_sha256, shards_location
from freescale_core.store.store import write_json_atomic
from schemas.lvsm import TrainLVSMShardsConfig

__all__ = [
    "RunExistsError",
    "load_shard_scenes",
    "split_heldout",
    "subset_views",
    "train_from_shards",
]


class RunExistsError(FileExistsError):
    """``out`` already holds a checkpoint and the caller did not ask to resume."""


def load_shard_scenes(shards: str | Path, scenes: list[str] | None = None,
                      image_size: int | None = None) -> list[SceneTensors]:
    """Every (or the named) scene of a shard folder as :class:`SceneTensors`, sorted by id.

    Args:
        shards: folder written by ``freescale shards pack`` (``manifest.parquet`` + shards).
        scenes: scene ids to read (None: all).
        image_size: square side of the returned images (area-resized from the shards' R,
            intrinsics scaled); None keeps R.
    Returns:
        One record per scene: captured and free views, capture order, the view graph.
    """
    from freescale_core.store.dataset import ShardReader

    reader = ShardReader(shards, scenes)
    out = []
    for i, e in enumerate(reader.entries):
        sv = reader.scene_views(i)
        n = sv.n_views
        a = reader.load(i, np.arange(n), confidence=True)
        rgb, K = np.asarray(a["images"]), np.asarray(a["fxfycxcy"], np.float64)  # [V, R, R, 3]
        R = rgb.shape[1]
        S = R if image_size is None else int(image_size)
        imgs, K = resize_views(rgb, K, S, S)
        rec = {"images": imgs, "fxfycxcy": K, "world_from_cam": a["world_from_cam"],
               "is_free": sv.is_free, "frame_index": sv.frame_index, "edges": sv.edges}
        c8 = a.get("confidence")  # [V, R, R] uint8; all 255 (photos only) weighs nothing
        if c8 is not None and int(c8.min()) < 255:
            rec["confidence"] = resize_confidence(c8, S)
        out.append(from_shard_record(rec, scene_id=e["scene_id"]))
    return sorted(out, key=lambda s: s.scene_id)


def resize_confidence(c8: np.ndarray, S: int) -> np.ndarray:
    """Shard confidence ``[V, R, R]`` uint8 (x 255) -> ``[V, S, S]`` float32 in [0, 1], area
    resized like the images (:func:`resize_views`)."""
    import cv2

    c8 = np.asarray(c8)
    if c8.shape[1:] != (S, S):
        c8 = np.stack([cv2.resize(c, (S, S), interpolation=cv2.INTER_AREA) for c in c8])
    return c8.astype(np.float32) / 255.0


def subset_views(scene: SceneTensors, ids: np.ndarray, scene_id: str | None = None
                 ) -> SceneTensors:
    """The views ``ids`` (rows of ``scene``, kept in that order) with the view-graph edges
    among them, renumbered."""
    ids = np.asarray(ids, np.int64)
    pos = -np.ones(scene.views.n_views, np.int64)
    pos[ids] = np.arange(len(ids))
    src, dst, w = scene.views.edges
    keep = (pos[src] >= 0) & (pos[dst] >= 0)
    v = scene.views
    views = SceneViews(scene_id or v.scene_id, v.is_free[ids], v.frame_index[ids],
                       (pos[src[keep]], pos[dst[keep]], np.asarray(w)[keep]))
    t = torch.as_tensor(ids)
    return SceneTensors(views, scene.images[t], scene.K[t], scene.world_from_cam[t],
                        None if scene.confidence is None else scene.confidence[t])


def split_heldout(scenes: list[SceneTensors], cfg: TrainLVSMShardsConfig
                  ) -> tuple[list[SceneTensors], list[SceneTensors], dict[str, Any]]:
    """Training scenes, held-out scenes (captured views only) and a description of the split.

    Held out: ``cfg.heldout_scenes`` (default: the last ``cfg.n_heldout_scenes`` by id when
    there are at least 2 scenes), and the last ``heldout_tail`` share of every training
    capture (default 0.3 when no scene is held out) as a held-out record ``<id>#tail``; the
    tail's captured views leave the training scene, its free views stay (they were made from
    the whole capture: store made with ``recon_split=ood`` for a clean split).
    """
    ids = [s.scene_id for s in scenes]
    if cfg.heldout_scenes is not None:
        missing = sorted(set(cfg.heldout_scenes) - set(ids))
        if missing:
            raise ValueError(f"held-out scenes {missing} are not in the shards (scenes: {ids})")
        held = set(cfg.heldout_scenes)
    else:
        k = cfg.n_heldout_scenes if len(ids) >= 2 else 0
        held = set(sorted(ids)[len(ids) - k:]) if k else set()
    train = [s for s in scenes if s.scene_id not in held]
    if not train:
        raise ValueError(f"every scene is held out ({sorted(held)}): nothing to train on")
    tail = cfg.heldout_tail if cfg.heldout_tail is not None else (0.0 if held else 0.3)
    evals = [subset_views(s, np.flatnonzero(~s.views.is_free)) for s in scenes
             if s.scene_id in held]
    split: dict[str, Any] = {"train_scenes": [s.scene_id for s in train],
                             "heldout_scenes": sorted(held), "heldout_tail": tail,
                             "heldout_views": {}}
    if tail > 0:
        kept = []
        for s in train:
            cap = s.views.captured_order  # captured rows in capture order
            n_tail = round(tail * len(cap))
            if n_tail < cfg.min_heldout_frames or len(cap) - n_tail < 2:
                kept.append(s)
                continue
            tail_ids = cap[len(cap) - n_tail:]
            rest = np.setdiff1d(np.arange(s.views.n_views), tail_ids)
            kept.append(subset_views(s, rest))
            evals.append(subset_views(s, tail_ids, f"{s.scene_id}#tail"))
            split["heldout_views"][s.scene_id] = s.views.frame_index[tail_ids].tolist()
        train = kept
    return train, evals, split


def _mean(xs: list[float]) -> float | None:
    return float(np.mean(xs)) if xs else None


def _check_resume_split(out: Path, split: dict) -> None:
    """A resumed run must read the shards, split and manifest it started on: another folder
    would train on scenes it held out and rewrite ``split.json`` to claim a clean split."""
    p = out / "split.json"
    try:
        prev = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise RunExistsError(f"cannot resume {out}: its split.json is missing or unreadable "
                             f"({e}); start a new run in another folder") from e
    prev_shards = str(Path(prev.get("shards", "")).absolute())
    diffs = []
    if prev_shards != split["shards"]:
        diffs.append(f"shards {prev_shards} -> {split['shards']}")
    for k in ("train_scenes", "heldout_scenes", "heldout_views"):
        if k in prev and prev[k] != split[k]:
            diffs.append(f"{k} differ")
    if prev.get("manifest_sha256") and prev["manifest_sha256"] != split["manifest_sha256"]:
        diffs.append("the shard manifest changed since the run started")
    if diffs:
        raise RunExistsError(f"cannot resume {out} on other data: {'; '.join(diffs)}; resume "
                             f"with the same shards and split, or start a new run in another "
                             f"folder")


def train_from_shards(shards: str | Path, out: str | Path, cfg: TrainLVSMShardsConfig | None = None,
                      seed: int = 0, *, resume: bool = False,
                      log: Callable[[str], None] | None = print,
                      callback: Callable[[int, dict[str, Any]], None] | None = None
                      ) -> dict[str, Any]:
    """Train an LVSM on the shards' scenes, evaluate on the held-out ones at intervals.

    Args:
        shards: shard folder (``freescale shards pack STORE OUT``).
        out: run folder (checkpoint, history, loss curve, metrics).
        cfg: :class:`TrainLVSMShardsConfig` (training run, held-out split).
        seed: model init and example draws.
        resume: continue from ``out/ckpt/last.pt``; False with a checkpoint present raises
            :class:`RunExistsError` (nothing is overwritten).
        log: line logger (loss / PSNR / lr / it/s every ``log_every`` steps, held-out numbers).
        callback: ``(step, record)`` after every step (progress reporting; tests stop runs).
    Returns:
        The ``metrics.json`` record.
    """
    from freescale_core.downstream.lvsm.train import CKPT_NAME, train_lvsm

    cfg = cfg or TrainLVSMShardsConfig()
    say = log or (lambda _s: None)
    out = Path(out)
    ckpt = out / "ckpt" / CKPT_NAME
    if ckpt.is_file() and not resume:
        raise RunExistsError(f"{out} already holds a run (checkpoint {ckpt}); resume it or "
                             "pick another output folder")
    t0, c0 = time.perf_counter(), time.process_time()
    mcfg = cfg.train.model()
    scenes = load_shard_scenes(shards, cfg.scenes, mcfg.image_size)
    if not scenes:
        raise ValueError(f"no scenes in the shards at {shards}")
    train, evals, split = split_heldout(scenes, cfg)
    n_free = sum(int(s.views.is_free.sum()) for s in train)
    n_cap = sum(int((~s.views.is_free).sum()) for s in train)
    use_free = cfg.train.sampler.use_free_views
    say(f"train-lvsm: {len(train)} training scenes ({n_cap} captured + {n_free} free views"
        f"{'' if use_free else ', free views unused'}), held out: "
        f"{split['heldout_scenes'] or 'no scene'}"
        + (f" + the last {split['heldout_tail']:.0%} of each capture" if split["heldout_views"]
           else "")
        + f"; {mcfg.d_model}x{mcfg.n_layers} model at {mcfg.image_size} px, "
        f"{cfg.train.steps} steps x batch {cfg.train.batch_size}, seed {seed}")
    if not evals:
        say("train-lvsm: warning: nothing held out (set heldout_scenes or heldout_tail)")
    split.update(shards=shards_location(shards), n_captured_train=n_cap,
                 n_free_train=n_free, use_free_views=use_free,
                 manifest_sha256=manifest_sha256(shards))
    if resume and ckpt.is_file():
        _check_resume_split(out, split)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "split.json", split)
    t_load = time.perf_counter() - t0

    res = train_lvsm(train, cfg.train, seed=seed, out_dir=out, eval_scenes=evals or None,
                     resume=resume, log=say, callback=callback)
    h = res.history
    tr, ev = h["train"], h["eval"]
    last = tr[-10:]
    best = max(ev, key=lambda r: r["psnr"]) if ev else None
    its = [r["it_s"] for r in tr[res.resumed_from:] if "it_s" in r]
    metrics = {
        "shards": str(shards), "out": str(out), "seed": seed, "steps": cfg.train.steps,
        "resumed_from": res.resumed_from, "use_free_views": use_free,
        "train_scenes": split["train_scenes"], "heldout_scenes": split["heldout_scenes"],
        "heldout_tail_scenes": sorted(split["heldout_views"]),
        "n_captured_train": n_cap, "n_free_train": n_free,
        "free_target_share": (sum(r["n_free_targets"] for r in tr)
                              / max(1, len(tr) * cfg.train.batch_size)),
        "n_params": sum(p.numel() for p in res.model.parameters()),
        "final_train_loss": _mean([r["loss"] for r in last]),
        "final_train_psnr": _mean([r["psnr"] for r in last]),
        "heldout_loss": ev[-1]["loss"] if ev else None,
        "heldout_psnr": ev[-1]["psnr"] if ev else None,
        "best_heldout_psnr": best["psnr"] if best else None,
        "best_heldout_step": best["step"] if best else None,
        "it_s": _mean(its), "load_seconds": t_load,
        "wall_seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
        "checkpoint": str(ckpt), "loss_png": str(out / "loss.png"),
        "config": cfg.model_dump(mode="json"),
    }
    write_json_atomic(out / "metrics.json", metrics)
    say("train-lvsm: done: train loss {} / PSNR {} dB (last 10 steps), held-out loss {} / "
        "PSNR {} dB, {} it/s, {:.0f} s wall; {}".format(
            _fmt(metrics["final_train_loss"], 5), _fmt(metrics["final_train_psnr"], 2),
            _fmt(metrics["heldout_loss"], 5), _fmt(metrics["heldout_psnr"], 2),
            _fmt(metrics["it_s"], 2), metrics["wall_seconds"], out))
    return metrics


def _fmt(v: float | None, nd: int) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def read_metrics(out: str | Path) -> dict[str, Any]:
    """The ``metrics.json`` of a finished run folder."""
    return json.loads((Path(out) / "metrics.json").read_text())
