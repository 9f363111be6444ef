"""Markdown tables of an evaluation's rows: points, scene sizing and stability."""

from __future__ import annotations

import math
import statistics


def _n(x, fmt: str = ".2f") -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return ""
    return "" if math.isnan(x) else format(x, fmt)


def points_table(rows: list[dict]) -> str:
    """One line per (label, scene): time, memory, accuracy, counts."""
    lines = ["| label | scene | status | s | CPU s | peak MB | fv PSNR | fv SSIM | true share "
             "| held-out PSNR | cand | feasible | selected | free | scarce |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    seeded = len({r.get("seed") for r in rows}) > 1
    for r in rows:
        scene = f"{r['scene']} (seed {r.get('seed')})" if seeded else r["scene"]
        lines.append(
            f"| {r['label']} | {scene} | {r['status']} | {_n(r['seconds'], '.1f')} | "
            f"{_n(r['cpu_total'], '.1f')} | {_n(r['peak_rss_mb'], '.0f')} | "
            f"{_n(r['fv_psnr'])} | {_n(r['fv_ssim'], '.3f')} | {_n(r['fv_true_share'])} | "
            f"{_n(r['heldout_psnr'])} | {_n(r['n_candidates'], '.0f')} | "
            f"{_n(r['n_feasible'], '.0f')} | {_n(r['n_selected'], '.0f')} | "
            f"{_n(r['n_free_views'], '.0f')} | {'yes' if r.get('scarce') else ''} |")
    return "\n".join(lines)


def downstream_table(rows: list[dict]) -> str:
    """One line per point refined (``--downstream refine``): the real-views-only baseline and
    the arm with the point's free views, their held-out PSNR and the gain."""
    lines = ["| label | scene | free views | added | baseline PSNR | with free views PSNR | "
             "gain (dB) | seeds spread | refine CPU s | note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "refine_gain_db" not in r:
            continue
        lines.append(
            f"| {r['label']} | {r['scene']} | {_n(r.get('n_free_views'), '.0f')} | "
            f"{_n(r.get('refine_n_added'), '.0f')} | {_n(r.get('refine_base_psnr'))} | "
            f"{_n(r.get('refine_fv_psnr'))} | {_n(r.get('refine_gain_db'), '+.2f')} | "
            f"{_n(r.get('refine_gain_std'))} | {_n(r.get('refine_cpu_seconds'), '.0f')} | "
            f"{str(r.get('refine_note', '')).replace('|', '/')[:120]} |")
    return "\n".join(lines)


CHOSEN = {"grid_r": "grid_R", "candidates": "n_candidates", "resolution": "train_long_side",
          "gaussians": "n_gaussians_budget", "steps": "iterations"}


def _over_seeds(rs: list[dict]) -> dict | None:
    """One sizing cell from a (scene, knob, half|adaptive|double) group of rows (one per
    seed): means of seconds, accuracy and the value used, the accuracy's spread over seeds
    (``accuracy_std``, NaN for one seed) and a status that is ``ok`` only if every run was."""
    if not rs:
        return None
    acc = [r["accuracy"] for r in rs]
    ok = all(a == a for a in acc)
    bad = [r["status"] for r in rs if r["status"] != "ok"]
    out = {"seconds": float(sum(r["seconds"] for r in rs) / len(rs)),
           "accuracy": float(sum(acc) / len(acc)) if ok else math.nan,
           "accuracy_std": (statistics.stdev(acc) if ok and len(acc) > 1 else math.nan),
           "status": "ok" if not bad else bad[0], "n": len(rs)}
    for c in set(CHOSEN.values()):
        v = [float(r[c]) for r in rs if c in r and r[c] == r[c]]
        if v:
            out[c] = sum(v) / len(v)
    return out


def sizing_table(rows: list[dict]) -> str:
    """Adaptive vs half vs double per knob and scene: value used, seconds, accuracy and what
    half / double change against adaptive (dAcc in dB, time ratio). With several seeds every
    cell is the mean over the seeds and ``+-`` the adaptive point's spread (std) over them."""
    sz = [r for r in rows if r.get("group") == "sizing"]
    seeded = len({r.get("seed") for r in sz}) > 1
    lines = ["| scene | knob | adaptive value | adaptive s / acc | half value | half s / acc "
             "(dAcc) | double value | double s / acc (dAcc) | verdict |",
             "|---|---|---|---|---|---|---|---|---|"]
    keys = []
    for r in sz:
        if (r["scene"], r["knob"]) not in keys:
            keys.append((r["scene"], r["knob"]))
    for scene, knob in keys:
        by = {w: _over_seeds([r for r in sz if r["scene"] == scene and r["knob"] == knob
                              and r["label"].split("=", 1)[1] == w])
              for w in ("adaptive", "half", "double")}
        a, h, d = by["adaptive"], by["half"], by["double"]
        if a is None:
            continue
        col = CHOSEN.get(knob, "")

        def cell(r):
            if r is None:
                return "", ""
            acc = r["accuracy"]
            s = f"{_n(r['seconds'], '.1f')} / {_n(acc)}"
            if r is a and seeded and r["accuracy_std"] == r["accuracy_std"]:
                s += f" +-{r['accuracy_std']:.2f} ({r['n']} seeds)"
            if r is not a and acc == acc and a["accuracy"] == a["accuracy"]:
                s += f" ({acc - a['accuracy']:+.2f})"
            if r["status"] != "ok":
                s += f" {r['status']}"
            return _n(r.get(col), ".0f"), s

        av, as_ = cell(a)
        hv, hs = cell(h)
        dv, ds = cell(d)
        lines.append(f"| {scene} | {knob} | {av} | {as_} | {hv} | {hs} | {dv} | {ds} | "
                     f"{sizing_verdict(a, h, d)} |")
    return "\n".join(lines)


def sizing_verdict(a: dict, h: dict | None, d: dict | None, tol_db: float = 0.3) -> str:
    """``on front`` when neither half nor double beats adaptive on both axes; else which one
    does (``half dominates``: as accurate within ``tol_db`` and faster; ``double buys X dB``:
    more accurate by more than ``tol_db``). With a measured spread over seeds
    (``accuracy_std`` of the adaptive cell) the tolerance is at least that spread, so a
    difference smaller than the seeds' own scatter is not read as a verdict."""
    sd = a.get("accuracy_std", math.nan)
    if sd == sd:
        tol_db = max(tol_db, float(sd))
    acc = a["accuracy"]
    if acc != acc:
        return "no accuracy"
    out = []
    if h is not None and h["accuracy"] == h["accuracy"]:
        if h["accuracy"] >= acc - tol_db and h["seconds"] < a["seconds"]:
            out.append("half as good, faster")
    if d is not None and d["accuracy"] == d["accuracy"]:
        if d["accuracy"] > acc + tol_db:
            out.append(f"double buys {d['accuracy'] - acc:+.2f} dB")
    return "; ".join(out) if out else "near the front"


def stability_table(rows: list[dict], describe=None) -> str:
    """Per scene (family): final state, free views, their true fidelity, time."""
    lines = ["| family | how it is made | state | free views | fv PSNR | true share | "
             "held-out PSNR | nearest photo / mean photo | s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["status"] != "ok":
            state = f"failed: {r['error'][:160]}"
        elif r.get("empty_reason"):
            state = f"scarce: {r['empty_reason'][:160]}"
        elif r.get("scarce"):
            state = "ok, scarce (below the target)"
        else:
            state = "ok"
        how = describe(r["scene"]) if describe else ""
        lines.append(f"| {r['scene']} | {how} | {state.replace('|', '/')} | "
                     f"{_n(r['n_free_views'], '.0f')} | {_n(r['fv_psnr'])} | "
                     f"{_n(r['fv_true_share'])} | {_n(r['heldout_psnr'])} | "
                     f"{_n(r.get('heldout_nearest_psnr'))} / {_n(r.get('heldout_mean_psnr'))} | "
                     f"{_n(r['seconds'], '.1f')} |")
    return "\n".join(lines)
