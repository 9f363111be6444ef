"""The evaluate-engine sweep (issue 16): results, chart and the point cache.

The points run the real stage chain (``tests/conftest.py::build_store``: the tasks'
functions, the publish path of ``generate-dataset``) without a Prefect server, on the tiny
procedural scene with a tiny budget, so the test takes seconds per point.
"""

from __future__ import annotations

import json

import pyarrow.csv as pcsv
import pyarrow.parquet as pq

from flows import cli
from freescale_core.eval.scenes import write_eval_scene
from freescale_core.eval.sweep import pareto_front, run_sweep
from schemas.evaluate import EvaluateConfig
from tests.conftest import build_store

TINY = {"recon": {"max_iterations": 40, "min_iterations": 20, "densify_from": 10,
                  "densify_until": 30, "densify_every": 10, "max_long_side": 48,
                  "cap_gaussians": 1500},
        "select": {"candidates": {"n_traj": 2}},
        "freeview": {"final": {"target": 5}}}


def test_sweep_writes_results_and_caches_points(tmp_path, monkeypatch):
    import freescale_core.store.figures as figures

    # the per-scene figures are not what is scored here; skipping them saves seconds a point
    monkeypatch.setattr(figures, "save_figures", lambda *a, **k: [])
    scene = write_eval_scene("tiny", tmp_path / "scenes" / "tiny")
    calls = []

    def run_point(scene_dir, store, cfg):
        calls.append(cfg.select.grid.resolution)
        build_store(store, {scene_dir.name: scene_dir}, cfg.model_dump(mode="json"))

    out = tmp_path / "eval"
    cfg = EvaluateConfig(preset="fast", overrides=TINY, knobs={"grid_r": [32]}, warmup=False)
    res = run_sweep([scene], cfg, out, run_point, log=lambda m: None)
    assert len(calls) == 2 and len(res.computed) == 2 and not res.cached
    for name in ("results.parquet", "results.csv", "pareto.png", "pareto.json"):
        assert (out / name).is_file(), name
    t = pq.read_table(out / "results.parquet")
    assert t.num_rows == 2 and sorted(t.column("label").to_pylist()) == ["base", "grid_r=32"]
    for col in ("seconds", "cpu_total", "peak_rss_mb", "fv_psnr", "fv_true_share",
                "heldout_psnr", "n_candidates", "n_feasible", "n_selected", "n_free_views",
                "wall_reconstruct", "cpu_reconstruct"):
        assert col in t.column_names, col
    assert pcsv.read_csv(out / "results.csv").num_rows == 2
    row = {k: v[0] for k, v in t.to_pydict().items()}
    assert row["status"] == "ok" and row["seconds"] > 0 and row["peak_rss_mb"] > 0
    assert row["heldout_psnr"] > 5  # recon_split=ood: held-out views exist
    assert row["n_free_views"] == 0 or 0 <= row["fv_true_share"] <= 1
    png = (out / "pareto.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert w > 400 and h > 300
    meta = json.loads((out / "pareto.json").read_text())
    assert meta["xlabel"].startswith("seconds per scene")
    assert "PSNR" in meta["ylabel"] and meta["xscale"] == "log"

    # one more point: only that one runs
    calls.clear()
    cfg2 = cfg.model_copy(update={"knobs": {"grid_r": [32, 40]}})
    res2 = run_sweep([scene], cfg2, out, run_point, log=lambda m: None)
    assert calls == [40] and len(res2.computed) == 1 and len(res2.cached) == 2
    assert pq.read_table(out / "results.parquet").num_rows == 3

    # seeds: the preset's seed (0) is the point already computed; seed 1 is one new run
    calls.clear()
    res3 = run_sweep([scene], cfg.model_copy(update={"knobs": {}, "seeds": [0, 1]}), out,
                     run_point, log=lambda m: None)
    assert len(calls) == 1 and len(res3.computed) == 1 and len(res3.cached) == 1
    assert sorted(r["seed"] for r in res3.rows) == [0, 1]
    meta = json.loads((out / "pareto.json").read_text())
    (pt,) = meta["points"]
    assert pt["n_seeds"] == 2 and pt["accuracy_std"] >= 0
    accs = [r["accuracy"] for r in res3.rows]
    assert abs(pt["accuracy"] - sum(accs) / 2) < 1e-9


def test_pareto_front():
    pts = [{"label": "a", "seconds": 1.0, "accuracy": 20.0},
           {"label": "b", "seconds": 2.0, "accuracy": 19.0},
           {"label": "c", "seconds": 3.0, "accuracy": 22.0},
           {"label": "d", "seconds": 0.5, "accuracy": float("nan")}]
    assert [p["label"] for p in pareto_front(pts)] == ["a", "c"]


def test_evaluate_command_builds_config(monkeypatch):
    got = {}
    import flows.evaluate_engine as F

    def fake(**kw):
        got.update(kw)
        return {"n_points": 0, "computed": [], "cached": [], "files": {}, "skipped": []}

    monkeypatch.setattr(F, "evaluate_engine", fake)
    rc = cli.main(["evaluate", "proc:tiny", "--out", "X", "--knob", "grid_r=32,adaptive",
                   "--knob", "visibility=occlusion", "--presets", "fast", "cpu",
                   "--preset-set", "cpu:recon.max_seconds=60", "--sizing", "gaussians",
                   "--set", "recon.max_iterations=90", "--eval-long-side", "256",
                   "--downstream", "refine", "--refine-steps", "40", "--refine-seeds", "0", "1",
                   "--refine-set", "recon.max_long_side=64"])
    assert rc == 0
    c = got["config"]
    assert c.eval_long_side == 256 and c.downstream == ["refine"] and c.refine_steps == 40
    assert c.refine_seeds == [0, 1] and c.refine_overrides == {"recon": {"max_long_side": 64}}
    assert got["scenes"] == ["proc:tiny"] and got["out"] == "X"
    assert c.knobs == {"grid_r": [32, "adaptive"], "visibility": ["occlusion"]}
    assert c.presets == ["fast", "cpu"] and c.sizing == ["gaussians"]
    assert c.preset_overrides == {"cpu": {"recon": {"max_seconds": 60}}}
    assert c.overrides == {"recon": {"max_iterations": 90}}


def test_render_options_dark_specular_and_defaults_unchanged():
    import numpy as np

    from freescale_core.scene.sample import SampleWorld, capture_path, sample_layout

    spec = sample_layout(0)
    assert not {"exposure", "specular", "shininess"} & set(spec.model_dump(mode="json")["render"])
    cams = capture_path(2, 48, 36, 0)

    def img(**render):
        s = spec.model_copy(update={"render": spec.render.model_copy(update=render)})
        return SampleWorld(s).render(cams.world_from_cam[0], cams.fx[0], cams.fy[0],
                                     cams.cx[0], cams.cy[0], 48, 36)[0].astype(float)

    base, dark, shiny = img(), img(exposure=0.12), img(specular=0.9, shininess=12.0)
    assert abs(dark.mean() / base.mean() - 0.12) < 0.02
    assert (shiny >= base).all() and shiny.mean() > base.mean()


def test_noisy_pose_scene_keeps_truth_in_scene_json(tmp_path):
    import numpy as np

    from freescale_core.scene.sample import SampleWorld
    from freescale_core.scene.io import load_scene

    p = write_eval_scene("noisy_rot3", tmp_path / "n")
    truth = SampleWorld.load(p).cameras.world_from_cam
    got = load_scene(p).cameras.world_from_cam
    cos = (np.einsum("nij,nij->n", truth[:, :3, :3], got[:, :3, :3]) - 1) / 2
    deg = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert 0.3 < deg.mean() < 10 and np.allclose(truth[:, :3, 3], got[:, :3, 3], atol=1e-6)


def test_turntable_bg_scene_and_masks_knob(tmp_path):
    """The changing-background turntable family: a COLMAP scene with a mask per image and no
    ``scene.json`` oracle (so a point scores held-out PSNR and counts only); the ``masks``
    knob toggles ``ingest.masks``; writing again keeps the folder (cache keys stay valid)."""
    from freescale_core.eval.knobs import apply_knob
    from freescale_core.eval.scenes import FAILURE_SCENES
    from schemas.pipeline import PipelineConfig

    assert "turntable_bg" in FAILURE_SCENES
    p = write_eval_scene("turntable_bg", tmp_path / "t")
    assert (p / "turntable.json").is_file() and not (p / "scene.json").exists()
    assert len(list((p / "images").iterdir())) == len(list((p / "masks").iterdir())) == 24
    mtime = (p / "turntable.json").stat().st_mtime_ns
    assert write_eval_scene("turntable_bg", p) == p
    assert (p / "turntable.json").stat().st_mtime_ns == mtime
    base = PipelineConfig.from_preset("fast")
    over = apply_knob(base, "masks", "ignore")
    assert over == {"ingest": {"masks": "ignore"}}
    assert base.model_copy(update={"ingest": base.ingest.model_copy(
        update=over["ingest"])}).ingest.masks == "ignore" and base.ingest.masks == "auto"


# --------------------------------------------------------------------------- eval resolution
import pytest  # noqa: E402


@pytest.fixture(scope="module")
def res_sweep(tmp_path_factory):
    """Two points on the tiny scene (48x36, 12 views: 8 train, 4 held out) that differ only in
    training resolution (48 px, the capture, and 24 px), scored at eval long side 40."""
    import freescale_core.store.figures as figures

    tmp = tmp_path_factory.mktemp("res_sweep")
    scene = write_eval_scene("tiny", tmp / "scenes" / "tiny")
    calls = []

    def run_point(scene_dir, store, cfg):
        calls.append(cfg.recon.max_long_side)
        build_store(store, {scene_dir.name: scene_dir}, cfg.model_dump(mode="json"))

    # every sparse point (the held-out views' too): 40 steps at 48 px from only the points the
    # 8 training views made end below the mean training photo on the 4 held-out views (18.75 vs
    # 18.93 dB), and the test below checks that the scored model beats it
    tiny = {**TINY, "recon": {**TINY["recon"], "init_points": "all"}}
    cfg = EvaluateConfig(preset="fast", overrides=tiny, knobs={"resolution": [24]},
                         warmup=False, eval_long_side=40)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(figures, "save_figures", lambda *a, **k: [])
        res = run_sweep([scene], cfg, tmp / "eval", run_point, log=lambda m: None)
    return {"scene": scene, "out": tmp / "eval", "cfg": cfg, "res": res, "calls": calls,
            "run_point": run_point}


def test_heldout_scored_at_one_eval_resolution(res_sweep):
    import math
    import pickle

    from freescale_core.eval.heldout import heldout_at_eval_resolution
    from freescale_core.recon.trainer import evaluate
    from freescale_core.scene.ply import read_ply
    from schemas.pipeline import PipelineConfig

    rows = {r["label"]: r for r in res_sweep["res"].rows}
    assert sorted(rows) == ["base", "resolution=24"] and res_sweep["calls"] == [48, 24]
    base, half = rows["base"], rows["resolution=24"]
    assert base["train_long_side"] == 48 and half["train_long_side"] == 24
    for r in (base, half):  # the same eval size, whatever the training resolution
        assert r["status"] == "ok" and r["eval_long_side"] == 40
        assert (r["eval_width"], r["eval_height"]) == (40, 30)
        assert r["heldout_eval_views"] == 4 and math.isfinite(r["heldout_psnr"])
    # the sweep's number is a direct call of the trainer's evaluate at that size on the
    # point's stored Gaussians, and differs from the pipeline's (training-resolution) one
    for r in (base, half):
        work = res_sweep["out"] / "points" / r["key"] / "store" / "scenes" / "tiny" / "_work"
        scene = pickle.loads((work / "scene.pkl").read_bytes())
        g = read_ply(work / "gaussians.ply")
        cfg = PipelineConfig.model_validate_json(
            (res_sweep["out"] / "points" / r["key"] / "config.json").read_text())
        test = scene.split("ood")[1]
        ev = evaluate(g, scene, test, long_side=40, background=cfg.recon.background,
                      backend=cfg.recon.raster_backend)
        assert ev["resolution"][0] == [40, 30]
        assert r["heldout_psnr"] == pytest.approx(ev["psnr_mean"], abs=1e-9)
        # trivial baselines, by the obvious loop: nearest training photo copied, mean photo
        import cv2
        import numpy as np

        train = scene.split("ood")[0]
        c = scene.cameras.world_from_cam[:, :3, 3]
        near, mean = [], []
        for i in test:
            tgt = cv2.resize(scene.load_image(int(i)), (40, 30), interpolation=cv2.INTER_AREA)
            tgt = tgt / 255.0
            k = min(train, key=lambda t: (np.linalg.norm(c[t] - c[i]), t))
            ph = [cv2.resize(scene.load_image(int(t)), (40, 30),
                             interpolation=cv2.INTER_AREA) / 255.0 for t in train]
            near.append(-10 * np.log10(np.mean((ph[list(train).index(k)] - tgt) ** 2)))
            mean.append(-10 * np.log10(np.mean((np.mean(ph, axis=0) - tgt) ** 2)))
        assert r["heldout_nearest_psnr"] == pytest.approx(np.mean(near), abs=1e-9)
        assert r["heldout_mean_psnr"] == pytest.approx(np.mean(mean), abs=1e-9)
        assert r["heldout_psnr"] > r["heldout_mean_psnr"]
        assert r["heldout_ssim"] == pytest.approx(ev["ssim_mean"], abs=1e-9)
        again = heldout_at_eval_resolution(work.parent.parent.parent, "tiny", cfg, 40)
        assert again["heldout_psnr"] == pytest.approx(ev["psnr_mean"], abs=1e-9)
    # a reconstruction that learned its background colour (saved in its PLY) is scored on it
    import shutil

    from freescale_core.scene.ply import write_ply

    r = base
    src = res_sweep["out"] / "points" / r["key"] / "store"
    cp = res_sweep["out"].parent / "learned_bg_store"
    shutil.copytree(src, cp, dirs_exist_ok=True)
    ply = cp / "scenes" / "tiny" / "_work" / "gaussians.ply"
    g = read_ply(ply)
    ply.unlink()  # a copy, but never write through a link into the published version
    write_ply(ply, g, background=(0.5, 0.25, 0.75))
    cfg = PipelineConfig.model_validate_json(
        (res_sweep["out"] / "points" / r["key"] / "config.json").read_text())
    work = cp / "scenes" / "tiny" / "_work"
    scene = pickle.loads((work / "scene.pkl").read_bytes())
    ev = evaluate(read_ply(work / "gaussians.ply"), scene, scene.split("ood")[1], long_side=40,
                  background=(0.5, 0.25, 0.75), backend=cfg.recon.raster_backend)
    got = heldout_at_eval_resolution(cp, "tiny", cfg, 40)["heldout_psnr"]
    assert got == pytest.approx(ev["psnr_mean"], abs=1e-9)
    assert got != pytest.approx(r["heldout_psnr"], abs=1e-6)
    assert half["heldout_psnr_train_res"] != pytest.approx(half["heldout_psnr"], abs=1e-6)
    t = pq.read_table(res_sweep["out"] / "results.parquet")
    for col in ("eval_long_side", "eval_width", "eval_height", "heldout_psnr_train_res"):
        assert col in t.column_names, col


def test_refine_gain_added_to_computed_points_and_cached(res_sweep, monkeypatch):
    """--downstream refine on points already computed runs only the refinement (no pipeline
    run), records gain = arm - baseline, and a third run recomputes nothing."""
    import math

    import freescale_core.downstream.refine as R
    from freescale_core.eval.downstream import refine_config
    from freescale_core.eval.tables import downstream_table

    refined = []
    real = R.refine_scene

    def spy(fvs, cfg, *a, **k):
        refined.append(fvs.scene_id)
        return real(fvs, cfg, *a, **k)

    monkeypatch.setattr(R, "refine_scene", spy)
    cfg = res_sweep["cfg"].model_copy(update={
        "downstream": ["refine"], "refine_steps": 12,
        "refine_overrides": {"recon": {"max_long_side": 32}, "oracle_views": 2}})
    rc = refine_config(cfg)
    assert rc.arm_names()[0] == "baseline" and rc.recon.max_iterations == 12
    assert rc.recon.min_iterations == 12 and rc.recon.max_long_side == 32
    calls = res_sweep["calls"]
    calls.clear()
    res = run_sweep([res_sweep["scene"]], cfg, res_sweep["out"], res_sweep["run_point"],
                    log=lambda m: None)
    assert calls == [] and len(res.cached) == 2  # the pipeline did not run again
    rows = res.rows
    with_fv = [r for r in rows if r["n_free_views"] > 0]
    assert with_fv, "the tiny points should have free views"
    assert len(refined) == len(with_fv)
    for r in with_fv:
        assert math.isfinite(r["refine_base_psnr"]) and math.isfinite(r["refine_fv_psnr"])
        assert r["refine_gain_db"] == pytest.approx(r["refine_fv_psnr"] - r["refine_base_psnr"])
        assert r["refine_n_added"] > 0 and r["refine_cpu_seconds"] > 0
        assert r["refine_long_side"] == 32 and r["refine_steps"] == 12
    for r in rows:
        if r["n_free_views"] == 0:
            assert math.isnan(r["refine_gain_db"]) and "no free views" in r["refine_note"]
    t = pq.read_table(res_sweep["out"] / "results.parquet")
    for col in ("refine_gain_db", "refine_base_psnr", "refine_fv_psnr", "refine_cpu_seconds"):
        assert col in t.column_names, col
    assert "gain (dB)" in downstream_table(rows)
    # once more: nothing recomputed, same numbers
    refined.clear()
    res2 = run_sweep([res_sweep["scene"]], cfg, res_sweep["out"], res_sweep["run_point"],
                     log=lambda m: None)
    assert refined == [] and calls == []
    assert [r["refine_gain_db"] for r in res2.rows if r["n_free_views"] > 0] == \
        [r["refine_gain_db"] for r in with_fv]


def test_real_knobs_recon_skips_selection_knobs_on_real_scenes(tmp_path):
    """``real_knobs="recon"``: a real scene (no oracle) gets only the knobs that change the
    reconstruction; a procedural scene keeps every knob."""
    from freescale_core.eval.sweep import plan_points
    from schemas.evaluate import EvaluateConfig

    proc, real = tmp_path / "proc", tmp_path / "real"
    proc.mkdir()
    real.mkdir()
    (proc / "scene.json").write_text("{}")
    knobs = {"grid_r": [32, 64], "candidates": [500], "gaussians": [1000], "steps": [100]}
    cfg = EvaluateConfig(knobs=knobs, sizing=["grid_r", "gaussians"], real_knobs="recon")
    labels = {sc: [p.label for p in plan_points([sc], cfg)] for sc in (proc, real)}
    assert labels[proc] == ["base", "grid_r=32", "grid_r=64", "candidates=500",
                            "gaussians=1000", "steps=100", "grid_r=adaptive",
                            "gaussians=adaptive"]
    assert labels[real] == ["base", "gaussians=1000", "steps=100", "gaussians=adaptive"]
    every = [p.label for p in plan_points([real], cfg.model_copy(update={"real_knobs": "all"}))]
    assert every == labels[proc]


def test_seeds_repeat_points_and_tables_use_their_spread(tmp_path):
    """``seeds``: every planned point once per seed (distinct keys, the seed in the config);
    the aggregate is the mean over seeds then scenes; the sizing verdict does not read a
    difference smaller than the seeds' spread as a win for half or double."""
    from freescale_core.eval.sweep import aggregate, plan_points, point_key
    from freescale_core.eval.tables import sizing_table

    sc = tmp_path / "s"
    sc.mkdir()
    (sc / "scene.json").write_text("{}")
    cfg = EvaluateConfig(knobs={"grid_r": [32]}, sizing=["grid_r"])
    one = plan_points([sc], cfg)
    two = plan_points([sc], cfg.model_copy(update={"seeds": [0, 5]}))
    assert [p.label for p in two] == [p.label for p in one for _ in (0, 5)]
    assert [p.cfg.seed for p in two] == [0, 5] * len(one) and [p.seed for p in two][:2] == [0, 5]
    assert point_key(sc, two[0].cfg) == point_key(sc, one[0].cfg)  # seed 0 = the preset's
    assert len({point_key(sc, p.cfg) for p in two}) == len(two)

    def row(label, scene, seed, acc, secs=10.0):
        return {"label": label, "group": "sizing", "knob": "grid_r", "scene": scene,
                "seed": seed, "accuracy": acc, "seconds": secs, "fv_true_share": 0.5,
                "status": "ok", "grid_R": 64}

    rows = [row("grid_r=adaptive", "a", 0, 20.0), row("grid_r=adaptive", "a", 1, 22.0),
            row("grid_r=adaptive", "b", 0, 10.0), row("grid_r=adaptive", "b", 1, 10.0),
            row("grid_r=double", "a", 0, 21.0, 20.0), row("grid_r=double", "a", 1, 22.6, 20.0),
            row("grid_r=half", "a", 0, 19.0, 5.0), row("grid_r=half", "a", 1, 21.0, 5.0)]
    agg = {p["label"]: p for p in aggregate(rows)}
    a = agg["grid_r=adaptive"]
    assert a["accuracy"] == 15.5 and a["n_seeds"] == 2 and a["n_scenes"] == 2
    assert abs(a["accuracy_std"] - (2 ** 0.5 + 0.0) / 2) < 1e-9  # scene a: std 1.41, b: 0
    table = sizing_table([r for r in rows if r["scene"] == "a"])
    # double +0.80 dB and half -1.00 dB on the means, but the adaptive's seeds spread
    # 1.41 dB: double is no resolved gain, half no resolved loss (and it is faster)
    assert "(+0.80)" in table and "(-1.00)" in table and "+-1.41 (2 seeds)" in table
    assert "double buys" not in table and "half as good, faster" in table
    # the same means from one seed each: double's +0.8 dB is a gain, half's -1 dB a loss
    single = [dict(r, accuracy=m) for r, m in
              ((rows[0], 21.0), (rows[4], 21.8), (rows[6], 20.0))]
    t1 = sizing_table(single)
    assert "double buys +0.80 dB" in t1 and "half as good" not in t1


def test_warm_up_runs_once_before_computed_points_only(tmp_path, monkeypatch):
    """The untimed warm-up runs the tiny scene once, into a store that does not stay, and
    only when some point will be computed (a sweep read from the cache does not pay it)."""
    import math

    from freescale_core.eval import sweep

    stores = []

    def run_point(scene_dir, store, cfg):
        stores.append((scene_dir.name, store))
        store.mkdir(parents=True)
        (store / "x").write_text("1")

    out = tmp_path / "eval"
    dt = sweep.warm_up(out, run_point, log=lambda m: None)
    assert dt >= 0 and [n for n, _ in stores] == ["tiny"]
    assert not stores[0][1].exists() and not list(out.glob("warmup-*"))

    warmups, runs = [], []
    monkeypatch.setattr(sweep, "warm_up", lambda *a, **k: warmups.append(1) or 0.5)
    row = {"status": "ok", "fv_psnr": 20.0, "fv_true_share": 1.0, "wall_total": 1.0,
           "heldout_psnr_train_res": math.nan}
    monkeypatch.setattr(sweep, "_run_one", lambda pt, *a, **k: runs.append(pt.label) or dict(row))
    monkeypatch.setattr(sweep, "heldout_part", lambda *a, **k: {"heldout_psnr": math.nan})
    monkeypatch.setattr(sweep, "write_results", lambda *a, **k: {})
    sc = tmp_path / "s"
    sc.mkdir()
    (sc / "scene.json").write_text("{}")
    cfg = EvaluateConfig(knobs={"grid_r": [32]})
    r1 = sweep.run_sweep([sc], cfg, out, run_point, log=lambda m: None)
    assert warmups == [1] and runs == ["base", "grid_r=32"] and r1.warmup_seconds == 0.5
    r2 = sweep.run_sweep([sc], cfg, out, run_point, log=lambda m: None)  # all cached
    assert warmups == [1] and runs == ["base", "grid_r=32"] and r2.warmup_seconds == 0.0
    sweep.run_sweep([sc], cfg.model_copy(update={"warmup": False, "knobs": {"grid_r": [40]}}),
                    out, run_point, log=lambda m: None)
    assert warmups == [1] and runs[-1] == "grid_r=40"


def test_rectifier_knob_selects_the_fixer():
    """`--knob rectifier=fixer` runs the free-view stage with the engine's fixer."""
    from freescale_core.eval.knobs import apply_knob
    from schemas.pipeline import PipelineConfig

    base = PipelineConfig()
    over = apply_knob(base, "rectifier", "fixer")
    assert over == {"freeview": {"rectifier": {"backend": "fixer"}}}
    cfg = PipelineConfig.model_validate({**base.model_dump(mode="json"), **over})
    assert cfg.freeview.rectifier.backend == "fixer"
