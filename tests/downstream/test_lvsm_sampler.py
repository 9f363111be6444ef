"""LVSM view sampler: frame windows, curriculum, target modes, view-graph preference, free-view
rules, DataLoader workers, determinism, and a Hypothesis property test."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch.utils.data import DataLoader, Dataset

from freescale_core.downstream.lvsm.sampler import Sample, SceneViews, ViewSampler
from freescale_core.store.dataset import worker_init_fn
from schemas.lvsm import LVSMSamplerConfig


def make_scene(n_cap: int = 300, n_free: int = 0, n_edges: int = 0, seed: int = 0,
               frame_step: int = 1, scene_id: str = "s") -> SceneViews:
    """Captured views (frame_index 0, step, 2 step, ...) then free views; random graph."""
    rng = np.random.default_rng(seed)
    n = n_cap + n_free
    is_free = np.r_[np.zeros(n_cap, bool), np.ones(n_free, bool)]
    frame_index = np.r_[np.arange(n_cap) * frame_step, -np.ones(n_free, np.int64)]
    src = rng.integers(0, n, n_edges)
    dst = rng.integers(0, n, n_edges)
    return SceneViews(scene_id, is_free, frame_index, (src, dst, rng.random(n_edges)))


def ranks(scene: SceneViews, ids: np.ndarray) -> np.ndarray:
    """Capture-order rank of captured view ids."""
    pos = np.empty(scene.n_views, np.int64)
    pos[scene.captured_order] = np.arange(scene.captured_order.size)
    return pos[ids]


# ---------------------------------------------------------------------------- frame branch

def test_config_defaults_are_the_papers():
    c = LVSMSamplerConfig()
    assert (c.n_input, c.n_target, c.frame_dist, c.warmup_frame_dist) == (4, 2, (15, 40), (10, 20))
    assert (c.graph_prob, c.novel_target_weight, c.target_mode) == (0.5, 0.3, "between")
    with pytest.raises(ValueError):
        LVSMSamplerConfig(frame_dist=(40, 15))
    with pytest.raises(ValueError):
        LVSMSamplerConfig(n_inputs=4)  # extra="forbid"


def test_curriculum_moves_the_range():
    s = ViewSampler(warmup_steps=1000)
    assert s.frame_range(300, 0) == (10, 20)
    assert s.frame_range(300, 500) == (12, 30)  # halfway: 12.5 -> 12 (banker's), 30
    assert s.frame_range(300, 1000) == s.frame_range(300, 10**9) == (15, 40)
    # scaled by n / reference_length, clamped to [n_views - 1, n - 1]
    assert s.frame_range(600, 10**9) == (30, 80)
    assert s.frame_range(60, 10**9) == (5, 8)
    assert s.frame_range(7, 10**9) == (5, 5)
    assert ViewSampler(reference_length=None).frame_range(60, 10**9) == (15, 40)
    assert ViewSampler(reference_length=None).frame_range(30, 10**9) == (15, 29)
    assert ViewSampler(reference_length=None).frame_range(10, 10**9) == (9, 9)
    # the shared step is the default
    s.set_step(1000)
    assert s.step == 1000 and s.frame_range(300) == (15, 40)


@pytest.mark.parametrize("mode", ["between", "extrapolate"])
def test_frame_distances_in_range(mode):
    scene = make_scene(300, frame_step=3)  # gaps in frame_index: distances count captured views
    s = ViewSampler(target_mode=mode, use_free_views=False, warmup_steps=100)
    rng = np.random.default_rng(0)
    for step, (lo, hi) in [(0, (10, 20)), (100, (15, 40))]:
        spans = []
        for _ in range(300):
            x = s.sample(scene, rng, step=step)
            r = ranks(scene, np.r_[x.input_ids, x.target_ids])
            assert x.source == "frames" and x.span == r.max() - r.min()
            assert np.unique(r).size == 6
            spans.append(x.span)
        assert min(spans) >= lo and max(spans) <= hi
        assert min(spans) == lo and max(spans) == hi  # 300 draws cover a range of <= 26 values


def test_between_and_extrapolate_targets():
    scene = make_scene(120)
    rng = np.random.default_rng(1)
    outside = 0
    for mode in ["between", "extrapolate"]:
        s = ViewSampler(target_mode=mode, use_free_views=False)
        for _ in range(200):
            x = s.sample(scene, rng)
            ri, rt = ranks(scene, x.input_ids), ranks(scene, x.target_ids)
            assert np.all(np.diff(ri) > 0)  # inputs in capture order
            out = (rt < ri.min()) | (rt > ri.max())
            if mode == "between":
                assert not out.any()
            else:
                outside += int(out.any())
            np.testing.assert_array_equal(x.target_weight, 1.0)
    assert 60 < outside < 180  # P(some target outside) = 1 - (4/6)(3/5) = 0.6


def test_too_few_captured_views_names_the_scene():
    scene = make_scene(5, n_free=20, n_edges=100, scene_id="tiny-kitchen")
    with pytest.raises(ValueError, match="tiny-kitchen.*5 captured views"):
        ViewSampler().sample(scene, np.random.default_rng(0))
    # exactly n_views captured: the only window is the whole capture
    x = ViewSampler(use_free_views=False).sample(make_scene(6), np.random.default_rng(0))
    assert x.span == 5


def test_scene_validation():
    with pytest.raises(ValueError, match="frame_index -1"):
        SceneViews("a", [False, True], [0, 3], (np.zeros(0), np.zeros(0), np.zeros(0)))
    with pytest.raises(ValueError, match="unique"):
        SceneViews("a", [False, False], [1, 1], (np.zeros(0), np.zeros(0), np.zeros(0)))
    with pytest.raises(ValueError, match=r"0\.\.1"):
        SceneViews("a", [False, False], [0, 1], (np.array([0]), np.array([2]), np.array([.5])))
    sv = SceneViews("a", [False, True, True], [0, -1, -1],
                    (np.array([0, 1, 2]), np.array([1, 1, 0]), np.array([np.nan, .2, 1.5])))
    np.testing.assert_array_equal(sv.edges[0], [0, 2])  # self-loop dropped
    np.testing.assert_array_equal(sv.edges[2], [0.5, 1.0])  # NaN -> 0.5, clipped


# ---------------------------------------------------------------------------- graph branch

def graph_draws(s: ViewSampler, scene: SceneViews, step: int, n: int, seed: int) -> list[Sample]:
    rng = np.random.default_rng(seed)
    out = [s.sample(scene, rng, step=step) for _ in range(n)]
    assert all(x.source == "graph" for x in out)
    return out


def test_graph_follows_wiou_order():
    scene = make_scene(40, n_free=60, n_edges=600, seed=3)
    src, dst, w = scene.edges
    s = ViewSampler(graph_prob=1.0, warmup_steps=100)
    warm = graph_draws(s, scene, 0, 300, seed=4)
    late = graph_draws(s, scene, 100, 300, seed=5)
    w_warm = np.concatenate([x.edge_wiou for x in warm])
    w_late = np.concatenate([x.edge_wiou for x in late])
    assert w_warm.size == w_late.size == 300 * 5
    # warm-up walks high-WIoU edges, later low-WIoU edges; the uniform edge mean lies between
    assert w_warm.mean() > w.mean() + 0.1 > w.mean() - 0.1 > w_late.mean()
    # warm-up seeds are strong nodes, later seeds are not preferred
    strength = np.bincount(src, w, scene.n_views) + np.bincount(dst, w, scene.n_views)
    seeds_warm = strength[[x.input_ids[0] for x in warm]]
    seeds_late = strength[[x.input_ids[0] for x in late]]
    assert seeds_warm.mean() > strength.mean() + 0.5 * strength.std()
    assert abs(seeds_late.mean() - strength.mean()) < 0.5 * strength.std()
    # every attached view is joined to the sample by a graph edge
    pairs = set(zip(src.tolist(), dst.tolist())) | set(zip(dst.tolist(), src.tolist()))
    for x in warm[:50]:
        ids = np.r_[x.input_ids, x.target_ids]
        for i in range(1, 6):
            assert any((int(ids[i]), int(j)) in pairs for j in ids[:i])
    # sharpness 0: no preference, the walk's edges average like all edges
    flat = graph_draws(ViewSampler(graph_prob=1.0, graph_sharpness=0.0), scene, 0, 300, seed=6)
    assert abs(np.concatenate([x.edge_wiou for x in flat]).mean() - w.mean()) < 0.05


def test_free_target_weights():
    scene = make_scene(40, n_free=60, n_edges=600, seed=3)
    s = ViewSampler(graph_prob=1.0, novel_target_weight=0.3)
    for x in graph_draws(s, scene, 0, 100, seed=7):
        assert x.target_weight.dtype == np.float32
        np.testing.assert_array_equal(x.target_weight,
                                      np.where(scene.is_free[x.target_ids], 0.3, 1.0)
                                      .astype(np.float32))


def swap_scene(bridge: bool) -> SceneViews:
    """Captured chain 0..7 (WIoU 0.05); free clique 8..13 (WIoU 0.95), joined to captured view
    0 through free view 8 when ``bridge`` (so captured views 0 and 1 are 1 and 2 hops away)."""
    n_cap, free = 8, np.arange(8, 14)
    src = list(range(n_cap - 1))
    dst = list(range(1, n_cap))
    w = [0.05] * (n_cap - 1)
    for i, a in enumerate(free):
        for b in free[i + 1:]:
            src.append(a), dst.append(b), w.append(0.95)
    if bridge:
        src.append(8), dst.append(0), w.append(0.05)
    return SceneViews("swap", np.r_[np.zeros(8, bool), np.ones(6, bool)],
                      np.r_[np.arange(8), -np.ones(6, np.int64)],
                      (np.array(src), np.array(dst), np.array(w)))


def test_free_only_sample_swaps_an_input_for_a_near_captured_view():
    scene = swap_scene(bridge=True)
    s = ViewSampler(graph_prob=1.0, graph_sharpness=8.0)
    draws = graph_draws(s, scene, 0, 200, seed=8)
    swapped = [x for x in draws if x.swapped]
    assert len(swapped) > 20  # the warm-up walk stays in the strong free clique
    for x in draws:
        ids = np.r_[x.input_ids, x.target_ids]
        assert not scene.is_free[ids].all() and np.unique(ids).size == 6
    for x in swapped:
        assert x.input_ids[-1] == 0  # captured view at one hop replaced the last input
        assert scene.is_free[np.r_[x.input_ids[:-1], x.target_ids]].all()
        np.testing.assert_array_equal(x.target_weight, np.float32(0.3))
    # no captured view within two hops: the frame branch is used instead
    rng = np.random.default_rng(9)
    lone = swap_scene(bridge=False)
    late = ViewSampler(graph_prob=1.0, graph_sharpness=8.0, warmup_steps=10)  # uniform seeds
    srcs = {late.sample(lone, rng, step=10).source for _ in range(100)}
    assert srcs == {"graph", "frames"}  # graph from the captured chain, frames from the clique


def test_use_free_views_false_never_draws_free_views():
    scene = make_scene(40, n_free=200, n_edges=800, seed=10)
    rng = np.random.default_rng(11)
    for s in [ViewSampler(use_free_views=False, graph_prob=1.0),
              ViewSampler(use_free_views=False, random_free=True, graph_prob=1.0)]:
        for _ in range(200):
            x = s.sample(scene, rng)
            assert x.source == "frames"
            assert not scene.is_free[np.r_[x.input_ids, x.target_ids]].any()


def test_random_free_arm_d():
    scene = make_scene(10, n_free=200, n_edges=0, seed=12)  # no graph needed
    s = ViewSampler(random_free=True, graph_prob=1.0)
    xs = [s.sample(scene, np.random.default_rng(i)) for i in range(200)]
    assert {x.source for x in xs} == {"random"}
    n_free = [scene.is_free[np.r_[x.input_ids, x.target_ids]].sum() for x in xs]
    assert max(n_free) == 5 and np.mean(n_free) > 4  # mostly free, never free-only
    assert any(x.swapped for x in xs)


def test_graph_prob_mixes_branches_and_seed_determinism():
    scene = make_scene(60, n_free=60, n_edges=400, seed=13)
    s = ViewSampler()
    a = [s.sample(scene, np.random.default_rng([5, i])) for i in range(200)]
    b = [s.sample(scene, np.random.default_rng([5, i])) for i in range(200)]
    for x, y in zip(a, b):
        assert x.source == y.source and np.array_equal(x.input_ids, y.input_ids)
        assert np.array_equal(x.target_ids, y.target_ids)
    n_graph = sum(x.source == "graph" for x in a)
    assert 70 < n_graph < 130


# ---------------------------------------------------------------------------- workers

class SpanDataset(Dataset):
    """Item i: the frame-branch span of a sample drawn with generator seed (7, i)."""

    def __init__(self, sampler: ViewSampler, scene: SceneViews, n: int = 16) -> None:
        self.sampler, self.scene, self.n = sampler, scene, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> torch.Tensor:
        x = self.sampler.sample(self.scene, np.random.default_rng([7, i]))
        return torch.tensor([x.span, x.step])


@pytest.mark.timeout(60)
@pytest.mark.parametrize("context", ["fork", "spawn"])
def test_workers_see_the_curriculum(context):
    sampler = ViewSampler(use_free_views=False, warmup_steps=1000)
    loader = DataLoader(SpanDataset(sampler, make_scene(300)), batch_size=4, num_workers=2,
                        persistent_workers=True, multiprocessing_context=context,
                        worker_init_fn=worker_init_fn)  # earlier tests ran Prefect in-process
    before = torch.cat(list(loader))  # [16, 2]
    assert (before[:, 1] == 0).all() and before[:, 0].max() <= 20
    sampler.set_step(10**6)  # main process only, after the workers started
    after = torch.cat(list(loader))
    assert (after[:, 1] == 10**6).all()
    assert after[:, 0].min() >= 15 and after[:, 0].max() > 20


# ---------------------------------------------------------------------------- properties

@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n_cap=st.integers(1, 40), n_free=st.integers(0, 30), n_edges=st.integers(0, 120),
       seed=st.integers(0, 2**32 - 1), step=st.integers(0, 5000),
       mode=st.sampled_from(["between", "extrapolate"]), use_free=st.booleans(),
       random_free=st.booleans(), n_input=st.integers(2, 5), n_target=st.integers(1, 3))
def test_property_any_scene(n_cap, n_free, n_edges, seed, step, mode, use_free, random_free,
                            n_input, n_target):
    scene = make_scene(n_cap, n_free, n_edges, seed=seed, frame_step=2)
    s = ViewSampler(target_mode=mode, use_free_views=use_free, random_free=random_free,
                    n_input=n_input, n_target=n_target, graph_prob=0.7)
    rng = np.random.default_rng(seed)
    if n_cap < n_input + n_target:
        with pytest.raises(ValueError, match="captured views"):
            s.sample(scene, rng, step=step)
        return
    for _ in range(5):
        x = s.sample(scene, rng, step=step)
        ids = np.r_[x.input_ids, x.target_ids]
        assert x.input_ids.shape == (n_input,) and x.target_ids.shape == (n_target,)
        assert ids.dtype == np.int64 and ids.min() >= 0 and ids.max() < scene.n_views
        assert np.unique(ids).size == ids.size
        assert not scene.is_free[ids].all()
        np.testing.assert_array_equal(
            x.target_weight, np.where(scene.is_free[x.target_ids], 0.3, 1.0).astype(np.float32))
        if not use_free:
            assert x.source == "frames"
        if x.source == "frames":
            assert not scene.is_free[ids].any()
            lo, hi = s.frame_range(n_cap, step)
            r = ranks(scene, ids)
            assert lo <= x.span == r.max() - r.min() <= hi
            if mode == "between":
                ri, rt = ranks(scene, x.input_ids), ranks(scene, x.target_ids)
                assert ri.min() < rt.min() and rt.max() < ri.max()
        else:
            assert x.source == ("random" if random_free else "graph")
