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
    python -m benchmarks.loader --store data/sample-store --remote [--views-per-shard 32]

``--remote``: the same shards also packed into a bucket of a moto S3 server started on
127.0.0.1 (a subprocess; no traffic leaves loopback), then the streaming reader
(``ShardIterableDataset``) is timed over one whole epoch each (worker start-up and the first
batch included, every shard read once) from the local folder, from the bucket with a cold
cache (a fresh cache folder) and with a warm one (the folder the cold epoch filled), at 0 and
2 workers. Besides samples/s and MB/s of delivered images, it prints the fetch rate of shard
bytes from the bucket and what that rate means at one sample per scene (the worst case: every
sample a new scene).
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
    ap.add_argument("--remote", action="store_true",
                    help="also stream the shards from a loopback moto S3 server")
    ap.add_argument("--views-per-shard", type=int, default=256,
                    help="shard capacity when packing (several shards: cold fetches count)")
    a = ap.parse_args()
    if a.remote:
        return main_remote(a)

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
            pack(s, out, resolution=a.resolution, views_per_shard=a.views_per_shard)
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


# --------------------------------------------------------------------------- --remote
def moto_server():
    """``(process, env)`` of a moto S3 server on 127.0.0.1 (a subprocess, so the server's
    Python does not share this process's GIL)."""
    import socket
    import subprocess

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p",
                             str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing",
           "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}
    os.environ.update(env)
    import s3fs

    t0 = time.monotonic()
    while True:
        try:
            s3fs.S3FileSystem.clear_instance_cache()
            s3fs.S3FileSystem().mkdir("bench")
            return proc, env
        except Exception:  # noqa: BLE001 - not up yet
            if time.monotonic() - t0 > 30 or proc.poll() is not None:
                proc.kill()
                raise SystemExit("moto server did not start (pip install 'moto[server]')")
            time.sleep(0.3)


def measure_epoch(ds, workers: int, batch: int) -> dict:
    """One whole epoch, from ``iter()`` to the last batch (start-up included)."""
    dl = torch.utils.data.DataLoader(ds, batch_size=batch, num_workers=workers,
                                     persistent_workers=False, drop_last=False)
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        n = nbytes = 0
        for b in dl:
            n += b["images"].shape[0]
            nbytes += b["images"].numel() * 4
        dt = time.perf_counter() - t0
    return {"samples_s": n / dt, "mb_s": nbytes / dt / 2 ** 20, "peak_mb": mem.peak_mb,
            "samples": n, "seconds": dt}


def main_remote(a) -> int:
    import shutil

    from freescale_core.store.dataset import (RandomViewSampler, ShardDataset,
                                              ShardIterableDataset)
    from freescale_core.store.shards import pack, read_manifest
    from freescale_core.store.shards_remote import _split, fetch_shard

    if not a.store:
        raise SystemExit("--remote needs --store STORE (packed into a folder and a bucket)")
    proc, env = moto_server()
    try:
        tmp = Path(tempfile.mkdtemp(prefix="freescale-bench-remote-"))
        out, url = tmp / "shards", "s3://bench/shards"
        t0 = time.perf_counter()
        for s in a.store:
            pack(s, out, resolution=a.resolution, views_per_shard=a.views_per_shard)
        t_local = time.perf_counter() - t0
        t0 = time.perf_counter()
        for s in a.store:
            pack(s, url, resolution=a.resolution, views_per_shard=a.views_per_shard)
        t_url = time.perf_counter() - t0
        m = read_manifest(out).to_pylist()
        shard_bytes = {r["shard"]: r["shard_bytes"] for r in m}
        n_scenes = len(m)
        total = sum(shard_bytes.values())
        print(f"packed {a.store}: {len(shard_bytes)} shards, {n_scenes} scenes, "
              f"{sum(r['n_views'] for r in m)} views at {a.resolution} px, "
              f"{total / 2**20:.1f} MB; into a folder {t_local:.1f} s, into the bucket "
              f"{t_url:.1f} s")
        # raw fetch rate: every shard once, sequentially, hashed (what a cold cache does)
        fs, base, u = _split(url)
        fetch = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            for r in {r["shard"]: r for r in read_manifest(url).to_pylist()}.values():
                fetch_shard(fs, base, u, r["shard_path"], r["shard_sha256"])
            fetch.append(total / (time.perf_counter() - t0) / 2**20)
        fetch_mb_s = statistics.median(fetch)
        need = a.batch * (a.batches + 1)
        sps = -(-need // n_scenes)
        if a.sampler == "lvsm":
            from freescale_core.downstream.lvsm.sampler import ViewSampler

            sampler = ViewSampler(n_input=4, n_target=2)
        else:
            sampler = RandomViewSampler(4, 2)
        rows = []
        for workers in (0, 2):
            reps = {"local": [], "s3 cold": [], "s3 warm": []}
            for r in range(a.repeats):
                kw = dict(sampler=sampler, seed=r, samples_per_scene=sps)
                reps["local"].append(measure_epoch(ShardIterableDataset(out, **kw), workers,
                                                   a.batch))
                cache = tmp / f"cache-{workers}-{r}"
                reps["s3 cold"].append(measure_epoch(
                    ShardIterableDataset(url, cache_dir=cache, **kw), workers, a.batch))
                reps["s3 warm"].append(measure_epoch(
                    ShardIterableDataset(url, cache_dir=cache, **kw), workers, a.batch))
                shutil.rmtree(cache, ignore_errors=True)
            for src, xs in reps.items():
                rows.append({"source": src, "num_workers": workers,
                             "samples_s": statistics.median(x["samples_s"] for x in xs),
                             "mb_s": statistics.median(x["mb_s"] for x in xs),
                             "peak_mb": max(x["peak_mb"] for x in xs),
                             "samples_s_all": [round(x["samples_s"], 1) for x in xs]})
        batch = next(iter(torch.utils.data.DataLoader(
            ShardDataset(out, sampler=sampler, samples_per_scene=sps), batch_size=a.batch)))
        steps = lvsm_step_seconds(batch, 4, max(5, a.repeats * 2))
    finally:
        proc.kill()
        proc.wait()
    step = statistics.median(steps)
    consume = a.batch / step
    per_scene_mb = total / n_scenes / 2**20
    scenes_s = fetch_mb_s / per_scene_mb
    if a.json:
        for r in rows:
            print(json.dumps({**r, "lvsm_step_s": step, "ratio": r["samples_s"] / consume}))
        print(json.dumps({"fetch_mb_s": fetch_mb_s, "fetch_all": fetch, "scenes_s": scenes_s,
                          "lvsm_step_s": step, "ratio_one_sample_per_scene":
                          scenes_s / consume}))
        return 0
    print(f"\nsampler: {type(sampler).__name__}, {sps} samples per scene per epoch "
          f"({n_scenes} scenes, {len(shard_bytes)} shards); LVSM step (cpu preset = "
          f"train-lvsm default: d=128, 4 layers, {batch['images'].shape[-1]} px, 4+2 views, "
          f"batch {a.batch}, torch threads {torch.get_num_threads()}): median "
          f"{step * 1e3:.0f} ms over {len(steps)} steps -> consumes {consume:.1f} samples/s")
    print(f"\n| source | num_workers | samples/s (median of {a.repeats}, whole epoch) | MB/s "
          "| peak RSS MB | x LVSM step | runs |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['source']} | {r['num_workers']} | {r['samples_s']:.1f} | {r['mb_s']:.1f} "
              f"| {r['peak_mb']:.0f} | {r['samples_s'] / consume:.1f}x | {r['samples_s_all']} |")
    print(f"\nshard fetch from the bucket (every shard once, hashed; median of {a.repeats}): "
          f"{fetch_mb_s:.1f} MB/s {[round(x, 1) for x in fetch]}; at {per_scene_mb:.2f} MB per "
          f"scene that is {scenes_s:.1f} scenes/s, i.e. {scenes_s / consume:.1f}x the step's "
          f"consumption at one sample per scene")
    return 0


if __name__ == "__main__":
    sys.exit(main())
