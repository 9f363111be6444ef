"""Micro-benchmark of the SSIM loss (freescale_core.recon.losses.ssim_map) on CPU.

Forward and forward+backward milliseconds of ``ssim(img, ref)`` (mean of the SSIM map, the
gradient w.r.t. ``img`` only, as in training) at 128x96, 256x192 and 512x384, float32, one
torch thread and one numba thread, per implementation:

* ``torch``: the reference, five separable 11-tap blurs by depthwise ``F.conv2d``, autograd
  backward (ten convolutions replayed);
* ``torch-analytic``: candidate, the same ``F.conv2d`` blurs (one grouped call over the five
  stacked moment maps) with the analytic backward of ``fused_ssim`` (three transposed blurs);
  kept here only as a measurement;
* ``fused``: numba forward and analytic backward (:mod:`freescale_core.recon.fused_ssim`).

The arms alternate inside every repeat (so load drift hits all of them); each cell is the
median over the repeats and the ratio is old / new of those medians from the same run. Times
are process-CPU milliseconds (``time.process_time``: with one torch and one numba thread that is
the work done, and it does not count the time the process waits for a core on a loaded
machine); ``--clock wall`` times wall-clock instead.

    python -m lab.ssim               # 9 repeats
    python -m lab.ssim --repeats 15 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
import torch.nn.functional as F

from freescale_core.recon import fused_ssim as fs
from freescale_core.recon.losses import SSIM_C1, SSIM_C2, gaussian_window, ssim_map

SIZES = [(128, 96), (256, 192), (512, 384)]


class _TorchAnalytic(torch.autograd.Function):
    """Candidate: F.conv2d blurs, analytic backward (the formulas of fused_ssim)."""

    @staticmethod
    def forward(ctx, x, y):  # [1, C, H, W]
        c = x.shape[1]
        w = gaussian_window(dtype=x.dtype)
        k = w.numel()
        wr = w.view(1, 1, 1, k).expand(5 * c, 1, 1, k)
        wc = w.view(1, 1, k, 1).expand(5 * c, 1, k, 1)
        m = torch.cat([x, y, x * x, y * y, x * y], 1)
        m = F.conv2d(F.conv2d(m, wr, groups=5 * c), wc, groups=5 * c)
        mx, my, mxx, myy, mxy = m.split(c, 1)
        a1 = 2 * mx * my + SSIM_C1
        a2 = 2 * (mxy - mx * my) + SSIM_C2
        b1 = mx * mx + my * my + SSIM_C1
        b2 = (mxx - mx * mx) + (myy - my * my) + SSIM_C2
        bb = b1 * b2
        s = a1 * a2 / bb
        d = torch.cat([2 * my * (a2 - a1) / bb + mx * (2 * s * (1 / b2 - 1 / b1)),
                       -s / b2, 2 * a1 / bb], 1)
        ctx.save_for_backward(x, y, d)
        ctx.k = k
        return s

    @staticmethod
    def backward(ctx, g):
        x, y, d = ctx.saved_tensors
        c, k = x.shape[1], ctx.k
        w = gaussian_window(dtype=x.dtype)
        wr = w.view(1, 1, 1, k).expand(3 * c, 1, 1, k)
        wc = w.view(1, 1, k, 1).expand(3 * c, 1, k, 1)
        t = d * g.repeat(1, 3, 1, 1)
        t = F.conv2d(F.pad(t, (k - 1, k - 1, k - 1, k - 1)), wr, groups=3 * c)
        t = F.conv2d(t, wc, groups=3 * c)
        ta, tb, tc = t.split(c, 1)
        return ta + 2 * x * tb + y * tc, None


def torch_analytic_map(img, ref):
    return _TorchAnalytic.apply(img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None])[0]


ARMS = {"torch": lambda a, b: ssim_map(a, b, "torch"),
        "torch-analytic": torch_analytic_map,
        "fused": fs.fused_ssim_map}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--clock", choices=["cpu", "wall"], default="cpu")
    a = ap.parse_args(argv)
    import numba

    clock = time.process_time if a.clock == "cpu" else time.perf_counter
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    rows = []
    for w, h in SIZES:
        g = torch.Generator().manual_seed(0)
        ref = torch.rand(h, w, 3, generator=g)
        img = (ref + 0.1 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
        times = {(n, m): [] for n in ARMS for m in ("fwd", "fwd+bwd")}
        vals = {}
        for n, f in ARMS.items():  # warm-up (numba compile / load from cache)
            x = img.clone().requires_grad_(True)
            f(x, ref).mean().backward()
        for _ in range(a.repeats):
            for n, f in ARMS.items():
                t0 = clock()
                with torch.no_grad():
                    vals[n] = float(f(img, ref).mean())
                t1 = clock()
                x = img.clone().requires_grad_(True)
                f(x, ref).mean().backward()
                t2 = clock()
                times[(n, "fwd")].append(1e3 * (t1 - t0))
                times[(n, "fwd+bwd")].append(1e3 * (t2 - t1))
        med = {k: statistics.median(v) for k, v in times.items()}
        for n in ARMS:
            rows.append({"size": f"{w}x{h}", "impl": n, "fwd_ms": med[(n, "fwd")],
                         "fwd_bwd_ms": med[(n, "fwd+bwd")],
                         "ratio_fwd": med[("torch", "fwd")] / med[(n, "fwd")],
                         "ratio_fwd_bwd": med[("torch", "fwd+bwd")] / med[(n, "fwd+bwd")],
                         "ssim_minus_torch": vals[n] - vals["torch"], "repeats": a.repeats,
                         "clock": a.clock})
            if a.json:
                print(json.dumps(rows[-1]), flush=True)
    if not a.json:
        print(f"{a.clock} ms, median of {a.repeats} repeats, torch threads 1, numba threads 1; "
              "ratio = torch / impl (same run)")
        print("| size | impl | fwd ms | fwd+bwd ms | ratio fwd | ratio fwd+bwd | SSIM - torch |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['size']} | {r['impl']} | {r['fwd_ms']:.1f} | {r['fwd_bwd_ms']:.1f} | "
                  f"{r['ratio_fwd']:.2f} | {r['ratio_fwd_bwd']:.2f} | "
                  f"{r['ssim_minus_torch']:+.1e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
