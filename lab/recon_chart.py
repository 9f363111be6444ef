"""Chart of ``benchmarks/recon.py --compare ... --out rows.jsonl``: held-out PSNR against
training CPU-minutes, one panel per scene and split, one line per arm and seed (an arm keeps
its colour and style across seeds and panels; the legend names it once) (PNG).

    .venv/bin/python -m lab.recon_chart rows.jsonl lab/results/2026-12-02/recon_time_to_quality.png

Rows of ``recon.py --covis-ref`` get a second panel per scene and split: the held-out PSNR on
the co-visible pixels only.
"""

from __future__ import annotations

import sys

from lab.recon_goals import covis_row, read_rows


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_rows(argv[0])
    rows += [{**c, "split": f"{c['split']}, co-visible pixels"}
             for c in map(covis_row, list(rows)) if c is not None]
    panels = list(dict.fromkeys((r["scene"], r["split"]) for r in rows))
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    cols = min(4, len(panels))
    nrows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 2.8 * nrows), squeeze=False)
    styles = {a: ["--", "-", ":", "-."][i % 4] for i, a in enumerate(arms)}
    colors = {a: f"C{i}" for i, a in enumerate(arms)}  # one colour per arm in every panel
    for ax, (scene, split) in zip(axes.flat, panels):
        named = set()
        for r in rows:
            if (r["scene"], r["split"]) != (scene, split):
                continue
            c = r.get("test_psnr_curve") or []
            ax.plot([p["train_cpu_minutes"] for p in c], [p["test_psnr"] for p in c],
                    styles[r["arm"]], color=colors[r["arm"]], marker=".", markersize=3,
                    lw=1.0, alpha=0.85, label=None if r["arm"] in named else r["arm"])
            named.add(r["arm"])
        ax.set_title(f"{scene} ({split})", fontsize=9)
        ax.set_xlabel("training CPU-minutes", fontsize=8)
        ax.set_ylabel("held-out PSNR (dB)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(argv[1], dpi=110)
    print(f"wrote {argv[1]} ({len(panels)} panels, arms {arms})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
