"""The background colour saved with the Gaussians: ``write_ply(..., background=)`` and its one
reader ``read_background`` (round trip, old files, bad lines naming the file)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.scene.ply import PlyError, read_background, read_ply, write_ply
from tests.scene.test_ply import assert_same, random_gaussians

unit = st.floats(0.0, 1.0, allow_nan=False, width=32)


@settings(max_examples=25, deadline=None)
@given(st.tuples(unit, unit, unit), st.integers(0, 3), st.integers(0, 30))
def test_background_round_trips_exactly(tmp_path_factory, bg, degree, n):
    p = tmp_path_factory.mktemp("bg") / "g.ply"
    g = random_gaussians(n, degree)
    write_ply(p, g, background=bg)
    assert read_background(p, default=(0.5, 0.5, 0.5)) == tuple(float(c) for c in bg)
    assert_same(read_ply(p), g)  # the Gaussians are unchanged by the header line


def test_a_ply_without_the_line_reads_the_default(tmp_path):
    p = tmp_path / "old.ply"
    write_ply(p, random_gaussians(5, 1))  # as every PLY was written before the line existed
    assert read_background(p) == (0.0, 0.0, 0.0)
    assert read_background(p, default=(1, 1, 1)) == (1.0, 1.0, 1.0)


def test_the_gaussian_bytes_are_the_same_with_or_without_the_line(tmp_path):
    g = random_gaussians(7, 2)
    write_ply(tmp_path / "a.ply", g)
    write_ply(tmp_path / "b.ply", g, background=(0.25, 0.5, 1.0))
    a, b = (tmp_path / "a.ply").read_bytes(), (tmp_path / "b.ply").read_bytes()
    assert b"comment background 0.25 0.5 1.0\n" in b
    assert a.split(b"end_header\n", 1)[1] == b.split(b"end_header\n", 1)[1]


def test_a_bad_line_names_the_file(tmp_path):
    p = tmp_path / "bad.ply"
    write_ply(p, random_gaussians(3, 0), background=(0.1, 0.2, 0.3))
    p.write_bytes(p.read_bytes().replace(b"background 0.1 0.2 0.3", b"background 0.1 0.2 2.0"))
    with pytest.raises(PlyError, match="bad.ply"):
        read_background(p)
    with pytest.raises(ValueError, match="three values"):
        write_ply(tmp_path / "x.ply", random_gaussians(3, 0), background=(0.1, 0.2))


def test_recon_result_saves_its_learned_colour(tmp_path):
    from freescale_core.recon.trainer import ReconResult

    res = ReconResult(random_gaussians(4, 0), {"background": [np.float32(0.3), 0.6, 0.9]})
    res.write_ply(tmp_path / "g.ply")
    assert read_background(tmp_path / "g.ply") == res.background == (float(np.float32(0.3)),
                                                                        0.6, 0.9)


def test_the_pipelines_ply_round_trips_its_learned_colour(tmp_path):
    """The reconstruct stage's ``gaussians.ply`` carries the colour the Gaussians were trained
    on (here learned, so not the configured black): every reader takes it from the file."""
    from freescale_core.scene.sample import write_sample_scene
    from freescale_core.store.store import Store
    from schemas.pipeline import PipelineConfig
    from tasks import scene_tasks as T
    from tests.conftest import TINY_OVERRIDES

    scene = write_sample_scene(tmp_path / "sample", n_views=8, width=64, height=48, seed=0,
                               n_points=300)
    over = {**TINY_OVERRIDES, "recon": {**TINY_OVERRIDES["recon"], "background_lr": 0.05,
                                        "threads": 1}}
    cfg = PipelineConfig.from_preset("fast", over)
    st = str(tmp_path / "store")
    i = T.ingest.fn(st, "sample", str(scene), cfg)
    T.reconstruct.fn(st, i, str(scene), cfg)
    learned = tuple(Store(st).stage_result("sample", "reconstruct")["background"])
    ply = Store(st).work_dir("sample") / "gaussians.ply"
    assert learned != (0.0, 0.0, 0.0)  # learned, not the configured colour
    assert read_background(ply, default=(0.5, 0.5, 0.5), scene_id="sample") == learned
