"""Training-shard loader throughput vs an LVSM training step on the CPU.

Packs the given store(s) into shards (or reads existing shards), then measures, for the
map-style ``ShardDataset`` and the streaming ``ShardIterableDataset`` at ``num_workers`` 0
and 2: samples/s, MB/s of delivered image tensors (float32) and the peak resident memory of
the process and its workers. In the same run it times one training step (forward, backward,
AdamW) of a stand-in for LVSM's decoder-only transformer at its CPU default (d=128, 4 layers,
64 px, patch 8, 4 inputs + 2 targets, batch 8) and prints the ratio.

    benchmarks/loader.py --store data/sample-store [--store /tmp/real] [--repeats 3]
    benchmarks/loader.py --shards /tmp/shards

The stand-in: each view is patchified (8x8) with its per-pixel Plucker rays (6 channels, from
the sample's own intrinsics and poses); input tokens carry RGB + rays (9 x 64 values), target
tokens rays only (6 x 64); for each target, [its 64 tokens + all 4 x 64 input tokens] go
through 4 pre-norm transformer blocks (4 heads), and a linear head predicts the target patch
RGB (MSE). That is LVSM's decoder-only design at this size; replace it with the real model
when ``freescale_core.downstream.lvsm`` has one.
"""

from __future__ import annotations

import os
import sys

# benchmarks/select.py shadows the stdlib ``select``: drop this folder from sys.path first.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402


class PeakRSS:
    """Peak resident memory (MB) of this process + its children, sampled every 10 ms."""

    def __init__(self):
        import psutil

        self.p = psutil.Process()
        self.peak = 0
        self._stop = threading.Event()

    def _rss(self) -> int:
        total = self.p.memory_info().rss
        for c in self.p.children(recursive=True):
            try:
                total += c.memory_info().rss
            except Exception:
                pass
        return total

    def __enter__(self):
        self.peak = self._rss()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(0.01)

    def __exit__(self, *a):
        self._stop.set()
        self.t.join()
        self.peak_mb = self.peak / 2 ** 20


def measure_loader(ds, workers: int, batch: int, n_batches: int) -> dict:
    dl = torch.utils.data.DataLoader(ds, batch_size=batch, num_workers=workers,
                                     persistent_workers=False, drop_last=True)
    with PeakRSS() as mem:
        it = iter(dl)
        next(it)  # warm-up: worker start-up and first reads are not throughput
        t0 = time.perf_counter()
        n = nbytes = 0
        for _ in range(n_batches):
            try:
                b = next(it)
            except StopIteration:
                break
            n += b["images"].shape[0]
            nbytes += b["images"].numel() * 4
        dt = time.perf_counter() - t0
        del it
    return {"samples_s": n / dt, "mb_s": nbytes / dt / 2 ** 20, "peak_mb": mem.peak_mb,
            "samples": n}


# --------------------------------------------------------------------------- LVSM stand-in
def plucker(fxfycxcy: torch.Tensor, c2w: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """[B, V, 6, H, W] Plucker rays (direction, origin x direction) in OpenCV axes."""
    B, V = fxfycxcy.shape[:2]
    y, x = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    fx, fy, cx, cy = (fxfycxcy[..., i, None, None] for i in range(4))
    d = torch.stack([(x - cx) / fx, (y - cy) / fy, torch.ones_like(x).expand(B, V, H, W)], -1)
    d = torch.einsum("bvij,bvhwj->bvhwi", c2w[..., :3, :3], d)
    d = torch.nn.functional.normalize(d, dim=-1)
    o = c2w[..., None, None, :3, 3].expand_as(d)
    return torch.cat([d, torch.cross(o, d, dim=-1)], -1).permute(0, 1, 4, 2, 3)


class StandIn(torch.nn.Module):
    def __init__(self, d=128, layers=4, heads=4, patch=8):
        super().__init__()
        self.p = patch
        self.inp = torch.nn.Linear(9 * patch * patch, d)
        self.tgt = torch.nn.Linear(6 * patch * patch, d)
        layer = torch.nn.TransformerEncoderLayer(d, heads, 4 * d, dropout=0.0,
                                                 batch_first=True, norm_first=True)
        self.blocks = torch.nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = torch.nn.LayerNorm(d)
        self.out = torch.nn.Linear(d, 3 * patch * patch)

    def tokens(self, x):  # [B, V, C, H, W] -> [B, V, T, C p p]
        B, V, C, H, W = x.shape
        p = self.p
        x = x.reshape(B, V, C, H // p, p, W // p, p).permute(0, 1, 3, 5, 2, 4, 6)
        return x.reshape(B, V, (H // p) * (W // p), C * p * p)

    def forward(self, images, rays, n_in):
        B, V, _, H, W = images.shape
        inp = self.inp(self.tokens(torch.cat([images[:, :n_in], rays[:, :n_in]], 2)))
        tgt = self.tgt(self.tokens(rays[:, n_in:]))  # [B, Vt, T, d]
        Vt, T = tgt.shape[1], tgt.shape[2]
        ctx = inp.reshape(B, 1, n_in * T, -1).expand(B, Vt, n_in * T, inp.shape[-1])
        seq = torch.cat([tgt, ctx], 2).reshape(B * Vt, T + n_in * T, -1)
        h = self.norm(self.blocks(seq))[:, :T]
        return self.out(h).reshape(B, Vt, T, -1)


def lvsm_step_seconds(batch: dict, repeats: int) -> list[float]:
    torch.manual_seed(0)
    model = StandIn()
    opt = torch.optim.AdamW(model.parameters(), lr=4e-4)
    imgs, n_in = batch["images"], 4
    H, W = imgs.shape[-2:]
    times = []
    for k in range(repeats + 2):
        t0 = time.perf_counter()
        rays = plucker(batch["fxfycxcy"], batch["world_from_cam"], H, W)
        pred = model(imgs, rays, n_in)
        loss = torch.nn.functional.mse_loss(pred, model.tokens(imgs[:, n_in:]))
        opt.zero_grad()
        loss.backward()
        opt.step()
        if k >= 2:  # two warm-up steps
            times.append(time.perf_counter() - t0)
    return times


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", action="append", default=[], help="store(s) to pack")
    ap.add_argument("--shards", default=None, help="existing shard folder (skips packing)")
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--batches", type=int, default=40, help="timed batches per measurement")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()

    from freescale_core.store.dataset import (RandomViewSampler, ShardDataset,
                                              ShardIterableDataset)
    from freescale_core.store.shards import pack, read_manifest

    if a.shards:
        out = Path(a.shards)
    else:
        if not a.store:
            ap.error("give --store STORE (e.g. data/sample-store from `make run`) or --shards")
        out = Path(tempfile.mkdtemp(prefix="freescale-bench-shards-")) / "shards"
        t0 = time.perf_counter()
        for s in a.store:
            pack(s, out, resolution=a.resolution, views_per_shard=256)
        print(f"packed {a.store} -> {out} in {time.perf_counter() - t0:.1f} s")
    m = read_manifest(out)
    print(f"shards: {len(set(m.column('shard').to_pylist()))}, scenes: {m.num_rows}, views: "
          f"{sum(m.column('n_views').to_pylist())}, resolution {m.column('resolution')[0]}")
    need = a.batch * (a.batches + 1)
    sps = -(-need // m.num_rows)
    sampler = RandomViewSampler(4, 2)
    rows = []
    for kind, cls in (("map", ShardDataset), ("iterable", ShardIterableDataset)):
        for workers in (0, 2):
            reps = []
            for r in range(a.repeats):
                ds = cls(out, sampler=sampler, seed=r, samples_per_scene=sps)
                reps.append(measure_loader(ds, workers, a.batch, a.batches))
            rows.append({"dataset": kind, "num_workers": workers,
                         "samples_s": statistics.median(x["samples_s"] for x in reps),
                         "mb_s": statistics.median(x["mb_s"] for x in reps),
                         "peak_mb": max(x["peak_mb"] for x in reps),
                         "samples_s_all": [round(x["samples_s"], 1) for x in reps]})
    batch = next(iter(torch.utils.data.DataLoader(ShardDataset(out, sampler=sampler,
                                                               samples_per_scene=sps),
                                                  batch_size=a.batch)))
    steps = lvsm_step_seconds(batch, max(5, a.repeats * 2))
    step = statistics.median(steps)
    consume = a.batch / step
    if a.json:
        for r in rows:
            print(json.dumps({**r, "lvsm_step_s": step, "ratio": r["samples_s"] / consume}))
        return 0
    print(f"\nLVSM stand-in step (d=128, 4 layers, 64 px, 4+2 views, batch {a.batch}, "
          f"torch threads {torch.get_num_threads()}): median {step * 1e3:.0f} ms over "
          f"{len(steps)} steps -> consumes {consume:.1f} samples/s")
    print(f"\n| dataset | num_workers | samples/s (median of {a.repeats}) | MB/s | peak RSS MB "
          "| x LVSM step | runs |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['dataset']} | {r['num_workers']} | {r['samples_s']:.0f} | {r['mb_s']:.0f} "
              f"| {r['peak_mb']:.0f} | {r['samples_s'] / consume:.1f}x | {r['samples_s_all']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
