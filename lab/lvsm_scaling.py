"""Scaling of the LVSM experiment with model size: table and learning curves from runs of
``lab/lvsm.py`` at several sizes (arms A' and B22, same seeds, budget and scenes).

    python -m lab.lvsm_scaling /tmp/lvsm18-scale/*/results.json \\
        --png docs/img/lvsm_learning_curves.png

Prints per size and arm the off-path / small / large PSNR (mean ± std over seeds), the paired
gap B22 - A' per seed (mean ± std) and the seconds per run; draws held-out PSNR and loss
against steps (mean over seeds, one line per arm and size).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

REGIMES = ("small", "large", "offpath")


def load(paths: list[Path]) -> list[dict]:
    rows = []
    for p in paths:
        for r in json.loads(Path(p).read_text()).values():
            r.setdefault("d_model", 64), r.setdefault("n_layers", 2), r.setdefault("n_heads", 4)
            rows.append(r)
    return rows


def ms(v) -> str:
    v = np.asarray(v, float)
    return f"{v.mean():+.2f} ± {v.std():.2f}" if len(v) > 1 else f"{v.mean():+.2f}"


def m_s(v) -> str:
    v = np.asarray(v, float)
    return f"{v.mean():.2f} ± {v.std():.2f}" if len(v) > 1 else f"{v.mean():.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", nargs="+", type=Path)
    ap.add_argument("--arms", nargs=2, default=["A'", "B22"], help="baseline arm, treated arm")
    ap.add_argument("--ceiling", default="C", help="arm reported as a gap to the baseline "
                    "where every seed has it (C: oracle images at the free views' poses)")
    ap.add_argument("--png", type=Path, default=None)
    a = ap.parse_args()
    base, arm = a.arms
    rows = [r for r in load(a.results) if r["arm"] in (base, arm, a.ceiling)]
    by = defaultdict(dict)  # (size, steps) -> {(arm, seed): row}
    for r in rows:
        by[(r["d_model"], r["n_layers"], r["n_heads"], r["steps"])][(r["arm"], r["seed"])] = r
    print(f"| size (d x layers) | params | steps | seeds | {base} offpath | {arm} offpath "
          f"| gap offpath | gap small | gap large | s / run ({base}, {arm}) "
          f"| {a.ceiling} - {base} offpath / small / large |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    curves = {}
    for key in sorted(by):
        d, L, _h, steps = key
        runs = by[key]
        seeds = sorted({s for (_, s) in runs if (base, s) in runs and (arm, s) in runs})
        if not seeds:
            continue
        gap = {g: [runs[(arm, s)]["scores"][g]["psnr"] - runs[(base, s)]["scores"][g]["psnr"]
                   for s in seeds] for g in REGIMES}
        npar = next((r["n_params"] for k2, rs in by.items() if k2[:3] == key[:3]
                     for r in rs.values() if r.get("n_params")), None)
        npar_s = f"{npar / 1e6:.2f} M" if npar else "-"
        sec = [np.mean([runs[(x, s)]["seconds"] for s in seeds]) for x in (base, arm)]
        ceil = ""
        if all((a.ceiling, s) in runs for s in seeds):
            ceil = " / ".join(ms([runs[(a.ceiling, s)]["scores"][g]["psnr"]
                                  - runs[(base, s)]["scores"][g]["psnr"] for s in seeds])
                              for g in ("offpath", "small", "large"))
        print(f"| d{d} x {L} | {npar_s} | {steps} | {len(seeds)} | "
              f"{m_s([runs[(base, s)]['scores']['offpath']['psnr'] for s in seeds])} | "
              f"{m_s([runs[(arm, s)]['scores']['offpath']['psnr'] for s in seeds])} | "
              f"{ms(gap['offpath'])} | {ms(gap['small'])} | {ms(gap['large'])} | "
              f"{sec[0]:.0f}, {sec[1]:.0f} | {ceil} |")
        for x in (base, arm, a.ceiling):
            if not all((x, s) in runs for s in seeds):
                continue
            hs = [runs[(x, s)].get("heldout") for s in seeds]
            if all(hs):
                steps_ = [e["step"] for e in hs[0]]
                curves[(f"d{d}x{L}", x)] = (
                    steps_, np.mean([[e["psnr"] for e in hh] for hh in hs], 0),
                    np.mean([[e["loss"] for e in hh] for hh in hs], 0), len(seeds))
    if a.png and curves:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
        sizes = sorted({s for s, _ in curves}, key=lambda s: int(s[1:].split("x")[0]))
        colors = dict(zip(sizes, plt.cm.viridis(np.linspace(0, 0.85, len(sizes)))))
        for (size, x), (st, ps, ls, n) in sorted(curves.items()):
            style = {base: "-", arm: "--"}.get(x, ":")
            lab = f"{x} {size} ({n} seeds)"
            a1.plot(st, ps, style, marker="o", ms=3, color=colors[size], label=lab)
            a2.plot(st, ls, style, marker="o", ms=3, color=colors[size], label=lab)
        a1.set(xlabel="step", ylabel="held-out PSNR (dB)",
               title="held-out PSNR (captured views, 3 unseen scenes)")
        a2.set(xlabel="step", ylabel="held-out MSE", yscale="log", title="held-out loss")
        for ax in (a1, a2):
            ax.grid(alpha=0.3)
        a1.legend(fontsize=7)
        fig.tight_layout()
        a.png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(a.png, dpi=90)
        print(f"wrote {a.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
