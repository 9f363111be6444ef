"""Free-view stage (METHOD.md stages 7-10): profile, side-by-side old vs new, yield funnel.

Runs the free-view stage from a store's checkpoints (``STORE/scenes/<id>/_work/``: scene.pkl,
gaussians.ply, selection.pkl and the reconstruction's recorded train scale / background), so
the reconstruction is paid once:

    freescale run ../shared/datasets/kermit --store /tmp/fv --preset cpu
    python benchmarks/freeviews.py profile --store /tmp/fv --scene kermit --preset cpu \
        --repeats 3

Each repeat runs both arms in fresh subprocesses, alternating (old, new, old, new, ...):

* ``old``: the stage as it was at ``--old-commit`` (extracted with ``git archive`` into a
  cache folder and put first on ``PYTHONPATH``); its parts are timed by wrapping its
  functions (exclusive seconds: a part's time excludes the parts it calls);
* ``new``: the stage of this checkout; its parts are the stage's own ``result.timings``.

The table prints the median seconds per part, the stage total, seconds per 100 kept views,
the counts (rendered, passed, kept) and the mean predicted PSNR (and, on the sample scene, the
true PSNR) of the kept views. ``writing`` is ``store.layout.write_scene_outputs`` into a
scratch folder (the publish stage's work for these views).

``funnel`` prints feasible -> NMS-selected -> reserve drawn -> passed -> kept -> mean
predicted (and, where the scene has an oracle, true) PSNR of the kept views per scene. By
default it reads what the store published (``CURRENT``'s ``views.parquet``: dispositions,
``suppress_reason``, ``passed``, ``pred_psnr``, ``gt_psnr_render``), no computing:

    python -m benchmarks.freeviews funnel --store /tmp/fv --scenes kermit

With ``--rerun`` it runs the selection and the stage of this checkout (and, with ``--old``,
the ``--old-commit``'s) at ``--preset`` on the stored reconstruction, in fresh processes; the
store is only read. The views used are the reconstruction's own split (the store's
``run_config.json``), so a fast-preset reconstruction can be run with the cpu preset's
selection and free-view settings:

    python -m benchmarks.freeviews funnel --store /tmp/fv --scenes kermit --preset cpu \
        --rerun --old --old-commit 6091708
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OLD_COMMIT = "af8c556"  # the stage before issue 63 (batched renders, reserve candidates)
PARTS = ("render", "render_rectify", "render_final", "render_reference", "reference_photo",
         "brisque", "scores", "trust_photometric", "trust_certainty", "trust_edges",
         "trust_floaters", "trust_angle", "trust_other", "rectify", "references", "other",
         "ground_truth", "writing")


# --------------------------------------------------------------------------- old tree
def old_tree(commit: str) -> Path:
    """``freescale_core`` and ``schemas`` of ``commit``, extracted once into a cache folder
    (numba then compiles that tree's kernels once and caches them there)."""
    full = subprocess.run(["git", "-C", str(ROOT), "rev-parse", commit], check=True,
                          capture_output=True, text=True).stdout.strip()
    dst = Path(tempfile.gettempdir()) / f"freescale_old_{full[:12]}"
    if not (dst / ".complete").is_file():
        dst.mkdir(parents=True, exist_ok=True)
        arc = subprocess.run(["git", "-C", str(ROOT), "archive", full, "freescale_core",
                              "schemas"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dst)], input=arc, check=True)
        (dst / ".complete").write_text(full)
    return dst


# --------------------------------------------------------------------------- timing wrappers
class _Clock:
    """Exclusive seconds per part: a nested part's time is not counted in its caller's."""

    def __init__(self):
        self.t: dict[str, float] = {}
        self.stack: list[list] = []

    def wrap(self, part, fn):
        def inner(*a, **k):
            p = part(*a, **k) if callable(part) else part
            self.stack.append([p, 0.0])
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                _, child = self.stack.pop()
                self.t[p] = self.t.get(p, 0.0) + dt - child
                if self.stack:
                    self.stack[-1][1] += dt
        inner.__wrapped__ = fn
        return inner


def _instrument_old(clock: _Clock):
    """Wrap the old tree's functions by part (they are looked up as module globals)."""
    import inspect

    from freescale_core.freeviews import quality, run, stage, trust

    src, first = inspect.getsourcelines(run.run_freeviews)
    line_of = {}
    for n, s in enumerate(src):
        if "r = _render(render_fn, p, cams, j)" in s:
            line_of[first + n] = "render_rectify"
        elif "_render(render_fn, rec.world_from_cam, cams, j)" in s:
            line_of[first + n] = "render_final"

    def render_part(*a, **k):
        f = sys._getframe(2)  # inner -> render_part's caller is inner; its caller is the site
        if f.f_code.co_name == "_reference":
            return "render_reference"
        return line_of.get(f.f_lineno, "render")

    run._render = clock.wrap(render_part, run._render)
    run._reference = clock.wrap("reference_photo", run._reference)
    b = clock.wrap("brisque", quality.brisque_score)
    quality.brisque_score = b
    run.brisque_score = b
    run.score_view = clock.wrap("scores", run.score_view)
    for name, part in (("nearest_training_views", "trust_photometric"),
                       ("photometric_consistency", "trust_photometric"),
                       ("certainty_support", "trust_certainty"),
                       ("depth_edge_share", "trust_edges"), ("floater_share", "trust_floaters"),
                       ("view_angle_deg", "trust_angle"), ("score_trust", "trust_other")):
        setattr(trust, name, clock.wrap(part, getattr(trust, name)))
    run.select_reference = clock.wrap("references", run.select_reference)
    make = run.make_rectifier

    class _Timed:
        def __init__(self, r):
            self._r = r
            self.name, self.needs_reference = r.name, r.needs_reference
            self._call = clock.wrap("rectify", r.__call__)

        def __call__(self, *a, **k):
            return self._call(*a, **k)

    run.make_rectifier = lambda cfg=None: _Timed(make(cfg))
    mk = stage.make_overlap_fn

    class _TimedOverlap:
        def __init__(self, o):
            self._o, self.grid = o, getattr(o, "grid", None)
            self._call = clock.wrap("references", o.__call__)

        def __call__(self, *a, **k):
            return self._call(*a, **k)

    def make_overlap(*a, **k):
        o = mk(*a, **k)
        return None if o is None else _TimedOverlap(o)

    stage.make_overlap_fn = make_overlap
    og = stage.ground_truth_oracle

    def oracle(path):
        o = og(path)
        if o is not None:
            o.render = clock.wrap("ground_truth", o.render)
        return o

    stage.ground_truth_oracle = oracle


def _load(store: Path, sid: str, selection: bool = True):
    import pickle

    from freescale_core.scene.ply import read_ply

    work = store / "scenes" / sid / "_work"
    with open(work / "scene.pkl", "rb") as f:
        scene = pickle.load(f)
    sel = None
    if selection:
        with open(work / "selection.pkl", "rb") as f:
            sel = pickle.load(f)
    g = read_ply(work / "gaussians.ply", scene_id=sid)
    rec = json.loads((work / "reconstruct.done.json").read_text())["result"]
    return work, scene, sel, g, rec


def _recon_split(store: Path, cfg) -> str:
    """The split the stored reconstruction trained on (the store's ``run_config.json``), so
    that the training views of the stage are the reconstruction's whatever ``--preset``."""
    p = store / "run_config.json"
    if p.is_file():
        return json.loads(p.read_text()).get("config", {}).get("recon_split", cfg.recon_split)
    return cfg.recon_split


def worker(args) -> dict:
    """One run of the stage in this process (the arm is whatever ``freescale_core`` imports)."""
    import numpy as np

    import freescale_core
    from schemas.pipeline import PipelineConfig

    try:
        from freescale_core.freeviews.run import run_free_view_stage
    except ImportError:  # a tree from before the entry point moved into freeviews/run.py
        from freescale_core.freeviews.stage import run_free_view_stage
    from freescale_core.scene.ply import read_background

    work, scene, sel, g, rec = _load(Path(args.store), args.scene)
    cfg = PipelineConfig.from_preset(args.preset)
    clock = _Clock()
    if args.arm == "old":
        import freescale_core.freeviews.run as run_mod
        import freescale_core.freeviews.stage as stage_mod

        if "timings" not in getattr(run_mod.FreeViewResult, "__dataclass_fields__", {}):
            _instrument_old(clock)  # a stage before result.timings: time it from outside
        run_stage = stage_mod.run_free_view_stage
    else:
        run_stage = run_free_view_stage
    scene_view, _ = scene.views_for(_recon_split(Path(args.store), cfg))
    if args.reselect:
        from freescale_core.select.run import run_selection

        sel = run_selection(g, scene_view.cameras, cfg.select, seed=cfg.seed,
                            scene_id=args.scene, capture_order=scene_view.capture_order,
                            points=scene_view.points_xyz,
                            train_masks=scene_view.load_mask if scene_view.has_masks else None)
    src = json.loads((work / "ingest.done.json").read_text())
    scene_path = args.scene_path
    t0 = time.perf_counter()
    fv = run_stage(scene_view, g, sel, cfg.freeview, seed=cfg.seed, scene_path=scene_path,
                   train_scale=float(rec.get("train_scale", 1.0)),
                   background=read_background(work / "gaussians.ply", cfg.recon.background,
                                              args.scene),  # the colour saved with the model
                   backend=cfg.recon.raster_backend)
    total = time.perf_counter() - t0
    parts = dict(getattr(fv, "timings", None) or clock.t)
    from freescale_core.store.layout import write_scene_outputs

    with tempfile.TemporaryDirectory() as d:
        t1 = time.perf_counter()
        write_scene_outputs(Path(d), scene_view, sel, fv, work / "gaussians.ply", cfg.freeview)
        parts["writing"] = time.perf_counter() - t1
    parts["other"] = parts.get("other", 0.0) + max(
        0.0, total - sum(v for k, v in parts.items() if k not in ("writing", "other")))
    kept = [r for r in fv.records if r.final]
    gt = getattr(fv, "gt", {}) or {}
    del src
    return {
        "arm": args.arm, "code": str(Path(freescale_core.__file__).parent), "seconds": total,
        "parts": parts, "counts": {k: (bool(v) if isinstance(v, (bool, np.bool_)) else int(v))
                                   for k, v in fv.counts.items()},
        "n_final": fv.n_final, "n_selected": int(len(sel.selected)),
        "n_reserve": int(len(getattr(sel, "reserve", ()))),
        "n_feasible": int(sel.counts.get("n_feasible", -1)),
        "mean_pred_psnr": float(np.mean([r.pred_psnr for r in kept])) if kept else float("nan"),
        "mean_true_psnr": (float(np.mean([v[0] for v in gt.values()])) if gt
                           else float("nan")),
        "threshold": float(fv.brisque_threshold),
    }


def select(args) -> None:
    """Stages 2-6 of this checkout on the stored reconstruction -> ``_work/selection.pkl``
    (what the pipeline's select stage writes), so the profile can start from it."""
    import pickle

    from schemas.pipeline import PipelineConfig

    from freescale_core.select.run import run_selection

    work, scene, _, g, _ = _load(Path(args.store), args.scene, selection=False)
    cfg = PipelineConfig.from_preset(args.preset)
    sv, _ = scene.views_for(_recon_split(Path(args.store), cfg))
    t0 = time.perf_counter()
    sel = run_selection(g, sv.cameras, cfg.select, seed=cfg.seed, scene_id=args.scene,
                        capture_order=sv.capture_order, points=sv.points_xyz,
                        train_masks=sv.load_mask if sv.has_masks else None)
    dt = time.perf_counter() - t0
    tmp = work / "selection.pkl.tmp"
    with open(tmp, "wb") as f:
        pickle.dump(sel, f)
    os.replace(tmp, work / "selection.pkl")
    c = sel.counts
    print(f"{args.scene}: selection {dt:.1f} s, {c.get('n_feasible')} feasible, "
          f"{c.get('n_selected')} selected, {c.get('n_reserve', 0)} reserve")


def _spawn(arm: str, args, old: Path | None, extra=()) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(old) if arm == "old" else str(ROOT)
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        out = f.name
    cmd = [sys.executable, str(Path(__file__).resolve()), "_worker", "--arm", arm,
           "--store", args.store, "--scene", args.scene, "--preset", args.preset,
           "--out", out, *extra]
    if args.scene_path:
        cmd += ["--scene-path", args.scene_path]
    subprocess.run(cmd, check=True, env=env, cwd=str(ROOT))
    res = json.loads(Path(out).read_text())
    os.unlink(out)
    return res


def _med(rows, key):
    return statistics.median(key(r) for r in rows)


def profile(args) -> None:
    arms = args.arms.split(",")
    old = old_tree(args.old_commit) if "old" in arms else None
    runs: dict[str, list[dict]] = {a: [] for a in arms}
    if "old" in arms and args.warm:
        _spawn("old", args, old)  # numba compiles the old tree's kernels once
    for _ in range(args.repeats):
        for a in arms:
            runs[a].append(_spawn(a, args, old))
            r = runs[a][-1]
            print(f"# {a}: {r['seconds']:.1f} s, {r['n_final']} kept", file=sys.stderr)
    print(f"scene {args.scene}, preset {args.preset}, median of {args.repeats} run(s) per arm,"
          f" arms alternating; old = {args.old_commit}")
    hdr = "| part (s) | " + " | ".join(arms) + " |"
    print(hdr)
    print("|---|" + "---|" * len(arms))
    for p in PARTS:
        vals = [_med(runs[a], lambda r: r["parts"].get(p, 0.0)) for a in arms]
        if any(v > 0 for v in vals):
            print(f"| {p} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
    rows = [("stage total (s)", lambda r: r["seconds"], "{:.1f}"),
            ("writing (s)", lambda r: r["parts"].get("writing", 0.0), "{:.2f}"),
            ("s per 100 kept views", lambda r: 100 * r["seconds"] / max(r["n_final"], 1),
             "{:.1f}"),
            ("s per 100 kept views without ground_truth",
             lambda r: 100 * (r["seconds"] - r["parts"].get("ground_truth", 0.0))
             / max(r["n_final"], 1), "{:.1f}"),
            ("renders", lambda r: r["counts"].get("rendered", 0), "{:.0f}"),
            ("selected (+ reserve rendered)", lambda r: r["counts"].get("candidates", 0),
             "{:.0f}"),
            ("passed", lambda r: r["counts"].get("passed", 0), "{:.0f}"),
            ("kept", lambda r: r["n_final"], "{:.0f}"),
            ("mean pred PSNR kept (dB)", lambda r: r["mean_pred_psnr"], "{:.2f}"),
            ("mean true PSNR kept (dB)", lambda r: r["mean_true_psnr"], "{:.2f}")]
    for name, key, fmt in rows:
        vals = [_med(runs[a], key) for a in arms]
        print(f"| {name} | " + " | ".join(fmt.format(v) for v in vals) + " |")
    if len(arms) == 2:
        ratios = [o["seconds"] / n["seconds"] for o, n in zip(runs[arms[0]], runs[arms[1]])]
        per100 = [(o["seconds"] / max(o["n_final"], 1)) / (n["seconds"] / max(n["n_final"], 1))
                  for o, n in zip(runs[arms[0]], runs[arms[1]])]
        print(f"same-run ratio {arms[0]}/{arms[1]}: stage seconds "
              + ", ".join(f"{x:.1f}" for x in ratios) + "; seconds per kept view "
              + ", ".join(f"{x:.1f}" for x in per100))
    if args.json:
        Path(args.json).write_text(json.dumps(runs, indent=1))


FUNNEL_HEADER = ("| scene | source | feasible | NMS-selected | reserve drawn | passed | kept |"
                 " mean pred PSNR kept (dB) | mean true PSNR kept (dB) |")


def published_funnel(store: Path, sid: str) -> dict:
    """The funnel of what ``store`` published for ``sid`` (its ``CURRENT`` version)."""
    import numpy as np
    import pyarrow.parquet as pq

    sdir = store / "scenes" / sid
    cur = sdir / "CURRENT"
    if not cur.is_file():
        raise SystemExit(f"{sdir}: no published version (no CURRENT file)")
    path = sdir / cur.read_text().strip() / "views.parquet"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (scene {sid} was not published)")
    d = pq.read_table(path, columns=["kind", "disposition", "suppress_reason", "passed",
                                     "pred_psnr", "gt_psnr_render"]).to_pydict()
    kind, disp = np.array(d["kind"]), np.array(d["disposition"])
    cand = kind == "candidate"
    rendered = cand & np.isin(disp, ["free_view", "rejected"])
    reserve = rendered & (np.array(d["suppress_reason"]) == "overlap")
    kept = disp == "free_view"
    pred = np.array(d["pred_psnr"], float)[kept]
    true = np.array(d["gt_psnr_render"], float)[kept]
    return {"scene": sid, "source": f"published {path.parent.name}",
            "n_feasible": int((cand & (disp != "infeasible")).sum()),
            "n_selected": int((rendered & ~reserve).sum()), "reserve_drawn": int(reserve.sum()),
            "passed": int((rendered & np.array(d["passed"], bool)).sum()),
            "kept": int(kept.sum()),
            "mean_pred_psnr": float(pred.mean()) if pred.size else float("nan"),
            "mean_true_psnr": (float(np.nanmean(true)) if np.isfinite(true).any()
                               else float("nan"))}


def _funnel_row(r: dict) -> str:
    def f(x):
        return "-" if x != x else f"{x:.2f}"
    return (f"| {r['scene']} | {r['source']} | {r['n_feasible']} | {r['n_selected']} | "
            f"{r['reserve_drawn']} | {r['passed']} | {r['kept']} | {f(r['mean_pred_psnr'])} | "
            f"{f(r['mean_true_psnr'])} |")


def funnel(args) -> None:
    rows = []
    print(FUNNEL_HEADER)
    print("|---|---|---|---|---|---|---|---|---|")
    if not args.rerun:
        for sid in args.scenes:
            rows.append(published_funnel(Path(args.store), sid))
            print(_funnel_row(rows[-1]), flush=True)
    else:
        arms = ["old", "new"] if args.old else ["new"]
        old = old_tree(args.old_commit) if args.old else None
        paths = dict(zip(args.scenes, args.scene_paths or [None] * len(args.scenes)))
        for sid in args.scenes:
            a2 = argparse.Namespace(**{**vars(args), "scene": sid,
                                       "scene_path": paths.get(sid)})
            for a in arms:
                r = _spawn(a, a2, old, ["--reselect"])
                c = r["counts"]
                code = args.old_commit if a == "old" else "this checkout"
                rows.append({"scene": sid, "source": f"{code}, {args.preset}",
                             "n_feasible": r["n_feasible"], "n_selected": r["n_selected"],
                             "reserve_drawn": c.get("reserve_drawn", 0),
                             "passed": c.get("passed", 0), "kept": r["n_final"],
                             "mean_pred_psnr": r["mean_pred_psnr"],
                             "mean_true_psnr": r["mean_true_psnr"], "n_reserve": r["n_reserve"],
                             "seconds": r["seconds"], "renders": c.get("rendered", 0)})
                print(_funnel_row(rows[-1]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("select", "profile", "funnel", "_worker"):
        p = sub.add_parser(name)
        p.add_argument("--store", required=True)
        p.add_argument("--preset", default="cpu")
        p.add_argument("--scene-path", default=None,
                       help="the scene folder (the sample scene's oracle gives true PSNR)")
        p.add_argument("--old-commit", default=OLD_COMMIT)
        if name == "funnel":
            p.add_argument("--scenes", nargs="+", required=True)
            p.add_argument("--rerun", action="store_true",
                           help="run selection + stage at --preset instead of reading the "
                                "published views")
            p.add_argument("--old", action="store_true",
                           help="with --rerun: also the --old-commit's selection + stage")
            p.add_argument("--scene-paths", nargs="+", default=None,
                           help="with --rerun: scene folders in the order of --scenes "
                                "(an oracle scene gives true PSNR)")
            p.add_argument("--json", default=None)
        else:
            p.add_argument("--scene", required=True)
        if name == "profile":
            p.add_argument("--repeats", type=int, default=3)
            p.add_argument("--arms", default="old,new")
            p.add_argument("--warm", action="store_true",
                           help="one untimed old run first (numba compiles its kernels)")
            p.add_argument("--json", default=None)
        if name == "_worker":
            p.add_argument("--arm", required=True)
            p.add_argument("--out", required=True)
            p.add_argument("--reselect", action="store_true")
    args = ap.parse_args(argv)
    if args.cmd == "_worker":
        Path(args.out).write_text(json.dumps(worker(args)))
    elif args.cmd == "select":
        select(args)
    elif args.cmd == "profile":
        profile(args)
    else:
        funnel(args)


if __name__ == "__main__":
    main()
