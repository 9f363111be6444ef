"""Smoke test of ``benchmarks/fidelity.py``: its core function on a very small sample scene
(fast preset, a few dozen reconstruction steps) returns rows of the documented schema."""

from __future__ import annotations

import importlib
import json
import math

import numpy as np
import pytest


@pytest.fixture(scope="module")
def fidelity():
    return importlib.import_module("benchmarks.fidelity")


@pytest.fixture(scope="module")
def sample_result(fidelity, tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path_factory.mktemp("fid") / "sample", n_views=10, width=96,
                           height=72, seed=0, n_points=600)
    cfg = fidelity.build_config("fast", iterations=30, long_side=64)
    return fidelity.run_sample(d, cfg, seed=0)


FIDELITY_KEYS = {"kind", "scene", "split", "filter", "reference", "rectifier", "n_views",
                 "psnr_before", "psnr_after", "ssim_before", "ssim_after", "psnr_fg_before",
                 "psnr_fg_after", "n_improved", "n_worse", "rect_weight", "reference_rules",
                 "ref_cover", "best_cover"}


def test_fidelity_rows_schema(fidelity, sample_result):
    rows = sample_result["rows"]
    assert [(r["reference"], r["rectifier"]) for r in rows] == list(fidelity.VARIANTS)
    n = {r["n_views"] for r in rows}
    assert len(n) == 1  # stages 7-9 do not depend on the variant
    for r in rows:
        assert FIDELITY_KEYS <= set(r)
        assert r["kind"] == "fidelity" and r["scene"] == "sample"
        if r["n_views"]:
            assert math.isfinite(r["psnr_before"]) and math.isfinite(r["psnr_after"])
            assert -1.0 <= r["ssim_before"] <= 1.0
        if r["rectifier"] == "none":  # identity: after == before, no reference chosen
            assert r["psnr_after"] == r["psnr_before"] or r["n_views"] == 0
            assert r["reference_rules"] == ""
    # both reference rules render the same views: the render-side numbers agree
    by = {(r["reference"], r["rectifier"]): r for r in rows}
    assert by[("graph", "none")]["psnr_before"] == by[("pose", "reproject")]["psnr_before"] \
        or by[("graph", "none")]["n_views"] == 0
    json.dumps([fidelity._clean_dict(r) for r in rows], allow_nan=False)
    # true coverage of the chosen reference: only where a reference was chosen, never above
    # the best training view's
    for r in rows:
        if r["rectifier"] == "none" or not r["n_views"]:
            assert math.isnan(r["ref_cover"])
        else:
            assert 0.0 <= r["ref_cover"] <= r["best_cover"] + 1e-12 <= 1.0 + 1e-12
    for v in sample_result["views"]:
        if v["reference_view"] >= 0:
            assert 0.0 <= v["ref_cover"] <= v["best_cover"] <= 1.0
    assert {c["reference"] for c in sample_result["compare"]} <= set(fidelity.GRAPH_RULES)


def test_true_coverage_counts_only_truly_seen_pixels(fidelity):
    """Same camera: everything; a camera looking away: nothing; an occluder in front of half
    the reference's view: about half; a nearby camera: most."""
    from tests.freeviews.test_rectify import H, K, W, PlaneWorld, cam

    world = PlaneWorld()
    v_pose = cam([0.0, 0.0, 0.0], target=(0.0, 0.0, 4.0))
    d_v = world.render(v_pose, *K, W, H)[1]
    vc = (v_pose, *K)
    assert fidelity.true_coverage(vc, d_v, vc, d_v) == 1.0
    away = cam([0.0, 0.0, 0.0], target=(0.0, 0.0, -4.0))
    assert fidelity.true_coverage(vc, d_v, (away, *K), world.render(away, *K, W, H)[1]) == 0.0
    occluded = d_v.copy()
    occluded[:, : W // 2] *= 0.5  # something halfway in front of the left half
    c = fidelity.true_coverage(vc, d_v, vc, occluded)
    assert 0.45 < c < 0.55
    near = cam([0.3, 0.1, 0.2], target=(0.2, 0.0, 4.0))
    c = fidelity.true_coverage(vc, d_v, (near, *K), world.render(near, *K, W, H)[1])
    assert 0.6 < c < 1.0
    assert math.isnan(fidelity.true_coverage(vc, np.zeros_like(d_v), vc, d_v))


def test_spearman_and_filter_rows(fidelity, sample_result):
    spear = sample_result["spearman"]
    assert [s["score"] for s in spear] == list(fidelity.SCORES)
    for s in spear:
        assert {"scene", "score", "spearman", "n"} <= set(s)
        n_cand = sample_result["filter"][0]["n_candidates"]
        # photo_psnr is NaN for a render no training photo supports
        assert 0 < s["n"] <= n_cand
        if s["score"] in ("brisque", "black_ratio", "depth_validity", "pred_psnr"):
            assert s["n"] == n_cand
        assert math.isnan(s["spearman"]) or -1.0 <= s["spearman"] <= 1.0
    f = sample_result["filter"][0]
    assert f["n_passed"] + f["n_rejected"] == f["n_candidates"]
    json.dumps([fidelity._clean_dict(r) for r in spear + sample_result["filter"]],
               allow_nan=False)


def test_image_metrics_reference(fidelity):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    p, s, pm = fidelity.image_metrics(a, a, np.ones((24, 32), bool))
    assert p == math.inf and pm == math.inf and s == pytest.approx(1.0)
    b = np.clip(a.astype(int) + 10, 0, 255).astype(np.uint8)
    mse = np.mean((a.astype(float) - b) ** 2)
    p, _, pm = fidelity.image_metrics(b, a)
    assert p == pytest.approx(10 * np.log10(255.0**2 / mse))
    assert math.isnan(pm)
    mask = np.zeros((24, 32), bool)
    mask[:, :16] = True
    _, _, pm = fidelity.image_metrics(b, a, mask)
    mse_m = np.mean((a[:, :16].astype(float) - b[:, :16]) ** 2)
    assert pm == pytest.approx(10 * np.log10(255.0**2 / mse_m))


def test_cached_render_counts(fidelity):
    calls = []

    def fn(pose, fx, fy, cx, cy, w, h):
        calls.append(1)
        z = np.zeros((h, w), np.float32)
        return np.zeros((h, w, 3), np.float32), z, z

    c = fidelity.CachedRender(fn)
    pose = np.eye(4)
    c(pose, 10, 10, 4, 3, 8, 6)
    c(pose.copy(), 10.0, 10.0, 4.0, 3.0, 8, 6)
    pose2 = pose.copy()
    pose2[0, 3] = 1e-9
    c(pose2, 10, 10, 4, 3, 8, 6)
    assert (c.misses, c.hits, len(calls)) == (2, 1, 2)
