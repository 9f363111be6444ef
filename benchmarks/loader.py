"""Training-shard loader throughput vs an LVSM training step on the CPU.

Packs the given store(s) into shards (or reads existing shards), then measures, for the
map-style ``ShardDataset`` and the streaming ``ShardIterableDataset`` at ``num_workers`` 0
and 2: samples/s, MB/s of delivered image tensors (float32) and the peak resident memory of
the process and its workers. Views are drawn by the LVSM view sampler
(``freescale_core.downstream.lvsm.sampler.ViewSampler``, 4 inputs + 2 targets; ``--sampler
random`` for the default random one). In the same run it times one training step (forward,
backward, AdamW) of the project's LVSM (``freescale_core.downstream.lvsm.model``) at its CPU
default (d=128, 4 layers, 64 px, patch 8, 4 inputs + 2 targets, batch 8) on a real batch,
and prints the ratio of loader rate to the rate a training step consumes samples.

    python -m benchmarks.loader --store data/sample-store [--store /tmp/real] [--repeats 3]
    python -m benchmarks.loader --shards /tmp/shards
"""

from __future__ import annotations

import os
import sys

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path

import torch


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


# --------------------------------------------------------------------------- LVSM step
def lvsm_step_seconds(batch: dict, n_input: int, repeats: int) -> list[float]:
    """Wall seconds of ``repeats`` training steps (after two warm-up steps)."""
    from freescale_core.downstream.lvsm.model import LVSM, loss
    from schemas.lvsm import LVSMModelConfig

    torch.manual_seed(0)
    model = LVSM(LVSMModelConfig.preset("cpu"))
    opt = torch.optim.AdamW(model.parameters(), lr=4e-4)
    im, K, P = batch["images"], batch["fxfycxcy"], batch["world_from_cam"]
    i, t = slice(0, n_input), slice(n_input, None)
    times = []
    for k in range(repeats + 2):
        t0 = time.perf_counter()
        pred = model(im[:, i], P[:, i], K[:, i], P[:, t], K[:, t])
        lo = loss(pred, im[:, t], batch["target_weight"])
        opt.zero_grad()
        lo.backward()
        opt.step()
        if k >= 2:
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
    ap.add_argument("--sampler", choices=["lvsm", "random"], default="lvsm")
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
    if a.sampler == "lvsm":
        from freescale_core.downstream.lvsm.sampler import ViewSampler

        sampler = ViewSampler(n_input=4, n_target=2)
    else:
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
    steps = lvsm_step_seconds(batch, 4, max(5, a.repeats * 2))
    step = statistics.median(steps)
    consume = a.batch / step
    if a.json:
        for r in rows:
            print(json.dumps({**r, "lvsm_step_s": step, "ratio": r["samples_s"] / consume}))
        return 0
    print(f"\nsampler: {type(sampler).__name__}; LVSM step (cpu preset: d=128, 4 layers, "
          f"{batch['images'].shape[-1]} px, 4+2 views, batch {a.batch}, "
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
