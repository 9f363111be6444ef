"""Figures of a published version: the funnel counts (against a plain loop) and the files."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.store.figures import funnel_counts
from schemas.select import TRAJECTORY_MODES

DISP = ["infeasible", "suppressed", "free_view", "rejected"]


def fake_scene(cams, root, scene_id: str = "room"):
    """The parts of a ``Scene`` that publishing reads, with real (tiny) training images."""
    from types import SimpleNamespace

    from PIL import Image

    root.mkdir(parents=True, exist_ok=True)
    names = [f"{i:03d}.png" for i in range(len(cams))]
    for n in names:
        Image.new("RGB", (8, 6), (90, 120, 150)).save(root / n)
    rng = np.random.default_rng(0)
    return SimpleNamespace(cameras=cams, image_names=names, scene_id=scene_id,
                           image_paths=[root / n for n in names],
                           capture_order=np.arange(len(cams)),
                           points_xyz=rng.normal(size=(20, 3)),
                           points_rgb=rng.integers(0, 255, (20, 3)))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(TRAJECTORY_MODES), st.sampled_from(DISP),
                          st.booleans()), min_size=1, max_size=60), st.integers(0, 5))
def test_funnel_counts_match_a_plain_loop(cands, n_train):
    kind = ["train"] * n_train + ["candidate"] * len(cands)
    mode = ["train"] * n_train + [m for m, _, _ in cands]
    disp = ["train"] * n_train + [d for _, d, _ in cands]
    # a candidate passed the filter only if it was rendered (free_view or rejected)
    passed = [False] * n_train + [p and d in ("free_view", "rejected") for _, d, p in cands]
    passed = [p or d == "free_view" for p, d in zip(passed, disp)]
    brisque = [np.nan] * n_train + [0.3 if d in ("free_view", "rejected") else np.nan
                                    for _, d, _ in cands]
    fc = funnel_counts({"kind": kind, "mode": mode, "disposition": disp, "passed": passed,
                        "brisque": brisque})
    for m in TRAJECTORY_MODES:
        rows = [(d, p) for (mm, d, _), p in zip(cands, passed[n_train:]) if mm == m]
        rendered = any(d in ("free_view", "rejected") for _, d, _ in cands)
        assert fc["candidates"][m] == len(rows)
        assert fc["feasible"][m] == sum(d != "infeasible" for d, _ in rows)
        assert fc["selected"][m] == sum(d in ("free_view", "rejected") for d, _ in rows)
        assert fc["passed filter"][m] == (sum(p for d, p in rows) if rendered else 0)
        assert fc["free views"][m] == (sum(d == "free_view" for d, _ in rows) if rendered else 0)
    # a funnel never widens
    tot = [sum(v.values()) for v in fc.values()]
    assert all(a >= b for a, b in zip(tot, tot[1:]))
