"""The Pareto chart of an evaluation: seconds per scene (x) against accuracy (y).

Every point is one sweep label (aggregated over the scenes); the front (points no other point
beats on both axes) is drawn as a step line; presets and the base are labelled in bold, the
other points in small print. With several seeds each point is the mean over them and carries
an error bar of their spread (``accuracy_std``). A sidecar ``<name>.json`` holds the axes, the
points and the front, so the chart can be checked without reading pixels.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

XLABEL = "seconds per scene (wall, sum of the pipeline stages)"


def pareto_front(points: list[dict]) -> list[dict]:
    """Points no other point beats (fewer or equal seconds and higher or equal accuracy, one
    strictly), sorted by seconds."""
    pts = sorted((p for p in points if p["accuracy"] == p["accuracy"]),
                 key=lambda p: (p["seconds"], -p["accuracy"]))
    front, best = [], -math.inf
    for p in pts:
        if p["accuracy"] > best:
            front.append(p)
            best = p["accuracy"]
    return front


def pareto_chart(points: list[dict], path: Path, ylabel: str, title: str = "") -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    pts = [p for p in points if p["accuracy"] == p["accuracy"]]
    front = pareto_front(pts)
    fig, ax = plt.subplots(figsize=(8, 5.5), dpi=110)
    on_front = {p["label"] for p in front}
    offsets = ((4, 3), (4, -10), (4, 12), (-10, -14), (4, 20))  # near points: labels apart
    for i, p in enumerate(sorted(pts, key=lambda q: (q["accuracy"], q["seconds"]))):
        preset = p["group"] in ("preset", "base")
        colour = {"preset": "tab:red", "base": "tab:blue", "sizing": "tab:green"}.get(
            p["group"], "tab:gray")
        ax.scatter(p["seconds"], p["accuracy"], s=60 if preset else 28, c=colour,
                   edgecolors="black" if p["label"] in on_front else "none", zorder=3)
        sd = p.get("accuracy_std", math.nan)
        if sd == sd:  # spread over seeds (mean over the scenes of the per-scene std)
            ax.errorbar(p["seconds"], p["accuracy"], yerr=sd, fmt="none", ecolor=colour,
                        elinewidth=0.8, capsize=2, alpha=0.7, zorder=2)
        ax.annotate(p["label"], (p["seconds"], p["accuracy"]), xytext=offsets[i % len(offsets)],
                    textcoords="offset points", fontsize=8 if preset else 6.5,
                    fontweight="bold" if preset else "normal")
    if front:
        xs, ys = [front[0]["seconds"]], [front[0]["accuracy"]]
        for p in front[1:]:
            xs += [p["seconds"], p["seconds"]]
            ys += [ys[-1], p["accuracy"]]
        ax.plot(xs, ys, "-", c="tab:orange", lw=1.5, zorder=2, label="Pareto front")
        ax.legend(loc="best", fontsize=8)
    ax.set_xscale("log")
    from matplotlib.ticker import LogLocator, ScalarFormatter

    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_minor_locator(LogLocator(base=10, subs=(3.0, 4.0, 6.0, 7.0, 8.0, 9.0)))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xlabel(XLABEL)
    ax.set_ylabel(ylabel)
    ax.set_title(title or "speed against accuracy", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    meta = {"xlabel": XLABEL, "ylabel": ylabel, "xscale": "log", "title": title,
            "points": pts, "front": [p["label"] for p in front]}
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1, default=str) + "\n")
    return str(path)
