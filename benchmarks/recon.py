"""Benchmark of the reconstruction stage (METHOD.md stage 1) on real and sample scenes.

Trains on the paper's OOD split (first 70% of frames in capture order) and evaluates PSNR /
SSIM on the held-out 30% at the training resolution. Prints a table; ``--json`` prints one
JSON object per row instead.

    .venv/bin/python -m benchmarks.recon                       # buddha, strecha, sample scene
    .venv/bin/python -m benchmarks.recon /path/to/scene --preset cpu --json
    .venv/bin/python -m benchmarks.recon sample --max-minutes 10
    .venv/bin/python -m benchmarks.recon sample --split every8 --max-minutes 10 --eval-every 500

``--eval-every N`` also evaluates test PSNR every N training steps (the training clock and the
time budget are paused meanwhile; the evaluation seconds are reported) and prints the training
minutes at which test PSNR first reached ``--target-db`` (28). Those minutes are an upper bound
at the resolution of N steps.

Scene arguments: a folder (COLMAP layout), a shared dataset name, or ``sample`` (the embedded
sample scene, written to a temporary folder; its images are exact ground-truth renders).
"""

from __future__ import annotations

import sys
from pathlib import Path

import argparse
import json
import os
import tempfile
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from freescale_core.eval.sweep import code_version
from freescale_core.recon.trainer import evaluate, reconstruct, sparse_points_for
from freescale_core.scene.scene import Scene
from schemas.pipeline import PipelineConfig
from schemas.recon import ReconConfig

DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))


def load(d: Path) -> Scene:
    """The project's own reader (undistortion and input pre-filter included)."""
    from freescale_core.scene.io import load_scene

    return load_scene(d)


def resolve(arg: str, tmp: Path) -> Path | None:
    if arg == "sample":
        try:
            from freescale_core.scene.sample import write_sample_scene
        except ImportError:
            print("# sample scene module not available; skipped", file=sys.stderr)
            return None
        out = tmp / "sample"
        if not out.exists():
            write_sample_scene(out)
        return out
    p = Path(arg)
    if not p.is_dir():
        p = DATASETS / arg
    if not (p / "sparse" / "0").is_dir():
        print(f"# {arg}: no COLMAP model found ({p}); skipped", file=sys.stderr)
        return None
    return p


def oracle_covis(scene_dir: Path, scene: Scene, train, test, scale: float
                 ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Sample scene only: the true images and depths (0 on the sky) of the test views at
    ``scale`` and their exact co-visibility masks (:func:`freescale_core.eval.covis.
    covisible_masks` on the oracle's depths, 2% agreement; sky counts as covered)."""
    from freescale_core.eval.covis import covisible_masks
    from freescale_core.scene.sample import SampleWorld

    world = SampleWorld.load(scene_dir)
    tr = scene.cameras.subset(train).scaled(scale)
    te = scene.cameras.subset(test).scaled(scale)

    def render(c, i):
        return world.render(c.world_from_cam[i], c.fx[i], c.fy[i], c.cx[i], c.cy[i],
                            int(c.width[i]), int(c.height[i]))

    truth = [render(te, j) for j in range(len(te))]
    masks = covisible_masks(te, [d for _, d in truth], tr, [render(tr, i)[1] for i in
                                                             range(len(tr))],
                            rel_tol=0.02, no_depth_covered=True)
    return [gt for gt, _ in truth], [d for _, d in truth], masks


def sample_coverage(scene_dir: Path, scene: Scene, gaussians, train, test, scale: float,
                    bg) -> dict:
    """Sample scene only: how much of each test view the training views saw, from the oracle.

    A test pixel is *covered* if its true surface point (oracle depth) is seen, unoccluded
    (oracle depth agrees within 2%), by at least one training view, or if it is sky. PSNR on
    covered pixels separates reconstruction error from extrapolation into unseen space.
    """
    from freescale_core.raster import render_gaussians

    te = scene.cameras.subset(test).scaled(scale)
    truth, _, masks = oracle_covis(scene_dir, scene, train, test, scale)
    cov, ps = [], []
    for j, (gt, mask) in enumerate(zip(truth, masks)):
        W, H = int(te.width[j]), int(te.height[j])
        rgb, _, _ = render_gaussians(gaussians, te.world_from_cam[j], te.fx[j], te.fy[j],
                                     te.cx[j], te.cy[j], W, H, background=bg)
        err = ((rgb.astype(np.float64) - gt / 255.0) ** 2)[mask]
        cov.append(float(mask.mean()))
        ps.append(float(-10 * np.log10(max(err.mean(), 1e-12))) if err.size else float("nan"))
    return {"test_covered_fraction": cov, "test_psnr_covered": ps,
            "test_covered_mean": float(np.mean(cov)),
            "test_psnr_covered_mean": float(np.nanmean(ps))}


# a reference model's co-visibility masks: depth agreement and search radius (docs/RECON.md)
COVIS_REL_TOL = 0.02
COVIS_SEARCH_PX = 2


def load_covis_reference(ref_dir: Path, scene_id: str):
    """The reference Gaussians of ``lab/covis.py ref`` (trained on every view)."""
    from freescale_core.scene.ply import read_ply

    p = Path(ref_dir) / scene_id / "gaussians.ply"
    if not p.is_file():
        raise SystemExit(f"{scene_id}: no reference model {p} (make it with "
                         f"`lab/covis.py ref {scene_id} --out {ref_dir}`)")
    return read_ply(p, scene_id)


def numeric_versions() -> dict:
    """Versions of the packages a run's numbers depend on (a seeded run repeats to the last
    bit only on the same ones: constraints.txt pins them for ``make install``)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for p in ("numpy", "numba", "llvmlite", "torch", "opencv-contrib-python-headless",
              "pycolmap", "scipy"):
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = None
    return out


def first_reaching(curve: list[dict], target_db: float) -> dict | None:
    """The first checkpoint of ``curve`` whose test PSNR is at least ``target_db`` (or None)."""
    return next((c for c in curve if c["test_psnr"] >= target_db), None)


def run(scene_dir: Path, cfg: ReconConfig, split: str, seed: int, verbose: bool,
        save_dir: Path | None = None, eval_every: int = 0, target_db: float = 28.0,
        covis_ref: Path | None = None, stop_after: float | None = None,
        plugins: dict | None = None, clock: str = "wall") -> dict:
    """Train ``cfg`` on ``split`` of the scene and evaluate it (a benchmark row). With
    ``eval_every`` the held-out views are scored every that many steps; ``stop_after``
    (CPU-minutes, needs ``eval_every``) ends training at the first evaluation at or past it, the
    schedule up to there unchanged (the first minutes of a longer budget's curve).
    ``plugins``: keyword arguments of the trainer that replace one of its parts (``strategy``,
    ``photometric``, ``rasterizer`` of :func:`freescale_core.recon.trainer.train`; ``None``:
    today's); ``clock``: of ``cfg.max_seconds``, ``"cpu"`` with ``--cpu-minutes``."""
    scene = load(scene_dir)
    train, test = scene.split(split)
    covis: dict[float, list] = {}  # co-visibility masks of the held-out views, per scale
    ref = None if covis_ref is None else load_covis_reference(covis_ref, scene.scene_id)

    def covis_psnr(g, scale, bg) -> dict:
        if ref is None:
            return {}
        if scale not in covis:
            from freescale_core.eval.covis import split_masks

            covis[scale] = split_masks(scene, split, scale, ref, COVIS_REL_TOL,
                                       search_px=COVIS_SEARCH_PX)
        ev = evaluate(g, scene, test, scale=scale, background=bg,
                      backend=cfg.raster_backend, masks=covis[scale])
        return {"test_psnr_covis": ev["psnr_mean"], "test_psnr_covis_per_view": ev["psnr"]}
    load0 = os.getloadavg()[0]
    curve: list[dict] = []
    cpu0 = time.process_time()
    cpu_ck = [0.0]  # process CPU seconds spent in checkpoints so far

    def checkpoint(step, g, info):
        c, t = time.process_time(), time.perf_counter()
        # the training background (learned when background_lr is set)
        bg = info.get("background", cfg.background)
        ev = evaluate(g, scene, test, scale=info["train_scale"], background=bg,
                      backend=cfg.raster_backend)
        curve.append({"step": step, "train_minutes": info["train_seconds"] / 60.0,
                      "train_cpu_minutes": (c - cpu0 - cpu_ck[0]) / 60.0,
                      "test_psnr": ev["psnr_mean"], "test_ssim": ev["ssim_mean"],
                      "n_gaussians": len(g), "sh_degree": info["sh_degree"],
                      "eval_seconds": time.perf_counter() - t,
                      "load_avg": os.getloadavg()[0], **covis_psnr(g, info["train_scale"], bg)})
        cpu_ck[0] += time.process_time() - c
        if verbose:
            print(f"#   {scene.scene_id} step {step}: {curve[-1]['train_minutes']:.2f} train min, "
                  f"test PSNR {ev['psnr_mean']:.2f} dB", file=sys.stderr, flush=True)
        return stop_after is not None and curve[-1]["train_cpu_minutes"] >= stop_after

    def progress(step, info):
        if verbose and step % 200 == 0:
            print(f"#   {scene.scene_id} step {step}: loss_ema {info['loss_ema']:.4f} "
                  f"n {info['n_gaussians']} {info['phase']} sh {info['sh_degree']}",
                  file=sys.stderr, flush=True)

    res = reconstruct(scene, cfg, seed=seed, train_idx=train, progress=progress,
                      checkpoint_every=eval_every, on_checkpoint=checkpoint, clock=clock,
                      **(plugins or {}))
    cpu_train = time.process_time() - cpu0 - cpu_ck[0]
    st = res.stats
    if save_dir is not None:
        out = save_dir / scene.scene_id
        out.mkdir(parents=True, exist_ok=True)
        res.write_ply(out / "gaussians.ply")  # with its background colour
        (out / "recon_stats.json").write_text(json.dumps(st, indent=1))
    t = time.perf_counter()
    bg = res.background  # the training background (learned when background_lr is set)
    ev = evaluate(res.gaussians, scene, test, scale=st["train_scale"], background=bg,
                  backend=cfg.raster_backend)
    cv = covis_psnr(res.gaussians, st["train_scale"], bg)
    extra = {}
    if eval_every:
        if curve and curve[-1]["step"] == st["iterations"]:
            curve.pop()  # the last checkpoint was the final model: keep its final evaluation
        curve.append({"step": st["iterations"], "train_minutes": st["recon_seconds"] / 60.0,
                      "train_cpu_minutes": cpu_train / 60.0, "test_psnr": ev["psnr_mean"],
                      "test_ssim": ev["ssim_mean"], "n_gaussians": st["n_gaussians"],
                      "sh_degree": st["sh_degree"], "eval_seconds": time.perf_counter() - t,
                      "load_avg": os.getloadavg()[0], "final": True, **cv})
        hit = first_reaching(curve, target_db)
        extra = {"eval_every": eval_every, "target_db": target_db, "test_psnr_curve": curve,
                 "checkpoint_seconds": st["checkpoint_seconds"],
                 "minutes_to_target": None if hit is None else hit["train_minutes"],
                 "cpu_minutes_to_target": None if hit is None else hit["train_cpu_minutes"],
                 "step_to_target": None if hit is None else hit["step"]}
    if ref is not None:
        extra |= {"covis_ref": str(covis_ref), "covis_rel_tol": COVIS_REL_TOL,
                  "covis_search_px": COVIS_SEARCH_PX,
                  "test_covis_fraction": [float(m.mean()) for m in covis[st["train_scale"]]],
                  "recon_test_psnr_covis": cv["test_psnr_covis"],
                  "test_psnr_covis_per_view": cv["test_psnr_covis_per_view"]}
    if (scene_dir / "scene.json").is_file():
        extra |= sample_coverage(scene_dir, scene, res.gaussians, train, test, st["train_scale"],
                                bg)
    return {
        **extra,
        "scene": scene.scene_id, "split": split,
        "n_train": len(train), "n_test": len(test),
        "n_gaussians": st["n_gaussians"], "n_gaussians_budget": st["n_gaussians_budget"],
        "iterations": st["iterations"], "width": st["train_resolution"][0],
        "height": st["train_resolution"][1], "minutes": st["recon_seconds"] / 60.0,
        "recon_seconds": st["recon_seconds"], "cpu_minutes": cpu_train / 60.0,
        "recon_train_psnr": st["recon_train_psnr"],
        "recon_test_psnr": ev["psnr_mean"], "recon_test_ssim": ev["ssim_mean"],
        "test_psnr_per_view": ev["psnr"], "eval_seconds": time.perf_counter() - t,
        "iterations_per_second": st["iterations_per_second"], "sh_degree": st["sh_degree"],
        "reasons": st["reasons"], "load_avg_start": load0, "load_avg_end": os.getloadavg()[0],
        "threads": st["threads"], "seed": seed, "train_scale": st["train_scale"],
        "gaussian_extent": st.get("gaussian_extent"),
        "n_gaussians_init": st.get("n_gaussians_init"),
        "init_triangulation": st.get("init_triangulation"),
        "stop_after": stop_after, "background": list(bg),
        "background_uncovered_share": st.get("background_uncovered_share"),
    }


# ``--compare`` arms: "new" is today's cpu preset, "new-fast" the fast one, or a preset name;
# ``NAME,FIELD=VALUE,...`` sets fields on top of one. :class:`Arms` names them; a subclass may
# add arms and trainer plug-ins (the frozen legacy arms: ``python -m lab.recon_compare``).
class Arms:
    """How ``--compare`` turns an arm's name into a ``ReconConfig`` and extra keys (recorded in
    the row's ``config``), and those into the trainer's plug-ins (:func:`run` ``plugins``)."""

    def base(self, name: str) -> tuple[ReconConfig, dict]:
        """An arm without ``,FIELD=VALUE`` sets: ``new``, ``new-fast`` or a preset name."""
        if name == "new":
            return ReconConfig.cpu(), {}
        if name == "new-fast":
            return ReconConfig.fast(), {}
        try:
            return PipelineConfig.from_preset(name).recon, {}
        except ValueError:
            raise SystemExit(f"arm {name!r}: not new, new-fast or a preset name "
                             "(paper, cpu, fast)") from None

    def split_sets(self, fields: dict) -> tuple[dict, dict]:
        """``FIELD=VALUE`` sets -> (``ReconConfig`` fields, extra keys); raises ``ValueError``
        for a bad extra value. Here every set is a ``ReconConfig`` field."""
        return fields, {}

    def plugins(self, cfg: ReconConfig, extra: dict) -> dict:
        """The trainer's plug-ins (:func:`run` ``plugins``) for ``cfg`` and the extra keys; a
        fresh set per run. Here none: today's trainer."""
        return {}

    def __call__(self, name: str) -> tuple[ReconConfig, dict]:
        """``NAME`` or ``NAME,FIELD=VALUE,...`` (e.g. ``new,background_lr=0.02``: an arm that
        differs from ``new`` in one field) -> its ``ReconConfig`` and extra keys."""
        if "," in name:
            base, *sets = split_top(name)
            cfg, extra = self(base)
            try:
                fields, more = self.split_sets(parse_sets(sets))
            except ValueError as e:
                raise SystemExit(f"arm {name!r}: {e}") from None
            return (ReconConfig.model_validate({**cfg.model_dump(), **fields}),
                    {**extra, **more})
        return self.base(name)


arm = Arms()  # today's arms: arm("new,bounds_every=7") -> (ReconConfig, {})


def arm_config(name: str) -> ReconConfig:
    """The ``ReconConfig`` of :func:`arm` ``name``."""
    return arm(name)[0]


def arm_dirname(name: str) -> str:
    """A folder name for an arm: ``'new,x=[1,2],y="a"'`` -> ``"new+x=1-2+y=a"`` (the fields of
    :func:`split_top` joined by ``+``; brackets and quotes go; other characters outside
    ``._-=`` become ``-``)."""
    def clean(part: str) -> str:
        return "".join(c if c.isalnum() or c in "._-=" else "-" for c in part if c not in "[]\"' ")

    return "+".join(clean(p) for p in split_top(name)) or "arm"


def split_top(text: str) -> list[str]:
    """Split at the commas outside brackets: ``"new,c=[[250,4],[600,2]],x=1"`` ->
    ``["new", "c=[[250,4],[600,2]]", "x=1"]`` (nested list values stay whole)."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    return parts + [cur]


def psnr_at(curve: list[dict], cpu_minutes: float) -> float | None:
    """Held-out PSNR of the last evaluation at or before ``cpu_minutes`` of training CPU time
    (None when the run's clock did not reach it or nothing was evaluated by then)."""
    if not curve or curve[-1]["train_cpu_minutes"] < cpu_minutes * 0.98:
        return None
    pts = [c for c in curve if c["train_cpu_minutes"] <= cpu_minutes * 1.02]
    return pts[-1]["test_psnr"] if pts else None


def parse_sets(items) -> dict:
    """``["field=json", ...]`` -> dict (a value that is not JSON is taken as a string)."""
    out = {}
    for it in items:
        k, sep, v = it.partition("=")
        if not sep:
            raise SystemExit(f"--set {it!r}: expected FIELD=VALUE")
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


def main(argv=None, arms: Arms | None = None, description: str | None = None) -> int:
    """The command line; ``arms`` names the ``--compare`` arms and the ``--set`` keys that are
    not ``ReconConfig`` fields (default :data:`arm`: today's trainer only)."""
    arms = arm if arms is None else arms
    ap = argparse.ArgumentParser(description=description or __doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="*", default=["buddha", "strecha_fountain-P11", "sample"])
    ap.add_argument("--preset", default="cpu", help="ReconConfig preset: paper, cpu, fast")
    ap.add_argument("--split", default="ood", choices=["ood", "every8"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="wall-clock budget per scene (annealing starts when reached)")
    ap.add_argument("--max-iterations", type=int, default=None)
    ap.add_argument("--max-long-side", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--save-dir", type=Path, default=None,
                    help="write <scene>/gaussians.ply and recon_stats.json here (with --compare: "
                    "under <arm>/<split>/)")
    ap.add_argument("--eval-every", type=int, default=0, metavar="N",
                    help="also evaluate test PSNR every N steps (clock paused while it runs) "
                    "and report the training minutes at which it first reached --target-db")
    ap.add_argument("--target-db", type=float, default=28.0)
    ap.add_argument("--compare", nargs="+", default=None, metavar="ARM",
                    help="train every scene and split with each arm (new, new-fast or a preset; "
                    "ARM,FIELD=VALUE,... changes fields of one arm), "
                    "alternating the order per scene so that load drift "
                    "hits both; prints held-out PSNR at --at CPU-minutes per arm. With --opensplat BIN "
                    "OpenSplat runs after them on each scene (at the cpu preset's resolution); "
                    "`--compare opensplat` runs it alone")
    ap.add_argument("--splits", nargs="+", default=None, choices=["ood", "every8"],
                    help="several splits (default: --split)")
    ap.add_argument("--every8-scenes", nargs="*", default=None,
                    help="with --splits ood every8: only these scenes get the every8 split")
    ap.add_argument("--cpu-minutes", type=float, default=None,
                    help="training budget in process-CPU minutes (the trainer's cpu clock), per run")
    ap.add_argument("--stop-after", type=float, default=None, metavar="CPU_MIN",
                    help="with --eval-every: end each run at its first evaluation at or past this "
                    "many CPU-minutes, its schedule (budget) unchanged up to there")
    ap.add_argument("--opensplat-seed", type=int, default=None, metavar="N",
                    help="OPENSPLAT_SEED for the OpenSplat arm (honoured by a binary built with "
                    "the seed patch of docs/RECON.md; unset: its hard-coded 42)")
    ap.add_argument("--at", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.0, 10.0],
                    help="CPU-minutes at which --compare reports PSNR")
    ap.add_argument("--out", type=Path, default=None, help="append JSON rows to this file")
    ap.add_argument("--opensplat", default=None, metavar="BIN",
                    help="OpenSplat binary for an external reference arm (see docs/RECON.md); "
                    "without one the arm is skipped with the reason")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a ReconConfig field (JSON value), e.g. --set bounds_every=100")
    ap.add_argument("--breakdown", type=int, nargs=2, default=None, metavar=("FROM", "TO"),
                    help="time each section of a training step (raster forward, loss, backward, "
                    "optimiser, densification, ...) over steps FROM+1..TO of --preset on each "
                    "scene and --split, and print ms per step instead of training to the end")
    ap.add_argument("--covis-ref", type=Path, default=None, metavar="DIR",
                    help="also score held-out PSNR on the pixels some training view saw, with "
                    "masks cut by DIR/<scene>/gaussians.ply (lab/covis.py ref)")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)

    upd = {}
    if a.max_minutes is not None:
        upd["max_seconds"] = 60.0 * a.max_minutes
    if a.max_iterations is not None:
        upd["max_iterations"] = a.max_iterations
    if a.max_long_side is not None:
        upd["max_long_side"] = a.max_long_side
    if a.threads is not None:
        upd["threads"] = a.threads
    upd |= parse_sets(a.set)
    try:
        upd, extra = arms.split_sets(upd)
    except ValueError as e:
        ap.error(str(e))
    if bad := sorted(set(upd) - set(ReconConfig.model_fields)):
        ap.error(f"--set {', '.join(bad)}: not a ReconConfig field")
    if a.cpu_minutes is not None:
        upd |= {"max_seconds": 60.0 * a.cpu_minutes}
    clock = "wall" if a.cpu_minutes is None else "cpu"
    if a.stop_after is not None and not a.eval_every:
        ap.error("--stop-after needs --eval-every")
    if a.compare:
        return compare(a, upd, extra, clock, arms)
    if a.breakdown:
        if extra:
            ap.error(f"--breakdown runs the preset's trainer; no switches {sorted(extra)}")
        return breakdown(a, upd)
    cfg = PipelineConfig.from_preset(a.preset).recon.model_copy(update=upd)
    cfg = ReconConfig.model_validate(cfg.model_dump())

    rows = []
    with tempfile.TemporaryDirectory(prefix="freescale_bench_recon_") as tmp:
        for s in a.scenes:
            d = resolve(s, Path(tmp))
            if d is None:
                continue
            row = run(d, cfg, a.split, a.seed, a.verbose, a.save_dir, a.eval_every,
                      a.target_db, a.covis_ref, a.stop_after, arms.plugins(cfg, extra), clock)
            row["preset"] = a.preset
            rows.append(row)
            if a.json:
                print(json.dumps(row), flush=True)
    if not a.json:
        print(f"# preset {a.preset}, split {a.split}, seed {a.seed}, {os.cpu_count()} cores")
        hdr = (f"{'scene':<22} {'n_gauss':>8} {'iters':>6} {'resolution':>10} {'min':>6} "
               f"{'cpu min':>7} {'train dB':>8} {'test dB':>8} {'test SSIM':>9} {'it/s':>6} "
               f"{'load':>9}")
        print(hdr)
        for r in rows:
            print(f"{r['scene']:<22} {r['n_gaussians']:>8} {r['iterations']:>6} "
                  f"{r['width']:>4}x{r['height']:<5} {r['minutes']:>6.2f} "
                  f"{r['cpu_minutes']:>7.2f} {r['recon_train_psnr']:>8.2f} "
                  f"{r['recon_test_psnr']:>8.2f} "
                  f"{r['recon_test_ssim']:>9.3f} {r['iterations_per_second']:>6.2f} "
                  f"{r['load_avg_start']:>4.1f}/{r['load_avg_end']:<4.1f}")
        for r in rows:
            if "test_covered_mean" in r:
                print(f"# {r['scene']}: oracle coverage of test views by training views "
                      f"{r['test_covered_mean']:.1%} (per view "
                      f"{[round(c, 2) for c in r['test_covered_fraction']]}); test PSNR on "
                      f"covered pixels {r['test_psnr_covered_mean']:.2f} dB")
            print(f"# {r['scene']}: test PSNR per view "
                  f"{[round(p, 1) for p in r['test_psnr_per_view']]}")
        for r in rows:
            if "test_psnr_curve" not in r:
                continue
            print(f"# {r['scene']}: test PSNR every {r['eval_every']} steps (clock paused for "
                  f"{r['checkpoint_seconds']:.0f} s of evaluation):")
            print(f"#   {'step':>6} {'train min':>9} {'cpu min':>8} {'test dB':>8} "
                  f"{'test SSIM':>9} {'n_gauss':>8} {'load':>5}")
            for c in r["test_psnr_curve"]:
                print(f"#   {c['step']:>6} {c['train_minutes']:>9.2f} "
                      f"{c['train_cpu_minutes']:>8.2f} {c['test_psnr']:>8.2f} "
                      f"{c['test_ssim']:>9.3f} {c['n_gaussians']:>8} {c['load_avg']:>5.1f}"
                      + ("  (final)" if c.get("final") else ""))
            if r["minutes_to_target"] is None:
                print(f"# {r['scene']}: test PSNR never reached {r['target_db']:g} dB")
            else:
                print(f"# {r['scene']}: test PSNR first >= {r['target_db']:g} dB at step "
                      f"{r['step_to_target']}, {r['minutes_to_target']:.2f} training minutes "
                      f"({r['cpu_minutes_to_target']:.2f} process-CPU minutes)")
        for r in rows:
            e = r.get("gaussian_extent")
            if e:
                print(f"# {r['scene']}: Gaussian extent: {e['share_beyond']:.2%} of {e['n']} "
                      f"beyond {e['beyond']:g} R, farthest {e['farthest']:.1f} R "
                      f"(R = {e['bound_radius']:.3g}: half-diagonal of cameras + points box)")
        for r in rows:
            print(f"# {r['scene']}: " + "; ".join(f"{k}: {v}" for k, v in r["reasons"].items()))
    return 0


class _Enough(Exception):
    pass


def step_breakdown(scene_dir: Path, cfg: ReconConfig, split: str, seed: int, start: int,
                   stop: int) -> dict:
    """Wall and process-CPU milliseconds per training step of each section of the step
    (:func:`freescale_core.recon.trainer.train` ``profile=``), over steps ``start+1..stop``."""
    from freescale_core.recon.trainer import train

    scene = load(scene_dir)
    tr, _ = scene.split(split)
    prof: dict[str, list[float]] = {}
    snap: dict[str, list[float]] = {}
    info: dict = {}

    def on_step(step, state, _):
        if step == start:
            snap.update({k: list(v) for k, v in prof.items()})
        if step == stop:
            info["n_gaussians"] = int(state.params["means"].shape[0])
            raise _Enough

    try:
        train(scene, cfg, seed, train_idx=tr, on_step=[on_step], profile=prof)
    except _Enough:
        pass
    if "n_gaussians" not in info:
        raise SystemExit(f"{scene.scene_id}: training ended before step {stop}")
    n = stop - start
    ms = {k: [1e3 * (v[0] - snap.get(k, [0, 0])[0]) / n, 1e3 * (v[1] - snap.get(k, [0, 0])[1]) / n]
          for k, v in prof.items()}
    return {"scene": scene.scene_id, "split": split, "from": start, "to": stop,
            "n_gaussians": info["n_gaussians"], "ms_per_step": ms}


def breakdown(a, upd: dict) -> int:
    cfg = PipelineConfig.from_preset(a.preset).recon.model_copy(update=upd)
    cfg = ReconConfig.model_validate(cfg.model_dump())
    start, stop = a.breakdown
    order = ["view", "raster_forward", "loss", "backward", "optimizer", "strategy", "other"]
    with tempfile.TemporaryDirectory(prefix="freescale_bench_recon_") as tmp:
        warm_up(Path(tmp))
        for s in a.scenes:
            d = resolve(s, Path(tmp))
            if d is None:
                continue
            r = step_breakdown(d, cfg, a.split, a.seed, start, stop)
            if a.json:
                print(json.dumps(r), flush=True)
                continue
            tot = [sum(v[i] for v in r["ms_per_step"].values()) for i in (0, 1)]
            print(f"# {r['scene']} {a.split}, preset {a.preset}, steps {start + 1}..{stop}, "
                  f"{r['n_gaussians']} Gaussians at the end")
            print(f"{'section':<16} {'wall ms':>8} {'cpu ms':>8} {'share':>6}")
            for k in order + sorted(set(r["ms_per_step"]) - set(order)):
                if k in r["ms_per_step"]:
                    w, c = r["ms_per_step"][k]
                    print(f"{k:<16} {w:>8.2f} {c:>8.2f} {c / max(tot[1], 1e-9):>6.1%}")
            print(f"{'total':<16} {tot[0]:>8.2f} {tot[1]:>8.2f}")
    return 0


def compare(a, upd: dict, extra: dict | None = None, clock: str = "wall",
            names: Arms | None = None) -> int:
    """``--compare``: every scene x split x arm, arms alternating, one table (``upd`` and the
    ``extra`` keys on top of every arm; ``names``: how arms are named, default :data:`arm`)."""
    names = arm if names is None else names
    arms = {}
    for n in a.compare:
        if n != "opensplat":
            cfg, sw = names(n)
            arms[n] = (ReconConfig.model_validate(cfg.model_copy(update=upd).model_dump()),
                       {**sw, **(extra or {})})
    status = opensplat_status(a.opensplat)
    use_opensplat = status.startswith("runs")
    print(f"# OpenSplat arm: {status}", file=sys.stderr, flush=True)
    splits = a.splits or [a.split]
    eval_every = a.eval_every or 100
    rows = []
    with tempfile.TemporaryDirectory(prefix="freescale_bench_recon_") as tmp:
        warm_up(Path(tmp))  # compile the numba kernels before the first arm's clock runs
        for si, s in enumerate(a.scenes):
            d = resolve(s, Path(tmp))
            if d is None:
                continue
            for split in splits:
                if (split == "every8" and a.every8_scenes is not None
                        and s not in a.every8_scenes):
                    continue
                order = list(arms) if si % 2 == 0 else list(arms)[::-1]
                for name in order:
                    save = (None if a.save_dir is None
                            else a.save_dir / arm_dirname(name) / split)
                    cfg, sw = arms[name]
                    row = run(d, cfg, split, a.seed, a.verbose, save, eval_every,
                              a.target_db, a.covis_ref, a.stop_after,
                              names.plugins(cfg, sw), clock)
                    row["arm"] = name
                    # an arm's extra keys (e.g. a legacy arm's switches under their old keys,
                    # as rows before they left the schema recorded them)
                    row["config"] = {**cfg.model_dump(mode="json"), **sw,
                                     "budget_clock": clock}
                    row["commit"] = code_version()
                    row["versions"] = numeric_versions()
                    row["psnr_at"] = {str(t): psnr_at(row["test_psnr_curve"], t) for t in a.at}
                    rows.append(row)
                    print(f"# {row['scene']} {split} {name}: {row['iterations']} steps, "
                          f"{row['cpu_minutes']:.2f} cpu min, test {row['recon_test_psnr']:.2f} dB"
                          f", extent {row['gaussian_extent']['share_beyond']:.2%} beyond 5R, "
                          f"farthest {row['gaussian_extent']['farthest']:.1f} R",
                          file=sys.stderr, flush=True)
                    if a.out is not None:
                        with open(a.out, "a") as fh:
                            fh.write(json.dumps(row) + "\n")
                if use_opensplat:
                    row = run_opensplat(a.opensplat, d, split, train_scale(d, split),
                                        a.cpu_minutes or 10.0, eval_every, Path(tmp),
                                        a.verbose, a.opensplat_seed,
                                        upd.get("init_points", "train"))
                    row["psnr_at"] = {str(t): psnr_at(row["test_psnr_curve"], t) for t in a.at}
                    rows.append(row)
                    print(f"# {row['scene']} {split} opensplat: {row['iterations']} steps, "
                          f"{row['cpu_minutes']:.2f} cpu min, best test "
                          f"{row['best_test_psnr']:.2f} dB at {row['best_cpu_minutes']:.2f} "
                          "cpu min", file=sys.stderr, flush=True)
                    if a.out is not None:
                        with open(a.out, "a") as fh:
                            fh.write(json.dumps(row) + "\n")
    print_compare(rows, a.at)
    return 0


def opensplat_status(binary: str | None) -> str:
    """Why the OpenSplat reference arm runs or is skipped."""
    import shutil

    if binary is None:
        return ("skipped: no --opensplat binary given (build it as docs/RECON.md says: "
                "OpenSplat 1.1.5 from source on the pinned torch's libtorch, GPU_RUNTIME=CPU)")
    if shutil.which(binary) is None and not Path(binary).is_file():
        return f"skipped: {binary} not found"
    return f"runs: {binary}"


# OpenSplat's background: nerfstudio's default colour. In 1.1.5 the tensor requires grad but
# belongs to no optimiser, so it stays this colour for the whole run (src/model.cpp
# setupOptimizers): its renders are evaluated on it, as it trained.
OPENSPLAT_BACKGROUND = (0.6130, 0.0101, 0.3984)


def _proc_cpu_seconds(pid: int) -> float:
    """utime + stime of a live process, from /proc (Linux)."""
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def train_scale(scene_dir: Path, split: str, preset: str = "cpu") -> float:
    """The training resolution our ``preset`` picks for this scene and split (the same rule
    and probe images as :func:`freescale_core.recon.trainer.reconstruct`)."""
    from freescale_core.recon.trainer import choose_resolution

    scene = load(scene_dir)
    train = np.asarray(scene.split(split)[0], np.int64)
    cams = scene.cameras.subset(train)
    probe = [scene.load_image(int(i)) for i in train[np.linspace(0, len(train) - 1,
                                                                   min(3, len(train))).astype(int)]]
    return choose_resolution(cams.width, cams.height, arm_config(preset), probe)[0]


def centre_principal_point(img: np.ndarray, cx: float, cy: float,
                           tol: float = 1e-3) -> tuple[np.ndarray, tuple[float, float]]:
    """``img [H, W, C]`` with principal point ``(cx, cy)`` (pixel centres at +0.5) as the same
    camera with the principal point at the centre of a smaller image: translated by
    ``(W'/2 - cx, H'/2 - cy)`` (Lanczos; exact for whole-pixel offsets) and cropped to
    ``W' = W - 2 ceil(|cx - W/2|)`` (likewise H'), so every output pixel comes from inside the
    input. Returns the image and its new ``(cx, cy) = (W'/2, H'/2)``; unchanged within ``tol``."""
    import cv2

    h, w = img.shape[:2]
    dx, dy = cx - w / 2.0, cy - h / 2.0
    if abs(dx) <= tol and abs(dy) <= tol:
        return img, (cx, cy)
    w2 = w - 2 * int(np.ceil(abs(dx) - tol))
    h2 = h - 2 * int(np.ceil(abs(dy) - tol))
    m = np.array([[1.0, 0.0, w2 / 2.0 - cx], [0.0, 1.0, h2 / 2.0 - cy]])
    out = cv2.warpAffine(img, m, (w2, h2), flags=cv2.INTER_LANCZOS4,
                         borderMode=cv2.BORDER_REPLICATE)
    return out, (w2 / 2.0, h2 / 2.0)


def write_opensplat_project(scene: Scene, train, scale: float, out: Path,
                            init_points: str = "train") -> None:
    """The training split as a nerfstudio project OpenSplat reads: undistorted images at the
    training resolution (our reader's undistortion and the trainer's INTER_AREA resize), PINHOLE
    intrinsics, camera-to-world in OpenGL axes, the sparse points as an ASCII PLY.

    Each image is also resampled so that its principal point is the image centre
    (:func:`centre_principal_point`): OpenSplat 1.1.5's CPU projection
    (``project_gaussians_forward_tensor_cpu``) places Gaussians with an OpenGL projection
    matrix built from the field of view alone, i.e. at ``cx = w/2, cy = h/2`` whatever
    ``cx, cy`` say (its GPU kernels do use them). dtu_scan24's principal point is 7.4 and 6.1 px
    off centre at 384 px, strecha's 2.6 and 2.9; the others' under 0.4."""
    import cv2

    from freescale_core.geometry.cameras import world_from_cam_to_nerfstudio
    from freescale_core.recon.trainer import _resize
    from freescale_core.scene.ply import write_ply_points

    cams = scene.cameras.subset(np.asarray(train)).scaled(scale)
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for j, i in enumerate(train):
        img = _resize(scene.load_image(int(i)), cams.width[j], cams.height[j])
        rel = f"images/{j:04d}.png"
        u8 = np.clip(np.round(np.asarray(img, np.float64) * (255.0 if img.dtype != np.uint8
                                                               else 1.0)), 0, 255)
        u8, (cx, cy) = centre_principal_point(u8.astype(np.uint8), float(cams.cx[j]),
                                              float(cams.cy[j]))
        cv2.imwrite(str(out / rel), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
        frames.append({"file_path": rel, "w": int(u8.shape[1]), "h": int(u8.shape[0]),
                       "fl_x": float(cams.fx[j]), "fl_y": float(cams.fy[j]),
                       "cx": cx, "cy": cy,
                       "transform_matrix":
                           world_from_cam_to_nerfstudio(cams.world_from_cam[j]).tolist()})
    # the same sparse points our arms start from (ReconConfig.init_points)
    xyz, rgb, _ = sparse_points_for(scene, ReconConfig(init_points=init_points), train)
    write_ply_points(out / "points.ply", xyz, rgb, ascii=True)
    (out / "transforms.json").write_text(json.dumps(
        {"camera_model": "PINHOLE", "frames": frames, "ply_file_path": "points.ply"}))


def run_opensplat(binary: str, scene_dir: Path, split: str, scale: float, cpu_minutes: float,
                  save_every: int, tmp: Path, verbose: bool = False,
                  seed: int | None = None, init_points: str = "train") -> dict:
    """Train OpenSplat (``--cpu``, one thread, fixed resolution) on the training split until
    ``cpu_minutes`` of its process-CPU time, saving a PLY every ``save_every`` steps; then
    evaluate every saved PLY on the held-out views with the same evaluator as our arms.

    The CPU time of each checkpoint is read from /proc when its file appears (polled every
    0.1 s), so the curve is in the same process-CPU minutes as the trainer's ``clock="cpu"``.
    OpenSplat runs its default 30k-step schedule and is stopped at the budget. ``seed`` is
    passed as ``OPENSPLAT_SEED`` (a binary with the seed patch of docs/RECON.md uses it for its
    initial rotations and camera order; upstream 1.1.5 ignores it and uses 42) and recorded as
    the row's ``opensplat_seed`` (None: not set, 42). ``init_points``: which sparse points it
    starts from, as ``ReconConfig.init_points`` (the same as our arms')."""
    import subprocess

    from freescale_core.scene.ply import read_ply

    scene = load(scene_dir)
    train, test = scene.split(split)
    proj = tmp / f"opensplat_{scene.scene_id}_{split}"
    if proj.exists():
        import shutil
        shutil.rmtree(proj)
    write_opensplat_project(scene, train, scale, proj, init_points)
    out = proj / "out"
    out.mkdir()
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("OPENSPLAT_SEED", None)
    if seed is not None:
        env["OPENSPLAT_SEED"] = str(seed)
    cmd = [binary, str(proj), "--cpu", "--keep-crs", "--num-downscales", "0", "-n", "30000",
           "-s", str(save_every), "-o", str(out / "splat.ply")]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    import threading

    log: list[str] = []
    reader = threading.Thread(target=lambda: log.extend(proc.stdout), daemon=True)
    reader.start()
    seen: dict[str, float] = {}
    cpu = 0.0
    while proc.poll() is None:
        try:
            cpu = _proc_cpu_seconds(proc.pid)
        except (OSError, IndexError):
            break
        for f in out.glob("splat_*.ply"):
            if f.name not in seen:
                seen[f.name] = cpu
        if cpu >= 60.0 * cpu_minutes:
            proc.terminate()
            break
        time.sleep(0.1)
    proc.wait()
    reader.join(timeout=5)
    wall = time.perf_counter() - t0
    if not seen and proc.returncode not in (0, -15):
        raise RuntimeError(f"OpenSplat failed on {scene.scene_id} (exit {proc.returncode}): "
                           + "".join(log[-20:]))
    curve = []
    ckpts = sorted(seen, key=lambda n: int(n.split("_")[-1].split(".")[0]))
    for name in ckpts:
        step = int(name.split("_")[-1].split(".")[0])
        try:
            g = read_ply(out / name, scene_id=scene.scene_id)
        except Exception as e:  # the last file may be cut short by the stop
            print(f"# opensplat {scene.scene_id}: {name} unreadable ({e}); skipped",
                  file=sys.stderr)
            continue
        bg = OPENSPLAT_BACKGROUND
        ev = evaluate(g, scene, test, scale=scale, background=bg)
        curve.append({"step": step, "train_cpu_minutes": seen[name] / 60.0,
                      "train_minutes": float("nan"), "test_psnr": ev["psnr_mean"],
                      "test_ssim": ev["ssim_mean"], "n_gaussians": len(g),
                      "background": bg})
        if verbose:
            print(f"#   opensplat {scene.scene_id} step {step}: {seen[name] / 60:.2f} cpu min,"
                  f" test {ev['psnr_mean']:.2f} dB", file=sys.stderr, flush=True)
    last = curve[-1] if curve else {"test_psnr": float("nan"), "test_ssim": float("nan"),
                                    "step": 0, "n_gaussians": 0}
    best = max(curve, key=lambda c: c["test_psnr"]) if curve else last
    return {"scene": scene.scene_id, "split": split, "arm": "opensplat",
            "n_train": len(train), "n_test": len(test), "test_psnr_curve": curve,
            "recon_test_psnr": last["test_psnr"], "recon_test_ssim": last["test_ssim"],
            "best_test_psnr": best["test_psnr"],
            "best_cpu_minutes": best.get("train_cpu_minutes", float("nan")),
            "iterations": last["step"], "n_gaussians": last["n_gaussians"],
            "cpu_minutes": cpu / 60.0, "minutes": wall / 60.0, "train_scale": scale,
            "gaussian_extent": None, "opensplat_cmd": " ".join(cmd), "opensplat_seed": seed,
            "init_points": init_points}


def warm_up(tmp: Path) -> None:
    """A few steps on a tiny sample scene: JIT compilation out of the first measured run."""
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp / "warmup", n_views=4, width=48, height=36, seed=0,
                           n_points=200)
    cfg = ReconConfig.fast().model_copy(update={"max_iterations": 3, "min_iterations": 3})
    reconstruct(load(d), cfg, seed=0)


def print_compare(rows: list[dict], at: list[float]) -> None:
    """Table: per scene, split and arm, held-out PSNR at each CPU-minute mark, final PSNR,
    steps, and the Gaussians' extent; then per-arm means over rows where all arms have a
    value."""
    hdr = (f"{'scene':<22} {'split':<6} {'arm':<9} " + " ".join(f"{f'@{t:g}m':>6}" for t in at)
           + f" {'final':>6} {'cpu min':>7} {'steps':>6} {'>5R %':>6} {'max R':>7}")
    print(hdr)
    for r in rows:
        e = r.get("gaussian_extent") or {}
        cells = " ".join(f"{v:>6.2f}" if (v := r["psnr_at"].get(str(t))) is not None
                         else f"{'-':>6}" for t in at)
        print(f"{r['scene']:<22} {r['split']:<6} {r['arm']:<9} {cells} "
              f"{r['recon_test_psnr']:>6.2f} {r['cpu_minutes']:>7.2f} {r['iterations']:>6} "
              f"{100 * e.get('share_beyond', float('nan')):>6.2f} "
              f"{e.get('farthest', float('nan')):>7.1f}")
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    if not arms:
        return
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["scene"], r["split"]), {})[r["arm"]] = r
    for t in at:
        vals = {n: [] for n in arms}
        for g in groups.values():
            v = {n: g[n]["psnr_at"].get(str(t)) for n in arms if n in g}
            if len(v) == len(arms) and all(x is not None for x in v.values()):
                for n in arms:
                    vals[n].append(v[n])
        if vals[arms[0]]:
            print(f"# mean held-out PSNR at {t:g} CPU-min over {len(vals[arms[0]])} scene-splits: "
                  + ", ".join(f"{n} {np.mean(vals[n]):.2f} dB" for n in arms))


if __name__ == "__main__":
    raise SystemExit(main())
