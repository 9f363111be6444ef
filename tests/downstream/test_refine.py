"""refine-3dgs: the pseudo-view schedule (by id, once per step, own weights), the weight
rules, shared seed and budget of the arms, published metrics and resume after a crash."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from freescale_core.downstream import refine as R
from freescale_core.recon.views import View, ViewCamera
from schemas.recon import ReconConfig
from schemas.refine import RefineConfig
from tests.conftest import TINY_OVERRIDES, build_store


# --------------------------------------------------------------------------- pure parts
class _Captured:
    """Stand-in for CapturedViews: n views, index j, weight 1."""

    def __init__(self, n):
        self.n = n

    def __len__(self):
        return self.n

    def view(self, j):
        return View(torch.zeros(2, 2, 3), _CAM, 1.0, index=j, kind="captured")


_CAM = ViewCamera(np.eye(4), 1.0, 1.0, 1.0, 1.0, 2, 2)


def _weight_of(vid: int) -> float:
    return 0.1 + vid / 100.0


def _make_view(vid: int) -> View:
    return View(torch.zeros(2, 2, 3), _CAM, weight=_weight_of(vid), lambda_ssim=0.5)


def test_schedule_adds_by_id_once_per_point_with_own_weights():
    ranking = [5, 3, 9, 1, 7]
    pool = R.PseudoViewPool(_Captured(4), ranking, schedule=[10, 20, 30], per_step=2,
                            make_view=_make_view)
    rng = np.random.default_rng(0)
    seen = []
    for step in range(1, 61):
        for _ in range(2 if step in (10, 20) else 1):  # a schedule point seen twice fires once
            seen.append(pool.next(step, rng))
    assert [(a.step, a.view_id) for a in pool.added] == [(10, 5), (10, 3), (20, 9), (20, 1),
                                                         (30, 7)]
    assert [a.weight for a in pool.added] == [_weight_of(i) for i in (5, 3, 9, 1, 7)]
    assert sorted(pool.used) == sorted(ranking) and len(pool.pseudo) == 5
    pseudo = [v for v in seen if v.kind == "pseudo"]
    assert pseudo, "pseudo views were never drawn"
    for v in pseudo:  # every drawn pseudo view carries its own id's weight
        assert v.weight == _weight_of(v.index) and v.lambda_ssim == 0.5
    # nothing joins before the first schedule point
    assert all(v.kind == "captured" for v in seen[:10])


def test_schedule_respects_max_views_and_exhaustion():
    pool = R.PseudoViewPool(_Captured(3), [4, 2, 8], schedule=[1, 2, 3, 4], per_step=2,
                            make_view=_make_view, max_views=3)
    rng = np.random.default_rng(1)
    for step in range(1, 10):
        pool.next(step, rng)
    assert [(a.step, a.view_id) for a in pool.added] == [(1, 4), (1, 2), (2, 8)]


@settings(max_examples=40, deadline=None)
@given(ranking=st.lists(st.integers(0, 500), unique=True, max_size=30),
       schedule=st.lists(st.integers(1, 50), unique=True, max_size=8),
       per_step=st.integers(1, 6), max_views=st.one_of(st.none(), st.integers(0, 20)))
def test_schedule_property(ranking, schedule, per_step, max_views):
    pool = R.PseudoViewPool(_Captured(2), ranking, schedule, per_step, _make_view, max_views)
    rng = np.random.default_rng(0)
    for step in range(1, 52):
        pool.next(step, rng)
        pool.next(step, rng)
    ids = [a.view_id for a in pool.added]
    cap = len(schedule) * per_step if max_views is None else min(max_views,
                                                                 len(schedule) * per_step)
    assert ids == ranking[:min(cap, len(ranking))]  # a prefix of the ranking, each once
    for s in set(a.step for a in pool.added):
        assert s in schedule and sum(a.step == s for a in pool.added) <= per_step


def test_config_schedule_scales_to_budget_and_weight_rules():
    c = RefineConfig()
    assert c.recon.max_iterations == c.recon.min_iterations  # fixed budget for every arm
    c = RefineConfig(recon=ReconConfig.fast().model_copy(update={"max_iterations": 600}))
    assert c.interval() == 60 and c.schedule() == list(range(60, 600, 60))
    c = RefineConfig(recon=ReconConfig(max_iterations=30_000))
    assert c.schedule() == list(range(3000, 30_000, 3000))
    ref = RefineConfig(weight_rule="reference")
    assert ref.alpha(0.1) == pytest.approx(0.6) and ref.alpha(0.9) == pytest.approx(0.1)
    assert ref.alpha(0.4) == pytest.approx(0.35)
    pap = RefineConfig(weight_rule="paper")
    assert pap.alpha(0.2) == pytest.approx(0.5) and pap.alpha(0.7) == pytest.approx(0.3)
    assert pap.alpha(0.4) == pytest.approx(0.4)
    with pytest.raises(ValueError):
        RefineConfig(arms=["baseline", "baseline"])
    with pytest.raises(ValueError):
        RefineConfig(arms=["wiou", "wiou@reference"])  # the same arm twice (default rule)
    with pytest.raises(ValueError):
        RefineConfig(arms=["baseline@paper"])
    assert RefineConfig(arms=["baseline", "wiou", "random@reference"],
                        weight_rule="paper").arm_names() == [
        "baseline", "wiou@paper", "random@reference"]
    assert RefineConfig(arms=["wiou"]).arm_names() == ["wiou@reference"]  # the default rule


def test_rank_free_views_lowest_wiou_first_and_random_is_seeded():
    rs = R.RefineScene(None, np.arange(3), np.array([10, 11, 12, 13]),
                       np.array([0.5, 0.1, np.nan, 0.1]), np.zeros(4), np.zeros(0), None, [])
    assert R.rank_free_views(rs, "wiou", 0) == [11, 13, 10, 12]
    a, b = R.rank_free_views(rs, "random", 3), R.rank_free_views(rs, "random", 3)
    assert a == b and sorted(a) == [10, 11, 12, 13]


# --------------------------------------------------------------------------- on a tiny store
TINY_REFINE = {"max_iterations": 40, "min_iterations": 40, "densify_from": 10,
               "densify_until": 30, "densify_every": 10, "max_long_side": 48,
               "cap_gaussians": 800, "plateau_window": 20}


@pytest.fixture(scope="module")
def ood_store(tmp_path_factory) -> Path:
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("refine_store")
    write_sample_scene(root / "scenes" / "tiny", n_views=20, width=64, height=48, seed=1)
    return build_store(root / "store", {"tiny": root / "scenes" / "tiny"},
                       {**TINY_OVERRIDES, "recon_split": "ood"})


def _cfg(arms, seeds=(0,)):
    return RefineConfig(recon=ReconConfig.fast().model_copy(update=TINY_REFINE),
                        arms=list(arms), seeds=list(seeds), oracle_views=3,
                        weight_rule="paper")


def test_refine_scene_publishes_metrics_and_shares_seed_and_budget(ood_store):
    from freescale_core.store.reader import FreeViewSet

    fvs = FreeViewSet.open(ood_store, "tiny")
    cfg = _cfg(["baseline", "wiou", "oracle"])
    out = R.refine_scene(fvs, cfg, log=lambda s: None)
    assert sorted(out["computed"]) == ["baseline/seed0", "oracle@paper/seed0",
                                       "wiou@paper/seed0"]
    root = Path(out["root"])
    assert root.parent.parent == fvs.version_dir.parent / "refine"
    n_ho = out["n_heldout_views"]
    assert n_ho == 6  # last 30% of 20 views
    rs = R.load_refine_scene(fvs, cfg)
    wiou_order = R.rank_free_views(rs, "wiou", 0)
    for arm in ("baseline", "wiou@paper", "oracle@paper"):
        d = R.arm_dir(root, arm, 0)
        m = json.loads((d / "metrics.json").read_text())
        assert (d / "gaussians.ply").is_file() and (d / "heldout.parquet").is_file()
        assert m["seed"] == 0 and m["iterations"] == 40  # same seed, same budget
        assert len(m["heldout"]["psnr"]) == n_ho and np.isfinite(m["heldout"]["psnr_mean"])
        assert len(m["offpath"]["psnr"]) == 3  # procedural: oracle poses off the path
        if arm == "baseline":
            assert m["added"] == []
        else:  # joined at the scaled schedule, in the paper's order, each once
            sched = cfg.schedule()
            steps = [a["step"] for a in m["added"]]
            assert set(steps) <= set(sched) and steps == sorted(steps)
            ids = [a["view_id"] for a in m["added"]]
            assert ids == wiou_order[:len(ids)] and len(ids) == min(
                len(wiou_order), len(sched) * cfg.per_step)
            b = dict(zip(rs.free_ids.tolist(), rs.free_brisque.tolist()))
            for a in m["added"]:
                assert a["weight"] == pytest.approx(2 * cfg.alpha(b[a["view_id"]]))
    summ = json.loads((root / "summary.json").read_text())["summary"]
    assert {"baseline", "wiou@paper", "oracle@paper"} <= set(summ)
    assert "dpsnr" in summ["wiou@paper"] and "doffpath_psnr" in summ["oracle@paper"]


def test_killed_run_resumes_only_the_missing_arm(ood_store, monkeypatch):
    from freescale_core.store.reader import FreeViewSet

    fvs = FreeViewSet.open(ood_store, "tiny")
    cfg = _cfg(["baseline", "random"], seeds=[1])
    real = R.run_arm
    calls = []

    def crashing(rs, data, c, arm, seed, *a, **k):
        calls.append(arm)
        if arm.startswith("random"):
            raise KeyboardInterrupt("killed")
        return real(rs, data, c, arm, seed, *a, **k)

    monkeypatch.setattr(R, "run_arm", crashing)
    with pytest.raises(KeyboardInterrupt):
        R.refine_scene(fvs, cfg, log=lambda s: None)
    root = R.refine_root(fvs, cfg)
    assert R.arm_done(root, "baseline", 1) is not None
    assert R.arm_done(root, "random@paper", 1) is None
    assert not (root / "random@paper").exists() or not any(
        p.name.startswith(".staging") for p in (root / "random@paper").iterdir())
    calls.clear()
    monkeypatch.setattr(R, "run_arm", lambda *a, **k: (calls.append(a[3]), real(*a, **k))[1])
    out = R.refine_scene(fvs, cfg, log=lambda s: None)
    assert calls == ["random@paper"]
    assert out["computed"] == ["random@paper/seed1"] and out["reused"] == ["baseline/seed1"]
    calls.clear()
    out = R.refine_scene(fvs, cfg, log=lambda s: None)  # all done: nothing recomputed
    assert calls == [] and sorted(out["reused"]) == ["baseline/seed1", "random@paper/seed1"]
    # another weight rule is another arm; the finished baseline is shared, not recomputed
    out = R.refine_scene(fvs, cfg.model_copy(update={"weight_rule": "reference"}),
                         log=lambda s: None)
    assert calls == ["random@reference"] and out["reused"] == ["baseline/seed1"]


def test_store_without_heldout_views_is_refused(ood_store, tmp_path):
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from freescale_core.errors import StoreError
    from freescale_core.store.reader import FreeViewSet

    src = FreeViewSet.open(ood_store, "tiny").version_dir
    v = tmp_path / "scenes" / "tiny" / "v0001"
    shutil.copytree(src, v)
    t = pq.read_table(v / "views.parquet")
    pq.write_table(t.filter(pc.not_equal(t.column("disposition"), "heldout")),
                   v / "views.parquet")
    with pytest.raises(StoreError, match="recon_split=ood"):
        R.load_refine_scene(FreeViewSet(v, "tiny"), RefineConfig())


def test_pseudo_images_match_the_store(ood_store):
    """The raw arm re-renders exactly what a store without an image rectifier stored, and the
    oracle arm's truth scores exactly the store's gt_psnr (same pose, same size)."""
    from freescale_core.eval.metrics import psnr_u8
    from freescale_core.scene.ply import read_ply
    from freescale_core.store.reader import FreeViewSet

    fvs = FreeViewSet.open(ood_store, "tiny")
    rs = R.load_refine_scene(fvs, RefineConfig())
    assert len(rs.free_ids) and rs.oracle is not None
    g = read_ply(fvs.gaussians_ply)
    v = fvs.dataset_views()
    vid = int(rs.free_ids[0])
    r = int(np.flatnonzero(v.view_id == vid)[0])
    c = v.cameras
    cam = ViewCamera(c.world_from_cam[r], c.fx[r], c.fy[r], c.cx[r], c.cy[r], int(c.width[r]),
                     int(c.height[r]))
    stored = fvs.rgb(vid)
    assert np.array_equal(R.pseudo_image(rs, "raw", vid, cam, g), stored)
    truth = R.pseudo_image(rs, "oracle", vid, cam)
    assert psnr_u8(stored, truth) == pytest.approx(rs.free_gt_psnr[0], abs=1e-6)


# --------------------------------------------------------------------------- fixed arms
def test_outward_order_is_the_nearest_ring_first():
    rs = R.RefineScene(None, np.arange(3), np.array([10, 11, 12, 13]),
                       np.array([0.5, 0.1, np.nan, 0.5]), np.zeros(4), np.zeros(0), None, [])
    assert R.rank_free_views(rs, "outward", 0) == [10, 13, 11, 12]


def test_time_matched_steps_from_cpu_seconds():
    cfg = _cfg(["baseline", "baseline+time", "fixed+conf"])
    arms = {"baseline": {"0": {"cpu_seconds": 10.0, "train_seconds": 99.0}},
            "fixed+conf@paper": {"0": {"cpu_seconds": 15.0, "train_seconds": 1.0}},
            "raw@paper": {"0": {"cpu_seconds": 12.0, "train_seconds": 1.0}}}
    assert R.time_matched_steps(cfg, arms, 0) == 60  # 40 steps x 15 / 10
    assert R.time_matched_steps(cfg, arms, 1) is None  # no arm of seed 1
    arms["fixed+conf@paper"]["0"]["cpu_seconds"] = 5.0
    arms["raw@paper"]["0"]["cpu_seconds"] = 5.0
    assert R.time_matched_steps(cfg, arms, 0) == 40  # never fewer than the baseline's


def test_fixed_arms_train_on_fixer_images_with_confidence(ood_store):
    """fixed / fixed+conf / progressive join the same number of views; fixed+conf carries the
    confidence as the loss weight; progressive renders from the model being trained (its
    pseudo images differ from the store render's fix); baseline+time runs last with at
    least the baseline's steps; post_fix scores every arm's fixed held-out renders."""
    from freescale_core.store.reader import FreeViewSet

    fvs = FreeViewSet.open(ood_store, "tiny")
    cfg = _cfg(["baseline", "baseline+time", "raw", "fixed", "fixed+conf", "progressive"])
    cfg = cfg.model_copy(update={"post_fix": True})
    out = R.refine_scene(fvs, cfg, log=lambda s: None)
    assert out["computed"][-1] == "baseline+time/seed0"
    arms = out["arms"]
    base = arms["baseline"]["0"]
    bt = arms["baseline+time"]["0"]
    assert bt["iterations"] >= base["iterations"] == 40
    assert bt["iterations"] == R.time_matched_steps(cfg, {k: v for k, v in arms.items()
                                                          if k != "baseline+time"}, 0)
    n = {a: len(arms[a]["0"]["added"]) for a in ("raw@paper", "fixed@paper",
                                                  "fixed+conf@paper", "progressive@paper")}
    assert len(set(n.values())) == 1 and n["raw@paper"] > 0
    for a in ("fixed@paper", "fixed+conf@paper", "progressive@paper"):
        for add in arms[a]["0"]["added"]:
            assert 0.0 <= add["info"]["confidence"] <= 1.0
            assert np.isfinite(add["info"]["pseudo_gt_psnr"])  # procedural: truth known
        assert arms[a]["0"]["fixer_seconds"] > 0
    # the same views (paper order) fixed from the same store model: same pseudo images
    f = {x["view_id"]: x["info"] for x in arms["fixed@paper"]["0"]["added"]}
    fc = {x["view_id"]: x["info"] for x in arms["fixed+conf@paper"]["0"]["added"]}
    assert f.keys() == fc.keys()
    assert all(f[k]["pseudo_gt_psnr"] == fc[k]["pseudo_gt_psnr"] for k in f)
    # progressive: nearest ring first, rendered from the live model (not the store's)
    rs = R.load_refine_scene(fvs, cfg)
    ids = [x["view_id"] for x in arms["progressive@paper"]["0"]["added"]]
    assert ids == R.rank_free_views(rs, "outward", 0)[:len(ids)]
    pr = {x["view_id"]: x["info"]["render_gt_psnr"] for x in arms["progressive@paper"]["0"]["added"]}
    st = {x["view_id"]: x["info"]["render_gt_psnr"] for x in arms["fixed@paper"]["0"]["added"]}
    assert any(pr[k] != st[k] for k in pr.keys() & st.keys())
    for a, by in arms.items():
        post = by["0"]["heldout_post"]
        assert len(post["psnr"]) == len(by["0"]["heldout"]["psnr"])
    summ = json.loads((Path(out["root"]) / "summary.json").read_text())["summary"]
    assert "dpsnr_time" in summ["fixed+conf@paper"] and "post_psnr" in summ["baseline"]


def test_confidence_weight_reaches_the_loss(ood_store, monkeypatch):
    """fixed+conf hands the trainer a float mask equal to confidence x observed; fixed none."""
    from freescale_core.store.reader import FreeViewSet

    fvs = FreeViewSet.open(ood_store, "tiny")
    cfg = _cfg(["fixed", "fixed+conf"])
    rs = R.load_refine_scene(fvs, cfg)
    data = R.training_data(rs, cfg.recon)
    from freescale_core.scene.ply import read_ply

    g = read_ply(fvs.gaussians_ply)
    seen = {}
    orig = R.PseudoViewPool._join

    def spy(self, step):
        orig(self, step)
        seen.setdefault(id(self), []).extend(self.pseudo)
    monkeypatch.setattr(R.PseudoViewPool, "_join", spy)
    R.run_arm(rs, data, cfg, "fixed@paper", 0, store_gaussians=g)
    R.run_arm(rs, data, cfg, "fixed+conf@paper", 0, store_gaussians=g)
    first, second = list(seen.values())
    assert all(v.mask is None for v in first)
    assert all(v.mask is not None and v.mask.is_floating_point() for v in second)
    assert all(float(v.mask.max()) <= 1.0 and float(v.mask.min()) >= 0.0 for v in second)
    assert any(float(v.mask.min()) < 1.0 for v in second)
