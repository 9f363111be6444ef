"""Speed against accuracy: the evaluation sweep behind the ``evaluate-engine`` flow (issue 16).

No Prefect here: the caller passes ``run_point(scene_dir, store_dir, cfg)``, which runs the
pipeline (the flow passes ``generate-dataset``) for one scene into a fresh store; this module
plans the points, caches them, measures them and scores them.

**Points.** A point is (label, scene, resolved ``PipelineConfig``). Labels: ``base`` (the
preset + overrides), ``<knob>=<value>`` (one knob on top of the base), ``preset:<name>``
(the presets, labelled on the chart) and, for sizing, ``<knob>=adaptive`` against
``<knob>=half`` / ``<knob>=double`` (half and double the value the adaptive rule chose *for
that scene*, set explicitly).

**Cache.** A point's key hashes the scene's input fingerprint, the full resolved config and
the code version (engine version + a hash of the pipeline's source); its store and
``result.json`` live in ``OUT/points/<key>/``. A point whose ``result.json`` exists is read,
not run: re-running a sweep with one more point computes that point only.

**Measured per point.** Wall and process-CPU seconds per stage (the stages record both in the
scene status), wall/CPU of the whole point, peak resident memory of this process while the
point ran (sampled every 0.1 s; it includes the evaluator's own baseline), the counts
(candidates, feasible, selected, free views, scarce, ``empty_reason``). ``seconds`` (the
chart's x) is the sum of the stages' wall seconds; ``wall_total`` adds the flow engine's
start-up around them, the sizes the engine
chose (grid R, Gaussian budget, training long side, iterations) and accuracy:

* procedural scenes (``scene.json``, exact oracle): every stored free view is compared with
  the oracle's true image at its final pose and intrinsics: ``fv_psnr`` / ``fv_ssim``
  (means) and ``fv_true_share`` (share of free views with PSNR >= ``true_psnr_db``);
* every scene with ``recon_split=ood``: the reconstruction's held-out PSNR / SSIM
  (``heldout_psnr`` / ``heldout_ssim``: the last 30% in capture order, never trained on),
  scored by the sweep itself at one evaluation size per scene (``eval_long_side``; the stored
  Gaussians rendered at the held-out cameras scaled to it, against the photos area-resized
  to it: :mod:`freescale_core.eval.heldout`), so points with different training resolutions
  are comparable; the pipeline's own score at the training resolution is kept as
  ``heldout_psnr_train_res``. Cached per point in ``heldout_v<k>_L<long side>.json``.

With ``downstream=["refine"]`` each point also gets its 3DGS-refinement gain (free views vs
the real-views-only baseline, :mod:`freescale_core.eval.downstream`), cached the same way.

``accuracy`` (the chart's y) is ``fv_psnr`` on procedural scenes and ``heldout_psnr`` on real
ones; a run with no free view on a procedural scene has no ``fv_psnr`` and stays off the chart
(it is in the tables).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from freescale_core.errors import StoreError
from freescale_core.eval.chart import pareto_front
from freescale_core.eval.knobs import RECON_KNOBS, apply_knob, chosen_value, scaled_value
from schemas.evaluate import EvaluateConfig
from schemas.pipeline import PipelineConfig, _deep_merge

RunPoint = Callable[[Path, Path, PipelineConfig], Any]
STAGES = ("ingest", "reconstruct", "select", "freeviews", "publish")
# the entry points of a point's result: the pipeline flow it runs and the scoring here
# (the key hashes every project module they reach, freescale_core.codekey)
POINT_ROOTS = ("flows.generate_dataset", "freescale_core.eval.sweep")

__all__ = ["Point", "SweepResult", "code_version", "plan_points", "point_key", "run_sweep",
           "score_store", "pareto_front", "aggregate"]


@dataclass
class Point:
    label: str
    scene: Path
    cfg: PipelineConfig
    knob: str = ""
    value: str = ""
    group: str = "knob"  # base | knob | preset | sizing
    seed: int | None = None  # set when the sweep repeats points over seeds

    def seeded(self, seed: int) -> "Point":
        """This point with the pipeline seed ``seed``."""
        return Point(self.label, self.scene, self.cfg.model_copy(update={"seed": int(seed)}),
                     self.knob, self.value, self.group, int(seed))

    @property
    def scene_id(self) -> str:
        return self.scene.name


@dataclass
class SweepResult:
    rows: list[dict]
    computed: list[str] = field(default_factory=list)  # keys run this time
    cached: list[str] = field(default_factory=list)  # keys read from the cache
    files: dict[str, str] = field(default_factory=dict)
    warmup_seconds: float = 0.0  # the untimed warm-up run before the first computed point


# --------------------------------------------------------------------------- keys
def code_version() -> str:
    """Engine version + the code key of a point (:data:`POINT_ROOTS`)."""
    from freescale_core import __version__
    from freescale_core.codekey import code_key

    return f"{__version__}+{code_key(POINT_ROOTS)}"


def point_key(scene: Path, cfg: PipelineConfig) -> str:
    """Hash of (scene input fingerprint, full resolved config, code version)."""
    from freescale_core.scene.fingerprint import input_fingerprint

    blob = json.dumps({"scene": input_fingerprint(scene), "name": scene.name,
                       "config": cfg.model_dump(mode="json"), "code": code_version()},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- planning
def base_config(ecfg: EvaluateConfig, extra: dict | None = None,
                preset: str | None = None) -> PipelineConfig:
    over = _deep_merge({"recon_split": ecfg.recon_split}, ecfg.overrides)
    if preset is not None:
        over = _deep_merge({"recon_split": ecfg.recon_split},
                           ecfg.preset_overrides.get(preset, {}))
    return PipelineConfig.from_preset(preset or ecfg.preset, _deep_merge(over, extra or {}))


def is_procedural(scene: Path) -> bool:
    """A scene written by the sample-scene writer (its ``scene.json`` is the exact oracle)."""
    return (Path(scene) / "scene.json").is_file()


def plan_points(scenes: list[Path], ecfg: EvaluateConfig) -> list[Point]:
    """Every point known before anything runs (sizing's half/double come later)."""
    base = base_config(ecfg)
    pts: list[Point] = []
    for sc in scenes:
        pts.append(Point(ecfg.base_label, sc, base, group="base"))
        # a real scene is scored by its held-out PSNR, which only reconstruction knobs move
        only_recon = ecfg.real_knobs == "recon" and not is_procedural(sc)
        for knob, values in ecfg.knobs.items():
            if only_recon and knob not in RECON_KNOBS:
                continue
            for v in values:
                cfg = base_config(ecfg, apply_knob(base, knob, v))
                pts.append(Point(f"{knob}={v}", sc, cfg, knob, str(v)))
        for p in ecfg.presets:
            pts.append(Point(f"preset:{p}", sc, base_config(ecfg, preset=p), group="preset"))
        for knob in ecfg.sizing:
            if only_recon and knob not in RECON_KNOBS:
                continue
            cfg = base_config(ecfg, apply_knob(base, knob, "adaptive"))
            pts.append(Point(f"{knob}=adaptive", sc, cfg, knob, "adaptive", group="sizing"))
    if ecfg.seeds:
        pts = [p.seeded(s) for p in pts for s in ecfg.seeds]
    return pts


# --------------------------------------------------------------------------- measuring
class _PeakRSS:
    """Peak resident memory (MB) of this process while the block runs (0.1 s samples)."""

    def __enter__(self):
        import psutil

        self._p = psutil.Process()
        self.peak = self._p.memory_info().rss
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.wait(0.1):
            try:
                self.peak = max(self.peak, self._p.memory_info().rss)
            except Exception:  # noqa: BLE001 - a sample lost is no error
                pass

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._p.memory_info().rss)
        self.peak_mb = self.peak / 2**20


def _f(x) -> float:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return math.nan
    return x


def score_store(store: Path, scene_id: str, scene_dir: Path, true_psnr_db: float) -> dict:
    """Status, counts, timings, chosen sizes and accuracy of one scene in a point's store."""
    from freescale_core.store.store import Store

    st = Store(store)
    status = st.read_status(scene_id)
    info, counts, secs = status.get("info", {}), status.get("counts", {}), status.get("seconds", {})
    row: dict[str, Any] = {
        "status": status.get("status", "failed") or "failed",
        "error": (status.get("error") or "")[:300],
        "empty_reason": info.get("empty_reason", ""),
        "scarce": bool(info.get("scarce", False)),
    }
    for s in STAGES:
        row[f"wall_{s}"] = _f(secs.get(s))
        row[f"cpu_{s}"] = _f(info.get(f"cpu_seconds_{s}"))
    for k in ("n_images", "n_candidates", "n_selected", "n_free_views", "n_final"):
        row[k] = _f(counts.get(k))
    infeasible = sum(_f(v) for k, v in counts.items()
                     if k.startswith("n_infeasible") and k != "n_infeasible" and _f(v) == _f(v))
    n_inf = _f(counts.get("n_infeasible")) if "n_infeasible" in counts else infeasible
    row["n_feasible"] = row["n_candidates"] - n_inf if row["n_candidates"] == row["n_candidates"] \
        else math.nan
    # sizes the engine chose, from the stage checkpoints
    rec = _done(st, scene_id, "reconstruct")
    sel = _done(st, scene_id, "select")
    res = rec.get("train_resolution") or []
    row["train_long_side"] = float(max(res)) if res else math.nan
    for k in ("n_gaussians", "n_gaussians_budget", "iterations"):
        row[k] = _f(rec.get(k))
    row["grid_R"] = _f(sel.get("grid_R"))
    row["recon_train_psnr"] = _f(info.get("recon_train_psnr"))
    # the pipeline's own held-out score, at the point's training resolution (not comparable
    # across training resolutions; the sweep's heldout_psnr is at the scene's eval size)
    row["heldout_psnr_train_res"] = _f(info.get("recon_test_psnr"))
    row["heldout_ssim_train_res"] = _f(info.get("recon_test_ssim"))
    row.update(fv_psnr=math.nan, fv_ssim=math.nan, fv_true_share=math.nan, fv_scored=0)
    if row["status"] == "ok" and (scene_dir / "scene.json").is_file():
        row.update(free_view_fidelity(store, scene_id, scene_dir, true_psnr_db))
    elif row["status"] == "ok" and (scene_dir / "turntable.json").is_file():
        row.update(free_view_fidelity(store, scene_id, scene_dir, true_psnr_db,
                                      object_only=True))
    return row


def _done(st, scene_id: str, stage: str) -> dict:
    """The stage's recorded result; {} when it has none or its record is unreadable."""
    try:
        return st.stage_result(scene_id, stage) or {}
    except StoreError:
        return {}


def free_view_fidelity(store: Path, scene_id: str, scene_dir: Path, true_psnr_db: float,
                       object_only: bool = False) -> dict:
    """PSNR / SSIM of every stored free view against the oracle at its final pose.

    ``object_only`` (a turntable scene, :mod:`freescale_core.scene.turntable`): the oracle is
    the object of ``turntable.json`` alone (its background changes per image and has no
    truth at a new pose), so PSNR is over the pixels where the true object is (depth > 0),
    SSIM is not computed, and views without object pixels are not scored."""
    from freescale_core.eval.metrics import psnr_u8, ssim_u8
    from freescale_core.eval.oracle import ground_truth_oracle
    from freescale_core.store.reader import FreeViewSet

    if object_only:
        from freescale_core.scene.sample import SampleWorld, SceneSpec

        world = SampleWorld(SceneSpec.model_validate_json(
            (scene_dir / "turntable.json").read_text()))
    else:
        world = ground_truth_oracle(scene_dir)
    fvs = FreeViewSet.open(store, scene_id)
    ids, cams = fvs.cameras("free")
    ps, ss = [], []
    for k, vid in enumerate(ids):
        img = fvs.rgb(int(vid))
        truth, depth = world.render(cams.world_from_cam[k], cams.fx[k], cams.fy[k], cams.cx[k],
                                    cams.cy[k], int(cams.width[k]), int(cams.height[k]))
        if object_only:
            m = np.asarray(depth) > 0
            if not m.any():
                continue
            ps.append(min(psnr_u8(img[m], truth[m]), 99.0))
            ss.append(math.nan)
            continue
        ps.append(min(psnr_u8(img, truth), 99.0))
        ss.append(ssim_u8(img, truth))
    if not ps:
        return {"fv_scored": 0}
    return {"fv_psnr": float(np.mean(ps)), "fv_ssim": float(np.nanmean(ss)) if
            np.isfinite(ss).any() else math.nan,
            "fv_true_share": float(np.mean(np.asarray(ps) >= true_psnr_db)),
            "fv_scored": len(ps)}


def _run_one(pt: Point, key: str, pdir: Path, run_point: RunPoint, ecfg: EvaluateConfig,
             log: Callable[[str], None]) -> dict:
    import shutil

    store = pdir / "store"
    if store.exists():  # an interrupted earlier attempt: start clean
        shutil.rmtree(store)
    log(f"point {pt.label} on {pt.scene_id}: running (key {key})")
    t0, c0 = time.perf_counter(), time.process_time()
    err = ""
    with _PeakRSS() as mem:
        try:
            run_point(pt.scene, store, pt.cfg)
        except Exception as e:  # noqa: BLE001 - recorded on the point (the store says more)
            err = f"{type(e).__name__}: {e}"
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    row = score_store(store, pt.scene_id, pt.scene, ecfg.true_psnr_db)
    if err and not row["error"]:
        row["error"] = err[:300]
    row.update(wall_total=wall, cpu_total=cpu, peak_rss_mb=mem.peak_mb,
               finished_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    log(f"point {pt.label} on {pt.scene_id}: {row['status']}, {wall:.1f} s, "
        f"{row['n_free_views']:.0f} free views, fv_psnr {row['fv_psnr']:.2f}, "
        f"heldout (training resolution) {row['heldout_psnr_train_res']:.2f}")
    return row


def _cached_part(path: Path, compute: Callable[[], dict]) -> tuple[dict, bool]:
    """A point's extra measurement cached in its own file beside ``result.json`` (so it can
    be added to, or recomputed for, a point whose pipeline run is cached): ``(dict,
    computed)``."""
    from freescale_core.store.store import write_json_atomic

    if path.is_file():
        try:
            return json.loads(path.read_text()), False
        except ValueError:
            pass
    d = compute()
    write_json_atomic(path, d)
    return d, True


def heldout_part(pt: Point, pdir: Path, row: dict, ecfg: EvaluateConfig,
                 log: Callable[[str], None]) -> dict:
    """``heldout_psnr`` / ``heldout_ssim`` of a point at the scene's evaluation size
    (:mod:`freescale_core.eval.heldout`), cached in ``pdir``."""
    from freescale_core.eval.heldout import heldout_at_eval_resolution, heldout_eval_name

    L = ecfg.eval_long_side

    def compute() -> dict:
        if row.get("status") != "ok" or not (pdir / "store").is_dir():
            return {"heldout_psnr": math.nan, "heldout_ssim": math.nan, "eval_long_side": L,
                    "heldout_eval_note": "point not ok" if (pdir / "store").is_dir()
                    else "the point's store is gone"}
        d = heldout_at_eval_resolution(pdir / "store", pt.scene_id, pt.cfg, L)
        log(f"point {pt.label} on {pt.scene_id}: held-out PSNR {d['heldout_psnr']:.2f} dB at "
            f"{d['eval_width']:.0f}x{d['eval_height']:.0f} (eval long side {L})")
        return d

    return _cached_part(pdir / heldout_eval_name(L), compute)[0]


def refine_part(pt: Point, pdir: Path, row: dict, rcfg, log: Callable[[str], None]) -> dict:
    """The point's 3DGS-refinement gain (:mod:`freescale_core.eval.downstream`), cached in
    ``pdir`` (computed once per point and refinement config)."""
    from freescale_core.eval.downstream import refine_part_name, refine_point

    return _cached_part(pdir / refine_part_name(rcfg), lambda: refine_point(
        pdir / "store", pt.scene_id, pt.scene, row, rcfg, log))[0]


def warm_up(out: Path, run_point: RunPoint, log: Callable[[str], None]) -> float:
    """Run the tiny procedural scene once at the quick sweep's budget, untimed, into a
    temporary store that is then removed: the process's one-time costs (loading or compiling
    the numba kernels, torch's and the flow engine's first use) would otherwise land on the
    first measured point (measured 2026-12-02: the first point of a sweep took 24 s where the
    same work took 4-5 s later in the run). Returns the warm-up's wall seconds."""
    import shutil
    import tempfile

    from freescale_core.eval.scenes import write_eval_scene

    scene = write_eval_scene("tiny", Path(out) / "scenes" / "tiny")
    cfg = PipelineConfig.from_preset("fast", _deep_merge({"recon_split": "ood"},
                                                         QUICK_OVERRIDES))
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="warmup-", dir=Path(out)) as tmp:
        try:
            run_point(scene, Path(tmp) / "store", cfg)
        except Exception as e:  # noqa: BLE001 - a failed warm-up only costs the warm-up
            log(f"warm-up failed ({type(e).__name__}: {e}); the first point may carry "
                "one-time costs")
        shutil.rmtree(Path(tmp) / "store", ignore_errors=True)
    dt = time.perf_counter() - t0
    log(f"warm-up: {dt:.1f} s on the tiny scene (untimed, not a point)")
    return dt


def run_sweep(scenes: list[Path], ecfg: EvaluateConfig, out: Path, run_point: RunPoint,
              log: Callable[[str], None] = print) -> SweepResult:
    """Run (or read from the cache) every point; write ``results.parquet``, ``results.csv``
    and the charts into ``out``; return the rows and what was computed."""
    from freescale_core.store.store import write_json_atomic

    out = Path(out)
    (out / "points").mkdir(parents=True, exist_ok=True)
    res = SweepResult(rows=[])
    rcfg = None
    if "refine" in ecfg.downstream:
        from freescale_core.eval.downstream import refine_config

        rcfg = refine_config(ecfg)

    def do(pt: Point) -> dict:
        key = point_key(pt.scene, pt.cfg)
        pdir = out / "points" / key
        rpath = pdir / "result.json"
        if rpath.is_file():
            row = json.loads(rpath.read_text())
            res.cached.append(key)
            if "heldout_psnr_train_res" not in row:  # a result.json from before eval_long_side
                row["heldout_psnr_train_res"] = row.pop("heldout_psnr", math.nan)
                row["heldout_ssim_train_res"] = row.pop("heldout_ssim", math.nan)
        else:
            pdir.mkdir(parents=True, exist_ok=True)
            for old in pdir.glob("*.json"):  # parts measured on an earlier, unfinished run
                old.unlink()
            row = _run_one(pt, key, pdir, run_point, ecfg, log)
            write_json_atomic(pdir / "config.json", pt.cfg.model_dump(mode="json"))
            write_json_atomic(rpath, row)
            res.computed.append(key)
        row = {**row, **heldout_part(pt, pdir, row, ecfg, log)}
        if "refine" in ecfg.downstream:
            row = {**row, **refine_part(pt, pdir, row, rcfg, log)}
        row = {**row, "label": pt.label, "group": pt.group, "knob": pt.knob,
               "value": pt.value, "scene": pt.scene_id, "scene_dir": str(pt.scene),
               "kind": "procedural" if is_procedural(pt.scene) else "real",
               "preset": pt.cfg.preset, "key": key, "seed": pt.cfg.seed}
        row["accuracy"] = row["fv_psnr"] if row["kind"] == "procedural" else row["heldout_psnr"]
        stages = [row.get(f"wall_{s}", math.nan) for s in STAGES]
        # the chart's x: the pipeline's own seconds (sum of the stages), without the flow
        # engine's start-up around them (in wall_total)
        row["seconds"] = (float(np.nansum(stages)) if any(x == x for x in stages)
                          else row["wall_total"])
        res.rows.append(row)
        return row

    planned = plan_points(scenes, ecfg)
    if ecfg.warmup and any(not (out / "points" / point_key(p.scene, p.cfg) / "result.json")
                           .is_file() for p in planned):
        res.warmup_seconds = warm_up(out, run_point, log)
    done_rows: dict[tuple[str, str, int | None], dict] = {}
    for pt in planned:
        done_rows[(pt.label, pt.scene_id, pt.seed)] = do(pt)
    base = base_config(ecfg)
    for knob in ecfg.sizing:  # half and double of what the adaptive rule chose per scene
        for sc in scenes:  # (and seed: the chosen value can depend on the run, e.g. grid R)
            for seed in (ecfg.seeds or [None]):
                chosen = chosen_value(knob, done_rows.get((f"{knob}=adaptive", sc.name, seed),
                                                          {}))
                if chosen is None:
                    log(f"sizing {knob} on {sc.name}: no chosen value (the adaptive point "
                        "failed)")
                    continue
                for name, f in (("half", 0.5), ("double", 2.0)):
                    v = scaled_value(knob, chosen, f)
                    cfg = base_config(ecfg, apply_knob(base, knob, v))
                    pt = Point(f"{knob}={name}", sc, cfg, knob, str(v), group="sizing")
                    do(pt if seed is None else pt.seeded(seed))
    res.files = write_results(res.rows, out, ecfg)
    log(f"evaluate: {len(res.rows)} points ({len(res.computed)} computed, {len(res.cached)} "
        f"from the cache) -> {out}")
    return res


# --------------------------------------------------------------------------- results
COLUMNS_FIRST = ("label", "group", "knob", "value", "scene", "kind", "preset", "status",
                 "accuracy", "seconds", "wall_total", "cpu_total", "peak_rss_mb", "fv_psnr", "fv_ssim",
                 "fv_true_share", "fv_scored", "heldout_psnr", "heldout_ssim", "heldout_nearest_psnr",
                 "heldout_mean_psnr", "eval_long_side",
                 "eval_width", "eval_height", "heldout_psnr_train_res", "refine_gain_db",
                 "refine_base_psnr", "refine_fv_psnr", "refine_cpu_seconds", "n_candidates",
                 "n_feasible", "n_selected", "n_free_views", "scarce", "empty_reason", "error",
                 "grid_R", "n_gaussians_budget", "n_gaussians", "train_long_side", "iterations")


def write_results(rows: list[dict], out: Path, ecfg: EvaluateConfig) -> dict[str, str]:
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    keys = [k for k in COLUMNS_FIRST if any(k in r for r in rows)]
    keys += sorted({k for r in rows for k in r} - set(keys))
    cols = {}
    for k in keys:
        vals = [r.get(k) for r in rows]
        if all(isinstance(v, (int, float, type(None))) and not isinstance(v, bool)
               for v in vals):
            cols[k] = pa.array([math.nan if v is None else float(v) for v in vals], pa.float64())
        elif all(isinstance(v, (bool, type(None))) for v in vals):
            cols[k] = pa.array(vals, pa.bool_())
        else:
            cols[k] = pa.array(["" if v is None else str(v) for v in vals], pa.string())
    table = pa.table(cols)
    files = {"parquet": str(out / "results.parquet"), "csv": str(out / "results.csv")}
    tmp = out / f".results.{os.getpid()}.parquet"
    pq.write_table(table, tmp)
    os.replace(tmp, files["parquet"])
    tmp = out / f".results.{os.getpid()}.csv"
    pcsv.write_csv(table, tmp)
    os.replace(tmp, files["csv"])
    from freescale_core.eval.chart import pareto_chart

    for kind, name in (("procedural", "pareto_freeview"), ("real", "pareto_heldout")):
        pts = aggregate([r for r in rows if r["kind"] == kind])
        if any(p["accuracy"] == p["accuracy"] for p in pts):
            ylabel = ("free-view PSNR vs truth (dB)" if kind == "procedural"
                      else "held-out PSNR of the reconstruction (dB)")
            files[name] = pareto_chart(pts, out / f"{name}.png", ylabel,
                                       title=f"{kind} scenes: seconds per scene vs accuracy")
    main = files.get("pareto_freeview") or files.get("pareto_heldout")
    if main:
        import shutil

        shutil.copyfile(main, out / "pareto.png")
        shutil.copyfile(Path(main).with_suffix(".json"), out / "pareto.json")
        files["pareto"] = str(out / "pareto.png")
    return files


def aggregate(rows: list[dict]) -> list[dict]:
    """One chart point per label: mean seconds per scene and mean accuracy over the scenes
    (accuracy only when every scene of the label has one). With several seeds a scene's value
    is first the mean over its seeds; ``accuracy_std`` is then the mean over scenes of the
    spread (standard deviation) over seeds, and ``n_seeds`` the seeds per scene."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["label"], []).append(r)
    out = []
    for label, rs in by.items():
        per_scene: dict[str, list[dict]] = {}
        for r in rs:
            per_scene.setdefault(r["scene"], []).append(r)
        acc_s, sec_s, std_s, share_s, gain_s = [], [], [], [], []
        for srs in per_scene.values():
            acc = [r["accuracy"] for r in srs]
            acc_s.append(float(np.mean(acc)) if all(a == a for a in acc) else math.nan)
            if len(acc) > 1 and all(a == a for a in acc):
                std_s.append(float(np.std(acc, ddof=1)))
            sec_s.append(float(np.mean([r["seconds"] for r in srs])))
            sh = [r["fv_true_share"] for r in srs if r["fv_true_share"] == r["fv_true_share"]]
            share_s.append(float(np.mean(sh)) if sh else math.nan)
            g = [r.get("refine_gain_db", math.nan) for r in srs]
            g = [x for x in g if x == x]
            gain_s.append(float(np.mean(g)) if g else math.nan)
        point = {"label": label, "group": rs[0]["group"], "n_scenes": len(per_scene),
                 "n_seeds": max(len(v) for v in per_scene.values()),
                 "seconds": float(np.mean(sec_s)),
                 "accuracy": float(np.mean(acc_s)) if all(a == a for a in acc_s) else math.nan,
                 "true_share": float(np.nanmean(share_s))
                 if any(x == x for x in share_s) else math.nan}
        if std_s:
            point["accuracy_std"] = float(np.mean(std_s))
        if any(g == g for g in gain_s):  # the downstream gain, where it was measured
            point["refine_gain_db"] = float(np.nanmean(gain_s))
        out.append(point)
    return out


# The --quick sweep (and the tests): a tiny scene, the fast preset made tiny.
QUICK_OVERRIDES = {"recon": {"max_iterations": 80, "min_iterations": 40, "densify_from": 20,
                             "densify_until": 60, "densify_every": 20, "max_long_side": 64,
                             "cap_gaussians": 2000},
                   "freeview": {"final": {"target": 10}}}


def quick_config() -> EvaluateConfig:
    """Two grid sizes (tiny budget) and the fast preset as it is, on the tiny scene."""
    return EvaluateConfig(preset="fast", overrides=QUICK_OVERRIDES,
                          knobs={"grid_r": [32, "adaptive"]}, presets=["fast"],
                          )
