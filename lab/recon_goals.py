"""Issue 17's goals, read from ``lab/recon_compare.py --compare ... --out rows.jsonl`` rows.

    .venv/bin/python -m lab.recon_goals rows.jsonl [--split ood] [--budget 10]

Prints (markdown):

* **equal time**: per scene, held-out PSNR of ``old`` and ``new`` at 1, 3 and 10 CPU-minutes
  and the difference (goal: up on the mean, nowhere down by more than 0.3 dB);
* **a third of the time**: ``old``'s PSNR at the end of its budget (10 CPU-minutes, or where it
  stopped on a plateau) against ``new`` at a third of that budget, per scene and on the mean,
  and the CPU-minute at which ``new`` first reached ``old``'s value;
* **OpenSplat**: its best held-out PSNR in its run and when, and when ``new`` first reached
  it (goal: at most a fifth of OpenSplat's time).

With rows of several ``--seed`` runs, ``--seeds`` adds a table paired by seed: per scene the
mean and spread (sample standard deviation) over seeds of each arm and of their difference,
and, with OpenSplat rows, when each seed of either arm first reached OpenSplat's best; with
OpenSplat rows of several ``--opensplat-seed`` runs, each of its runs against each seed of the new
arm, and the verdict against its median run.

``--smooth K`` replaces every arm's held-out curve (OpenSplat's and ours alike) by the trailing
median of its last K evaluations before any table is made, so that one lucky evaluation is not
a run's "best"; the raw reading (K = 1, the default) is the issue's goal.

``--metric covis`` reads every value from the held-out PSNR on co-visible pixels instead (rows
of ``recon.py --covis-ref``; see ``lab/covis.py``).

A mark reads a run's final evaluation when the run ended at most 5% past it (a 10-CPU-minute
budget ends a step and an annealing check past 10, at 10.1-10.3; its final model is what the
budget bought), else the last evaluation at or before the mark (2% slack). Until stop 53 the
marks read the latter only, so a 10-minute run whose final evaluation landed at 10.21 was read
at its evaluation before (up to a minute earlier, in the annealing that gains ~1 dB).

"When first reached" reads the evaluations (every ``--eval-every`` steps), so it is quantised to
them; a value "first reached" by a noisy held-out curve may be left again later.
"""

from __future__ import annotations

import argparse
import gzip
import json
import statistics
from pathlib import Path


def at(curve: list[dict], minutes: float) -> float | None:
    """PSNR of the last evaluation at or before ``minutes`` (None if the run did not get
    there)."""
    if not curve or curve[-1]["train_cpu_minutes"] < minutes * 0.98:
        return None
    pts = [c for c in curve if c["train_cpu_minutes"] <= minutes * 1.02]
    return pts[-1]["test_psnr"] if pts else None


def held(curve: list[dict], minutes: float) -> float | None:
    """PSNR at ``minutes`` of a run that may have ended earlier (on its plateau or its own
    budget): :func:`at`, else the run's final value when it stopped before ``minutes`` (its
    model does not change after it stops)."""
    v = at(curve, minutes)
    if v is None and curve and curve[-1]["train_cpu_minutes"] < minutes:
        v = curve[-1]["test_psnr"]
    return v


def end_value(curve: list[dict], minutes: float) -> tuple[float, float] | None:
    """(PSNR, CPU-minute) of the last evaluation at or before ``minutes`` (the run's end when
    it stopped earlier). 5% slack: a run budgeted ``minutes`` ends a step or an annealing
    check past it, and its final evaluation is what it reached in that budget."""
    pts = [c for c in curve if c["train_cpu_minutes"] <= minutes * 1.05]
    return (pts[-1]["test_psnr"], pts[-1]["train_cpu_minutes"]) if pts else None


def within(curve: list[dict], minutes: float) -> float | None:
    """PSNR a run reached within a budget of ``minutes``: the final value of a run that was
    budgeted for it (its last evaluation lies at most 5% past ``minutes``: the step and the
    annealing check that end it), else :func:`held` (an evaluation of a longer run)."""
    if curve and curve[-1]["train_cpu_minutes"] <= minutes * 1.05:
        return curve[-1]["test_psnr"]
    return held(curve, minutes)


def first_reaching(curve: list[dict], db: float) -> float | None:
    """CPU-minute of the first evaluation at or above ``db`` (None: never)."""
    for c in curve:
        if c["test_psnr"] >= db:
            return c["train_cpu_minutes"]
    return None


def best(curve: list[dict]) -> tuple[float, float] | None:
    if not curve:
        return None
    c = max(curve, key=lambda c: c["test_psnr"])
    return c["test_psnr"], c["train_cpu_minutes"]


def _f(v, fmt="{:.2f}") -> str:
    return "-" if v is None else fmt.format(v)


def group(rows: list[dict]) -> dict:
    """``{scene: {arm: row}}`` (a later row of the same scene and arm wins)."""
    out: dict = {}
    for r in rows:
        out.setdefault(r["scene"], {})[r["arm"]] = r
    return out


def _ms(vals: list[float], signed: bool = False) -> str:
    """``mean +- sd`` (sample sd; a lone value has none)."""
    if not vals:
        return "-"
    txt = f"{statistics.mean(vals):{'+' if signed else ''}.2f}"
    return txt if len(vals) < 2 else f"{txt} +- {statistics.stdev(vals):.2f}"


def read_rows(path: Path | str) -> list[dict]:
    """Every row of a ``recon.py --out`` file, in file order; ``.gz`` files (the rows kept in
    ``lab/results/``) are read through gzip."""
    path = Path(path)
    text = (gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz"
            else path.read_text())
    return [json.loads(ln) for ln in text.splitlines() if ln.strip()]


def load_rows(path: Path, split: str, metric: str = "all") -> list[dict]:
    """Every row of ``split`` (all seeds, in file order). ``metric="covis"``: each curve's
    ``test_psnr`` replaced by its co-visible-pixel PSNR; rows without one are left out."""
    rows = [r for r in read_rows(path) if r.get("split") == split]
    if metric == "all":
        return rows
    return [c for c in map(covis_row, rows) if c is not None]


def covis_row(r: dict) -> dict | None:
    """``r`` with each evaluation's ``test_psnr`` replaced by its co-visible-pixel PSNR (None
    for a row without one)."""
    curve = r.get("test_psnr_curve") or []
    if not curve or any("test_psnr_covis" not in c for c in curve):
        return None
    return {**r, "test_psnr_curve": [{**c, "test_psnr": c["test_psnr_covis"]} for c in curve]}


def smooth_row(r: dict, k: int) -> dict:
    """``r`` with each evaluation's ``test_psnr`` replaced by the median of it and the up to
    ``k - 1`` evaluations before it (a trailing window: a value never depends on a later
    evaluation, so "first reaching" keeps its meaning). ``k = 1`` returns ``r`` unchanged."""
    if k < 1:
        raise ValueError(f"smoothing window must be >= 1, got {k}")
    curve = r.get("test_psnr_curve") or []
    if k == 1 or not curve:
        return r
    vals = [c["test_psnr"] for c in curve]
    med = [statistics.median(vals[max(0, i - k + 1):i + 1]) for i in range(len(vals))]
    return {**r, "test_psnr_curve": [{**c, "test_psnr": m} for c, m in zip(curve, med)]}


def steps_axis_row(r: dict) -> dict:
    """``r`` with its curve's clock replaced by the step count in thousands: every reading
    (marks, "first reaching", bests) is then in kilo-steps, not CPU-minutes. Two sessions'
    rows of arms that cost the same per step pair on this axis without either session's
    CPU clock (a shared machine's clock moves with load)."""
    curve = r.get("test_psnr_curve") or []
    return {**r, "test_psnr_curve": [{**c, "train_cpu_minutes": c["step"] / 1000.0,
                                      "train_minutes": c["step"] / 1000.0} for c in curve]}


def by_seed(rows: list[dict]) -> dict:
    """``{scene: {seed: {arm: row}}}`` (a later row of the same scene, seed and arm wins; a row
    without a seed counts as seed 0)."""
    runs: dict = {}
    for r in rows:
        runs.setdefault(r["scene"], {}).setdefault(r.get("seed", 0), {})[r["arm"]] = r
    return runs


def seed_report(rows: list[dict], budget: float = 10.0, marks=(1.0, 3.0, 10.0),
                new_arm: str = "new", old_arm: str = "old") -> str:
    """Old and new paired by seed: per scene, mean +- sd over the seeds both arms ran, of
    each arm's held-out PSNR at each mark and at the end of old's budget against new at a
    third of it, and of the paired differences (a later row of the same scene, arm and seed
    wins)."""
    runs = by_seed(rows)
    cols = [f"@{m:g}" for m in marks] + [f"new @{budget / 3:.2f} vs old @{budget:g}"]
    lines = ["### Paired by seed: new - old (mean +- sd over seeds)", "",
             "| scene | seeds | " + " | ".join(f"old {c} | new {c} | diff" if c[0] == "@"
                                              else f"{c}: old | new | diff" for c in cols)
             + " |", "|---|---|" + "---|" * (3 * len(cols))]
    means: dict = {c: [] for c in cols}
    for s in sorted(runs):
        pairs = {sd: g for sd, g in runs[s].items() if old_arm in g and new_arm in g}
        if not pairs:
            continue
        cells = []
        for c, m in zip(cols, list(marks) + [None]):
            olds, news, diffs = [], [], []
            for g in pairs.values():
                o, n = g[old_arm]["test_psnr_curve"], g[new_arm]["test_psnr_curve"]
                if m is None:
                    e = end_value(o, budget)
                    a, b = (e and e[0]), within(n, budget / 3.0)
                else:
                    a, b = within(o, m), within(n, m)
                if a is not None and b is not None:
                    olds.append(a)
                    news.append(b)
                    diffs.append(b - a)
            if diffs:
                means[c].append(sum(diffs) / len(diffs))
            cells += [_ms(olds), _ms(news), _ms(diffs, signed=True)]
        lines.append(f"| {s} | {','.join(str(k) for k in sorted(pairs))} | "
                     + " | ".join(cells) + " |")
    for c in cols:
        if means[c]:
            lines.append(f"\n{c}: mean over {len(means[c])} scenes of the per-scene mean "
                         f"difference {sum(means[c]) / len(means[c]):+.2f} dB, lowest scene "
                         f"{min(means[c]):+.2f}")
    return "\n".join(lines)


def _reached(curves: dict, db: float, t_os: float, goal: float) -> tuple[str, int]:
    """For ``{seed: curve}``: ``"seed: first CPU-minute at >= db (ratio to t_os)"`` cells
    joined, and how many seeds got there within ``goal`` of ``t_os``."""
    got, met = [], 0
    for sd in sorted(curves):
        t = first_reaching(curves[sd], db)
        met += t is not None and t / t_os <= goal
        got.append(f"{sd}: -" if t is None else f"{sd}: {t:.2f} ({t / t_os:.2f})")
    return "; ".join(got) or "-", met


def opensplat_seed_report(rows: list[dict], arms: tuple[str, ...], goal: float = 0.2) -> str:
    """Per scene, OpenSplat's best held-out PSNR in its run (and when), and for each arm of
    ``arms`` and each of its seeds the CPU-minute at which that run first reached it and the
    ratio to OpenSplat's time (goal: at most ``goal``); "-" when it never did. OpenSplat's
    row is the last one of the scene (its runs carry no seed)."""
    os_best = {r["scene"]: best(r["test_psnr_curve"]) for r in rows if r["arm"] == "opensplat"}
    runs = by_seed([r for r in rows if r["arm"] in arms])
    lines = [f"### OpenSplat's best against each seed (goal: ratio <= {goal:g})", "",
             "| scene | OpenSplat best (at) | " + " | ".join(
                 f"{a}: first reaches it at (ratio), per seed | met" for a in arms) + " |",
             "|---|---|" + "---|---|" * len(arms)]
    for s in sorted(os_best):
        ob = os_best[s]
        if ob is None or s not in runs:
            continue
        cells = []
        for a in arms:
            seeds = {sd: g[a]["test_psnr_curve"] for sd, g in runs[s].items() if a in g}
            got, met = _reached(seeds, ob[0], ob[1], goal)
            cells += [got, f"{met}/{len(seeds)}"]
        lines.append(f"| {s} | {ob[0]:.2f} ({ob[1]:.2f}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def opensplat_runs_report(rows: list[dict], arm: str, goal: float = 0.2) -> str:
    """OpenSplat over its own seeds (rows of ``recon.py --opensplat-seed``; a row without
    ``opensplat_seed`` is its hard-coded 42). Per scene and OpenSplat run: its best held-out
    PSNR (and when), and for each seed of ``arm`` the CPU-minute it first reached that best and
    the ratio to OpenSplat's time. Then the verdict of a rule fixed before the runs
    (lab/results/2026-12-05_stop44/prereg_opensplat_seeds.md): against the run with the median best,
    met if more than half of ``arm``'s seeds reach it within ``goal`` of its time; the
    strictest reading (the highest best) beside it. A later row of the same scene and
    OpenSplat seed wins."""
    os_runs: dict = {}
    for r in rows:
        if r["arm"] == "opensplat" and r.get("test_psnr_curve"):
            os_runs.setdefault(r["scene"], {})[r.get("opensplat_seed") or 42] = r
    ours = by_seed([r for r in rows if r["arm"] == arm])
    lines = [f"### OpenSplat over its seeds against each seed of {arm} (goal: ratio <= {goal:g})",
             "", f"| scene | OpenSplat seed | its best (at) | {arm}: first reaches it at (ratio), "
             "per seed | met |", "|---|---|---|---|---|"]
    verdicts = []
    for s in sorted(os_runs):
        if s not in ours:
            continue
        seeds = {sd: g[arm]["test_psnr_curve"] for sd, g in ours[s].items() if arm in g}
        met_of: dict = {}
        bests = {k: best(r["test_psnr_curve"]) for k, r in sorted(os_runs[s].items())}
        for k, (db, t_os) in bests.items():
            got, met_of[k] = _reached(seeds, db, t_os, goal)
            lines.append(f"| {s} | {k} | {db:.2f} ({t_os:.2f}) | {got} | "
                         f"{met_of[k]}/{len(seeds)} |")
        vals = [b[0] for b in bests.values()]
        order = sorted(bests, key=lambda k: bests[k][0])
        med = order[(len(order) - 1) // 2]  # the lower median for an even count
        top = order[-1]
        ok_med = met_of[med] * 2 > len(seeds)
        spread = f" +- {statistics.stdev(vals):.2f}" if len(vals) > 1 else ""
        verdicts.append(
            f"- {s}: OpenSplat bests {statistics.mean(vals):.2f}{spread} over {len(vals)} seeds; "
            f"median run (seed {med}, {bests[med][0]:.2f}): {met_of[med]}/{len(seeds)} seeds "
            f"within {goal:g} -> **{'met' if ok_med else 'NOT met'}**; strictest (seed {top}, "
            f"{bests[top][0]:.2f}): {met_of[top]}/{len(seeds)} -> "
            f"{'met' if met_of[top] * 2 > len(seeds) else 'not met'}")
    return "\n".join(lines + [""] + verdicts)


def several_seeds_note(rows: list[dict], arms: tuple[str, str]) -> str | None:
    """With rows of more than one seed of ``arms``, a warning that :func:`report`'s tables read
    one row per scene and arm, the last in the files, naming its seed per scene (None with one
    seed). Without it a one-seed verdict there reads like the verdict over seeds."""
    seeds = {r.get("seed") for r in rows if r["arm"] in arms}
    if len(seeds) < 2:
        return None
    last = {s: {a: r.get("seed") for a, r in g.items() if a in arms}
            for s, g in group(rows).items()}
    per = "; ".join(f"{s}: " + ", ".join(f"{a} seed {sd}" for a, sd in g.items())
                    for s, g in sorted(last.items()) if g)
    return (f"Rows of {len(seeds)} seeds: the next two tables read ONE row per scene and arm, "
            f"the last in the files ({per}). Use --seed S for one seed; --seeds adds the "
            "reading over seeds (paired by seed).")


def report(groups: dict, budget: float = 10.0, marks=(1.0, 3.0, 10.0)) -> str:
    lines = []
    scenes = sorted(s for s, g in groups.items() if "old" in g and "new" in g)
    lines += ["### Equal CPU time: new - old", "",
              "| scene | " + " | ".join(f"old @{m:g} | new @{m:g} | diff" for m in marks) + " |",
              "|---|" + "---|" * (3 * len(marks))]
    diffs: dict = {m: [] for m in marks}
    for s in scenes:
        o, n = groups[s]["old"]["test_psnr_curve"], groups[s]["new"]["test_psnr_curve"]
        cells = []
        for m in marks:
            a, b = within(o, m), within(n, m)  # a run that ended before or at the mark: final
            d = None if a is None or b is None else b - a
            if d is not None:
                diffs[m].append(d)
            cells += [_f(a), _f(b), _f(d, "{:+.2f}")]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    for m in marks:
        if diffs[m]:
            lines.append(f"\nnew - old at {m:g} CPU-min over {len(diffs[m])} scenes: mean "
                         f"{sum(diffs[m]) / len(diffs[m]):+.2f} dB, min {min(diffs[m]):+.2f}, "
                         f"max {max(diffs[m]):+.2f}")

    third = budget / 3.0
    lines += ["", f"### A third of the time: new @{third:.2f} against old @{budget:g}", "",
              f"| scene | old @{budget:g} (at) | new @{third:.2f} | new first reaches old's "
              "value at | ratio to old's time |", "|---|---|---|---|---|"]
    olds, news = [], []
    for s in scenes:
        o, n = groups[s]["old"]["test_psnr_curve"], groups[s]["new"]["test_psnr_curve"]
        e, b = end_value(o, budget), within(n, third)
        if e is None or b is None:
            lines.append(f"| {s} | {_f(e and e[0])} | {_f(b)} | - | - |")
            continue
        olds.append(e[0])
        news.append(b)
        t = first_reaching(n, e[0])
        lines.append(f"| {s} | {e[0]:.2f} ({e[1]:.2f}) | {b:.2f} | {_f(t)} | "
                     f"{_f(None if t is None else t / e[1])} |")
    if olds:
        mo, mn = sum(olds) / len(olds), sum(news) / len(news)
        lines.append(f"\nmean over {len(olds)} scenes: old @{budget:g} {mo:.2f} dB, new "
                     f"@{third:.2f} {mn:.2f} dB: goal (new >= old) "
                     f"{'met' if mn >= mo else 'NOT met'} ({mn - mo:+.2f} dB)")

    os_scenes = sorted(s for s, g in groups.items() if "opensplat" in g and "new" in g)
    if os_scenes:
        lines += ["", "### OpenSplat's best against the new trainer", "",
                  "| scene | OpenSplat best (at) | new first reaches it at | ratio | "
                  "new best (at) |", "|---|---|---|---|---|"]
        for s in os_scenes:
            ob = best(groups[s]["opensplat"]["test_psnr_curve"])
            nc = groups[s]["new"]["test_psnr_curve"]
            nb = best(nc)
            t = first_reaching(nc, ob[0]) if ob else None
            lines.append(f"| {s} | {_f(ob and ob[0])} ({_f(ob and ob[1])}) | {_f(t)} | "
                         f"{_f(None if t is None or not ob else t / ob[1])} | "
                         f"{_f(nb and nb[0])} ({_f(nb and nb[1])}) |")
    return "\n".join(lines)


def extent_report(rows: list[dict], arms: tuple[str, ...]) -> str:
    """Per scene and arm, over its seeds: the largest share of Gaussians beyond 5 bound radii at
    the end of training and the farthest Gaussian (bound radii; ``gaussian_extent`` of the
    rows)."""
    runs = by_seed([r for r in rows if r["arm"] in arms and r.get("gaussian_extent")])
    lines = ["### Gaussian extent at the end (worst seed)", "",
             "| scene | " + " | ".join(f"{a}: seeds | beyond 5 R | farthest (R)" for a in arms)
             + " |", "|---|" + "---|---|---|" * len(arms)]
    for s in sorted(runs):
        cells = []
        for a in arms:
            ext = {sd: g[a]["gaussian_extent"] for sd, g in runs[s].items() if a in g}
            if not ext:
                cells += ["-", "-", "-"]
                continue
            cells += [",".join(str(k) for k in sorted(ext)),
                      f"{100 * max(e['share_beyond'] for e in ext.values()):.2f}%",
                      f"{max(e['farthest'] for e in ext.values()):.1f}"]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def opensplat_equal_time_report(rows: list[dict], arms: tuple[str, ...],
                                marks=(1.0, 3.0, 10.0)) -> str:
    """Per scene, OpenSplat's held-out PSNR at each mark beside each arm's (mean +- sd over its
    seeds) and the arm minus OpenSplat (mean +- sd over seeds): the equal-time view of the same
    runs whose best :func:`opensplat_seed_report` reads. OpenSplat's row is the last one of the
    scene (its runs carry no seed)."""
    os_rows = {r["scene"]: r for r in rows if r["arm"] == "opensplat"}
    runs = by_seed([r for r in rows if r["arm"] in arms])
    cols = [f"@{m:g}" for m in marks]
    lines = ["### Equal CPU time against OpenSplat (arms: mean +- sd over seeds)", "",
             "| scene | " + " | ".join(
                 f"OpenSplat {c} | " + " | ".join(f"{a} | {a} - OpenSplat" for a in arms)
                 for c in cols) + " |",
             "|---|" + "---|" * (len(cols) * (1 + 2 * len(arms)))]
    for s in sorted(os_rows):
        if s not in runs:
            continue
        cells = []
        for m in marks:
            o = within(os_rows[s]["test_psnr_curve"], m)
            cells.append(_f(o))
            for a in arms:
                vals = [v for g in runs[s].values() if a in g
                        for v in [within(g[a]["test_psnr_curve"], m)] if v is not None]
                cells += [_ms(vals), "-" if o is None else _ms([v - o for v in vals], True)]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def same_until_report(rows: list[dict], arms: tuple[str, str], step: int) -> str:
    """Whether two arms are the same computation up to ``step``: per scene and seed that both
    ran, how many held-out evaluations at steps <= ``step`` are bit-equal. Two arms that differ
    only in what switches on after ``step`` (e.g. ``sh_degree=1`` against 3, the same before
    the degree-2 step) must give all of them equal, also when they ran in different sessions;
    one unequal value means the install, the code or the data changed between the two rows."""
    lines = [f"### Held-out evaluations at steps <= {step}: {arms[0]} against {arms[1]}", "",
             "| scene | seed | bit-equal | first unequal step |", "|---|---|---|---|"]
    n_all = same_all = 0
    for scene, seeds in sorted(by_seed(rows).items()):
        for seed, runs in sorted(seeds.items()):
            if arms[0] not in runs or arms[1] not in runs:
                continue
            a, b = ({c["step"]: c["test_psnr"] for c in runs[arm]["test_psnr_curve"]
                     if c["step"] <= step} for arm in arms)
            common = sorted(set(a) & set(b))
            unequal = [s for s in common if a[s] != b[s]]
            same = len(common) - len(unequal)
            n_all += len(common)
            same_all += same
            lines.append(f"| {scene} | {seed} | {same} of {len(common)} | "
                         f"{unequal[0] if unequal else '-'} |")
    lines += ["", f"{same_all} of {n_all} evaluations bit-equal"]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rows", type=Path, nargs="+")
    ap.add_argument("--split", default="ood")
    ap.add_argument("--budget", type=float, default=10.0, help="old arm's budget (CPU-minutes)")
    ap.add_argument("--marks", type=float, nargs="+", default=[1.0, 3.0, 10.0])
    ap.add_argument("--new-arm", default="new", help="the arm that plays `new` (e.g. "
                    "new,init_triangulate_below=400)")
    ap.add_argument("--old-arm", default="old", help="the arm that plays `old` (e.g. new, to "
                    "pair a variant of new with it)")
    ap.add_argument("--seed", type=int, default=None,
                    help="only this seed's rows (and OpenSplat's, which carry none)")
    ap.add_argument("--seeds", action="store_true",
                    help="also print old and new paired by seed (mean +- sd over seeds)")
    ap.add_argument("--metric", default="all", choices=["all", "covis"],
                    help="held-out PSNR over all pixels, or over the co-visible ones only")
    ap.add_argument("--smooth", type=int, default=1, metavar="K",
                    help="read every arm's curve as the trailing median of its last K "
                    "evaluations (1: raw)")
    ap.add_argument("--same-until", type=int, default=None, metavar="STEP",
                    help="also count the held-out evaluations at steps <= STEP that are "
                    "bit-equal between the two arms (a check that rows of two sessions agree)")
    ap.add_argument("--axis", default="cpu", choices=["cpu", "steps"],
                    help="read the marks in CPU-minutes, or in thousands of training steps "
                    "(pairs rows of two sessions without their clocks)")
    a = ap.parse_args(argv)
    rows = [r for p in a.rows for r in load_rows(p, a.split, a.metric)
            if a.seed is None or r.get("seed") in (None, a.seed)]
    rows = [smooth_row(r, a.smooth) for r in rows]
    if a.axis == "steps":
        rows = [steps_axis_row(r) for r in rows]
        print("(axis: thousands of training steps; every 'CPU-minute' below is 1,000 steps)\n")
    groups = {s: {**g, "old": g[a.old_arm], "new": g[a.new_arm]}
              for s, g in group(rows).items() if a.old_arm in g and a.new_arm in g}
    note = several_seeds_note(rows, (a.old_arm, a.new_arm))
    if note:
        print(note + "\n")
    print(report(groups, a.budget, tuple(a.marks)))
    if a.seeds:
        print("\n" + seed_report(rows, a.budget, tuple(a.marks), a.new_arm, a.old_arm))
        if any(r["arm"] == "opensplat" for r in rows):
            if any("opensplat_seed" in r for r in rows if r["arm"] == "opensplat"):
                print("\n" + opensplat_runs_report(rows, a.new_arm))
            print("\n" + opensplat_seed_report(rows, (a.old_arm, a.new_arm)))
            print("\n" + opensplat_equal_time_report(rows, (a.old_arm, a.new_arm),
                                                      tuple(a.marks)))
        print("\n" + extent_report(rows, (a.old_arm, a.new_arm)))
    if a.same_until is not None:
        print("\n" + same_until_report(rows, (a.old_arm, a.new_arm), a.same_until))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
