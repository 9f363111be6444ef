"""The needle regulariser (``lab/needle.py``): zero for blobs and discs, the log excess of
longest / middle axis for needles, invariant to the order of the axes and to a uniform scale."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lab.needle import needle_loss


def _reference(log_scales: np.ndarray, max_ratio: float) -> float:
    """The obvious loop: sort each Gaussian's three scales, compare longest and middle."""
    out = []
    for row in log_scales:
        s = sorted(math.exp(v) for v in row)
        out.append(max(0.0, math.log(s[2] / s[1]) - math.log(max_ratio)))
    return sum(out) / len(out)


def test_blob_disc_needle():
    ls = torch.log(torch.tensor([[1.0, 1.0, 1.0],      # blob
                                 [1.0, 1.0, 0.001],    # flat disc: free
                                 [9.0, 1.0, 1.0],      # under the ratio
                                 [100.0, 1.0, 0.5]]))  # needle, 100 : 1
    got = float(needle_loss(ls, 10.0))
    assert got == pytest.approx(math.log(10.0) / 4, rel=1e-6)
    assert float(needle_loss(ls[:3], 10.0)) == 0.0
    assert float(needle_loss(ls[:0], 10.0)) == 0.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-6, 3)] * 3), min_size=1, max_size=12),
       st.floats(1.0, 50.0), st.floats(-3, 3), st.permutations([0, 1, 2]))
def test_matches_reference_and_invariances(rows, ratio, shift, perm):
    ls = np.asarray(rows, np.float64)
    t = torch.from_numpy(ls)
    got = float(needle_loss(t, ratio))
    assert got == pytest.approx(_reference(ls, ratio), abs=1e-9)
    assert float(needle_loss(t[:, list(perm)], ratio)) == pytest.approx(got, abs=1e-9)
    assert float(needle_loss(t + shift, ratio)) == pytest.approx(got, abs=1e-9)


def test_gradient_shortens_the_long_axis_only_for_needles():
    ls = torch.log(torch.tensor([[50.0, 1.0, 1.0], [2.0, 1.0, 1.0]])).requires_grad_(True)
    needle_loss(ls, 10.0).backward()
    g = ls.grad
    assert g[0, 0] > 0 and g[0, 1] + g[0, 2] < 0  # descent: long axis shrinks, middle grows
    assert torch.all(g[1] == 0)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path_factory.mktemp("needle") / "s", n_views=8, width=64,
                           height=48, seed=0, n_points=300)
    return load_scene(d)
