"""Fast tests of the reconstruction parts of ``benchmarks/recon.py`` (``--eval-every``) and
``benchmarks/rasterizer.py`` (``--trainer``) on a very small sample scene."""

from __future__ import annotations

import importlib
import json
import math
from pathlib import Path

import pytest


def _load(name: str):
    """The benchmark module as ``python -m benchmarks.NAME`` runs it (no path edits)."""
    return importlib.import_module(f"benchmarks.{name}")


@pytest.fixture(scope="module")
def recon_bench():
    return _load("recon")


@pytest.fixture(scope="module")
def raster_bench():
    return _load("rasterizer")


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    from freescale_core.scene.sample import write_sample_scene

    return write_sample_scene(tmp_path_factory.mktemp("rb") / "sample", n_views=10, width=96,
                              height=72, seed=0, n_points=600)


def test_first_reaching(recon_bench):
    curve = [{"step": 10, "test_psnr": 20.0}, {"step": 20, "test_psnr": 28.5},
             {"step": 30, "test_psnr": 27.0}, {"step": 40, "test_psnr": 29.0}]
    assert recon_bench.first_reaching(curve, 28.0)["step"] == 20
    assert recon_bench.first_reaching(curve, 28.7)["step"] == 40
    assert recon_bench.first_reaching(curve, 30.0) is None
    assert recon_bench.first_reaching([], 0.0) is None


def test_eval_every_curve(recon_bench, tiny_scene):
    from schemas.pipeline import PipelineConfig

    cfg = PipelineConfig.from_preset("fast").recon.model_copy(update={"max_iterations": 40,
                                                             "max_long_side": 64})
    row = recon_bench.run(tiny_scene, cfg, "every8", 0, False, eval_every=15, target_db=-50.0)
    curve = row["test_psnr_curve"]
    assert [c["step"] for c in curve] == [15, 30, 40] and curve[-1]["final"]
    assert curve[-1]["test_psnr"] == row["recon_test_psnr"]
    mins = [c["train_minutes"] for c in curve]
    assert mins == sorted(mins) and mins[-1] == pytest.approx(row["minutes"])
    assert all(math.isfinite(c["test_psnr"]) and c["eval_seconds"] > 0 for c in curve)
    # any PSNR is above -50 dB: the target is reached at the first checkpoint
    assert row["step_to_target"] == 15 and row["minutes_to_target"] == mins[0]
    row = recon_bench.run(tiny_scene, cfg, "every8", 0, False, eval_every=15, target_db=99.0)
    assert row["minutes_to_target"] is None and row["step_to_target"] is None
    assert "test_psnr_curve" not in recon_bench.run(tiny_scene, cfg, "every8", 0, False)


def test_a_learned_background_is_scored_on_its_colour(recon_bench, tiny_scene):
    """With background_lr the held-out views are scored on the learned colour (the row says
    which), at the end and at every checkpoint."""
    from freescale_core.recon.trainer import evaluate, reconstruct
    from freescale_core.scene.io import load_scene
    from schemas.pipeline import PipelineConfig

    cfg = PipelineConfig.from_preset("fast").recon.model_copy(update={
        "max_iterations": 40, "max_long_side": 64, "background_lr": 0.02})
    row = recon_bench.run(tiny_scene, cfg, "every8", 0, False, eval_every=20)
    col = tuple(row["background"])
    assert col != (0.0, 0.0, 0.0)
    scene = load_scene(tiny_scene)
    train, test = scene.split("every8")
    g = reconstruct(scene, cfg, seed=0, train_idx=train).gaussians  # same seed: same model
    on_col = evaluate(g, scene, test, scale=row["train_scale"], background=col)["psnr_mean"]
    on_black = evaluate(g, scene, test, scale=row["train_scale"])["psnr_mean"]
    assert row["recon_test_psnr"] == pytest.approx(on_col, abs=1e-4)
    assert abs(on_col - on_black) > 1e-3


def test_trainer_config_compresses_schedule(raster_bench):
    cfg = raster_bench.trainer_config(300)
    assert cfg.max_iterations == 300 and cfg.min_iterations > 300  # no plateau stop
    assert cfg.max_long_side == 512  # the cpu preset's resolution rule is kept
    # all growth steps and SH degree 3 happen within the first half
    last_growth = cfg.densify_from + (cfg.mcmc_grow_steps - 1) * cfg.densify_every
    assert last_growth <= cfg.densify_until <= 150
    assert cfg.sh_degree * cfg.sh_increase_every < 150


def test_trainer_rows(raster_bench, tiny_scene):
    rows = list(raster_bench.trainer_rows(40, scenes=("sample", "no_such_scene"),
                                          datasets=tiny_scene.parent))
    assert len(rows) == 2
    r, skipped = rows
    assert "not found" in skipped["skipped"] and skipped["scene"] == "no_such_scene"
    assert r["scene"] == "sample" and r["steps"] == 40 and (r["width"], r["height"]) == (96, 72)
    assert r["n_gaussians"] == r["n_gaussians_budget"]  # growth finished in the first half
    assert r["sh_degree"] == 3 and r["timed_steps"] == [20, 40]
    assert r["iterations_per_second"] > 0 and r["iterations_per_second_overall"] > 0


def test_psnr_at_and_arms(recon_bench):
    curve = [{"train_cpu_minutes": 0.2, "test_psnr": 10.0},
             {"train_cpu_minutes": 0.9, "test_psnr": 12.0},
             {"train_cpu_minutes": 1.6, "test_psnr": 13.0}]
    assert recon_bench.psnr_at(curve, 1.0) == 12.0
    assert recon_bench.psnr_at(curve, 0.1) is None  # nothing evaluated by then
    assert recon_bench.psnr_at(curve, 3.0) is None  # the run did not get there
    new, new_sw = recon_bench.arm("new")
    assert new.model_dump() == recon_bench.ReconConfig.cpu().model_dump() and new_sw == {}
    cfg, sw = recon_bench.arm("new,bounds_every=7")
    assert cfg.model_dump() == new.model_copy(update={"bounds_every": 7}).model_dump()
    assert sw == {} and recon_bench.arm.plugins(cfg, sw) == {}  # today's trainer, no plug-in
    nested = recon_bench.arm_config("new,coarse_to_fine=[[250,4],[1200,2]],bounds_every=7")
    assert nested.coarse_to_fine == ((250, 4), (1200, 2)) and nested.bounds_every == 7
    assert recon_bench.parse_sets(["bounds_every=7", "densify=none"]) == {
        "bounds_every": 7, "densify": "none"}


def test_benchmark_knows_only_todays_trainer(recon_bench, capsys):
    """The frozen legacy arms and the old trainer's switches are the lab's
    (``python -m lab.recon_compare``): here they are one-line errors."""
    with pytest.raises(SystemExit, match="'old'"):
        recon_bench.arm("old")
    with pytest.raises(SystemExit, match="'pre55'"):
        recon_bench.arm_config("pre55,bounds_every=7")
    with pytest.raises(Exception, match="ssim_impl"):
        recon_bench.arm("new,ssim_impl=torch")
    # a --set that is no ReconConfig field is an error, not dropped by model_copy
    with pytest.raises(SystemExit):
        recon_bench.main(["sample", "--set", "ssim_impl=torch", "--max-iterations", "1"])
    assert "ssim_impl: not a ReconConfig field" in capsys.readouterr().err


def test_arm_dirname_is_one_safe_folder_per_arm(recon_bench):
    names = ["old", "new", "new,bounds_every=7", "new,coarse_to_fine=[[250,4],[1200,2]]",
             "new,coarse_to_fine=[[250,4],[600,2]]", 'new,ssim_impl="torch"', "new,x=a/b"]
    dirs = [recon_bench.arm_dirname(n) for n in names]
    assert dirs[2] == "new+bounds_every=7" and dirs[3] == "new+coarse_to_fine=250-4-1200-2"
    assert len(set(dirs)) == len(dirs)  # distinct arms, distinct folders
    assert all("/" not in d and "," not in d and d for d in dirs)


def test_compare_saves_each_arms_reconstruction(recon_bench, tiny_scene, tmp_path, capsys):
    from freescale_core.scene.ply import read_background, read_ply

    arms = ["new-fast", "new-fast,cap_gaussians=100"]
    assert recon_bench.main([str(tiny_scene), "--compare", *arms, "--max-iterations", "12",
                             "--max-long-side", "48", "--threads", "1", "--eval-every", "6",
                             "--save-dir", str(tmp_path)]) == 0
    for arm in arms:
        d = tmp_path / recon_bench.arm_dirname(arm) / "ood" / tiny_scene.name
        assert (d / "recon_stats.json").is_file(), arm
        assert len(read_ply(d / "gaussians.ply")) > 0
        # the model carries its background colour (the learned one when background_lr is set)
        stats = json.loads((d / "recon_stats.json").read_text())
        assert read_background(d / "gaussians.ply", default=(9, 9, 9)) == tuple(
            stats["background"])
    n = [len(read_ply(tmp_path / recon_bench.arm_dirname(a) / "ood" / tiny_scene.name
                      / "gaussians.ply")) for a in arms]
    assert n[1] == 100 < n[0]  # each folder holds its own arm's model


def test_model_rows_compare_exact_tiles_on_a_saved_model(recon_bench, raster_bench, tiny_scene,
                                                         tmp_path, capsys):
    """``rasterizer.py --model``: a reconstruction saved by ``recon.py --save-dir`` is rendered
    on its training views with the exact tile test off and on (same output, checked in the
    run); the exact test never keeps more pairs."""
    import json

    assert recon_bench.main([str(tiny_scene), "--compare", "new-fast", "--max-iterations", "30",
                             "--max-long-side", "64", "--threads", "1",
                             "--save-dir", str(tmp_path)]) == 0
    ply = tmp_path / "new-fast" / "ood" / tiny_scene.name / "gaussians.ply"
    capsys.readouterr()
    assert raster_bench.main(["--model", str(ply), "--scene", str(tiny_scene), "--split", "ood",
                              "--views", "2", "--repeats", "1", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["exact_tiles"] for r in rows] == [False, True]
    assert rows[1]["pairs"] <= rows[0]["pairs"] and rows[0]["pairs"] > 0
    assert rows[1]["views"] == 2 and rows[1]["total_ratio"] > 0
    with pytest.raises(SystemExit, match="recon_stats.json"):
        raster_bench.main(["--model", str(tmp_path / "x.ply"), "--scene", str(tiny_scene)])


def test_opensplat_project_reads_back_with_the_same_cameras(recon_bench, tiny_scene, tmp_path):
    """The nerfstudio project handed to OpenSplat (training split, training resolution) holds
    the training cameras: read back with the project's own nerfstudio reader, intrinsics and
    poses equal the scaled originals, and the images have the cameras' sizes."""
    import numpy as np

    from freescale_core.scene.io import load_scene

    scene = recon_bench.load(tiny_scene)
    train, _ = scene.split("ood")
    scene.cameras.cx[:] = scene.cameras.width / 2.0  # centred: images written as they are
    scene.cameras.cy[:] = scene.cameras.height / 2.0
    recon_bench.write_opensplat_project(scene, train, 0.5, tmp_path / "proj")
    back = load_scene(tmp_path / "proj")
    want = scene.cameras.subset(np.asarray(train)).scaled(0.5)
    assert len(back) == len(train)
    np.testing.assert_allclose(back.cameras.world_from_cam, want.world_from_cam, atol=1e-6)
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        np.testing.assert_allclose(getattr(back.cameras, k), getattr(want, k), atol=1e-6)
    assert back.load_image(0).shape[:2] == (int(want.height[0]), int(want.width[0]))
    # the points our arms start from: the ones the training views alone made
    keep = scene.points_seen_by(train)
    assert 0 < keep.sum() < len(keep) and len(back.points_xyz) == keep.sum()
    np.testing.assert_allclose(back.points_xyz, scene.points_xyz[keep], atol=1e-5)


def test_opensplat_project_centres_the_principal_point(recon_bench, tiny_scene, tmp_path):
    """OpenSplat's CPU projection puts the principal point at the image centre, so the project
    holds each image cropped around its principal point: cx = w/2, cy = h/2, focal lengths and
    poses unchanged, and the pixels are the original ones moved by the crop (whole-pixel
    offsets here, so exactly)."""
    import numpy as np

    from freescale_core.recon.trainer import _resize
    from freescale_core.scene.io import load_scene

    scene = recon_bench.load(tiny_scene)
    train, _ = scene.split("ood")
    w, h = int(scene.cameras.width[0]), int(scene.cameras.height[0])
    scene.cameras.cx[:] = w / 2.0 + 3.0
    scene.cameras.cy[:] = h / 2.0 - 2.0
    recon_bench.write_opensplat_project(scene, train, 1.0, tmp_path / "proj")
    back = load_scene(tmp_path / "proj")
    want = scene.cameras.subset(np.asarray(train))
    np.testing.assert_array_equal(back.cameras.width, w - 6)
    np.testing.assert_array_equal(back.cameras.height, h - 4)
    np.testing.assert_allclose(back.cameras.cx, (w - 6) / 2.0)
    np.testing.assert_allclose(back.cameras.cy, (h - 4) / 2.0)
    for k in ("fx", "fy", "world_from_cam"):
        np.testing.assert_allclose(getattr(back.cameras, k), getattr(want, k), atol=1e-6)
    orig = np.asarray(_resize(scene.load_image(int(train[0])), w, h))
    np.testing.assert_allclose(back.load_image(0).astype(int), orig[:h - 4, 6:].astype(int),
                               atol=1)
    img = np.zeros((h, w, 3), np.uint8)
    same, (cx, cy) = recon_bench.centre_principal_point(img, w / 2.0, h / 2.0)
    assert same is img and (cx, cy) == (w / 2.0, h / 2.0)


def test_opensplat_status_says_why_it_skips(recon_bench, tmp_path):
    assert recon_bench.opensplat_status(None).startswith("skipped: no --opensplat")
    assert "not found" in recon_bench.opensplat_status(str(tmp_path / "nope"))


def test_step_breakdown_covers_every_section(recon_bench, tiny_scene):
    """``--breakdown``: every section of the step is timed, and the sections add up to the
    step (the per-step total is positive and each share non-negative)."""
    from schemas.recon import ReconConfig

    cfg = ReconConfig.fast().model_copy(update={"max_iterations": 40, "min_iterations": 40})
    r = recon_bench.step_breakdown(tiny_scene, cfg, "ood", 0, 10, 30)
    ms = r["ms_per_step"]
    assert {"view", "raster_forward", "loss", "backward", "optimizer", "strategy",
            "other"} <= set(ms)
    assert all(w >= 0 and c >= 0 for w, c in ms.values())
    assert ms["raster_forward"][0] > 0 and ms["backward"][0] > 0
    assert r["n_gaussians"] > 0 and (r["from"], r["to"]) == (10, 30)


def test_stop_after_ends_a_run_at_its_first_evaluation_past_it(recon_bench, tiny_scene):
    from schemas.pipeline import PipelineConfig

    cfg = PipelineConfig.from_preset("fast").recon.model_copy(update={"max_iterations": 40,
                                                             "max_long_side": 64})
    row = recon_bench.run(tiny_scene, cfg, "every8", 0, False, eval_every=15, target_db=-50.0,
                          stop_after=0.0)
    assert row["iterations"] == 15 and row["stop_after"] == 0.0
    assert [c["step"] for c in row["test_psnr_curve"]] == [15]
    assert "stopped by the caller" in row["reasons"]["iterations"]
    full = recon_bench.run(tiny_scene, cfg, "every8", 0, False, eval_every=15, target_db=-50.0)
    assert full["iterations"] == 40 and full["stop_after"] is None


def test_opensplat_seed_reaches_the_binary(recon_bench, tiny_scene, tmp_path, monkeypatch):
    """``--opensplat-seed`` is passed as OPENSPLAT_SEED; without it any inherited value is
    removed (the binary uses its own 42). A stand-in binary that fails prints what it got."""
    fake = tmp_path / "opensplat"
    fake.write_text('#!/bin/sh\necho "seed=${OPENSPLAT_SEED:-unset}"\nexit 3\n')
    fake.chmod(0o755)
    monkeypatch.setenv("OPENSPLAT_SEED", "99")
    with pytest.raises(RuntimeError, match="seed=7"):
        recon_bench.run_opensplat(str(fake), tiny_scene, "every8", 0.5, 0.1, 10, tmp_path,
                                  seed=7)
    with pytest.raises(RuntimeError, match="seed=unset"):
        recon_bench.run_opensplat(str(fake), tiny_scene, "every8", 0.5, 0.1, 10, tmp_path)
