"""A user PLY in another frame is refused with what was found (issue 12 #13)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from freescale_core.scene.io import load_scene
from freescale_core.scene.ply_alignment import PlyFrameError, check_alignment
from freescale_core.scene.sample import write_sample_scene


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from freescale_core.recon.trainer import reconstruct
    from schemas.pipeline import PipelineConfig
    from tests.flows.test_flow import TINY

    d = tmp_path_factory.mktemp("align")
    sc = load_scene(write_sample_scene(d / "s", n_views=16, width=80, height=60))
    g = reconstruct(sc, PipelineConfig.from_preset("fast", TINY).recon, seed=0).gaussians
    return sc, g


def _normalised(g):
    """What gsplat's normalize_world_space does: centre on the cameras, scale to unit size."""
    c = g.means.mean(axis=0)
    s = 1.0 / float(np.abs(g.means - c).max())
    return dataclasses.replace(g, means=((g.means - c) * s + [0.0, 0.0, 3.0]).astype(np.float32),
                               log_scales=(g.log_scales + np.log(s)).astype(np.float32))


def test_ply_in_the_scene_frame_passes(trained):
    sc, g = trained
    st = check_alignment(g, sc, "gaussians.ply")
    assert st["psnr_median"] > 15


def test_ply_in_a_normalised_frame_is_refused_with_numbers(trained):
    sc, g = trained
    with pytest.raises(PlyFrameError) as e:
        check_alignment(_normalised(g), sc, "gaussians.ply")
    msg = str(e.value)
    assert "PSNR" in msg and "cameras' extent" in msg and "another frame" in msg
    assert "gaussians.ply" in msg and sc.scene_id in msg
