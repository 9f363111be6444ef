"""Inference speed of the fixer network (``freescale_core.fixer.model``) on this machine.

Prints the parameter count and, per image size, the median wall seconds and CPU seconds
(process time, all threads) per view over ``--repeats`` batches of ``--batch`` views (random weights: the cost does not depend on them), and what
fixing 100 views costs at that rate. The goal (issue 60): 100 views at 256x192 in <= 10 s on
two CPU cores. On a shared machine the wall time depends on the load; the CPU time / threads
is what an idle machine's wall time would be.

    .venv/bin/python -m benchmarks.fixer_speed
    .venv/bin/python -m benchmarks.fixer_speed --base 24 --levels 3 --threads 2 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from freescale_core.fixer.infer import fix_tensor
from freescale_core.fixer.model import FixerNet, n_params
from schemas.fixer import FixerModelConfig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["256x192", "512x384"], help="WxH")
    ap.add_argument("--k", type=int, default=None)
    ap.add_argument("--base", type=int, default=None, help="base channels (None: default)")
    ap.add_argument("--levels", type=int, default=None)
    ap.add_argument("--blocks", type=int, default=None)
    ap.add_argument("--unshuffle", type=int, default=None)
    ap.add_argument("--batch", type=int, default=8, help="views per forward call")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (None: default)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    over = {k: v for k, v in dict(k=a.k, base_channels=a.base, levels=a.levels,
                                  blocks=a.blocks, unshuffle=a.unshuffle).items() if v is not None}
    cfg = FixerModelConfig(**over)
    torch.manual_seed(0)
    model = FixerNet(cfg).eval()
    for p in model.parameters():  # non-zero head: the whole graph runs as trained
        p.data.normal_(0, 0.05)
    rows = []
    for size in a.sizes:
        W, H = (int(v) for v in size.lower().split("x"))
        x = torch.rand(a.batch, cfg.in_channels, H, W)
        fix_tensor(model, x, a.batch)  # warm-up
        ts, cs = [], []
        for _ in range(a.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fix_tensor(model, x, a.batch)
            ts.append((time.perf_counter() - t0) / a.batch)
            cs.append((time.process_time() - c0) / a.batch)
        med = statistics.median(ts)
        rows.append(dict(size=f"{W}x{H}", s_per_view=med, s_per_100_views=100 * med,
                         cpu_s_per_view=statistics.median(cs),
                         params=n_params(model), threads=torch.get_num_threads(),
                         batch=a.batch, repeats=a.repeats, **cfg.model_dump()))
    if a.json:
        for r in rows:
            print(json.dumps(r))
    else:
        print(f"fixer {cfg.model_dump()}  params {n_params(model):,}  "
              f"threads {torch.get_num_threads()}  batch {a.batch}  repeats {a.repeats}")
        print("| size | median s/view (wall) | s per 100 views (wall) | median CPU s/view |")
        print("|---|---|---|---|")
        for r in rows:
            print(f"| {r['size']} | {r['s_per_view']:.4f} | {r['s_per_100_views']:.1f} "
                  f"| {r['cpu_s_per_view']:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
