"""Real-scene stability variants (freescale_core/eval/real_variants.py), made here from the
tiny procedural scene written as a plain COLMAP folder, so they run without the shared
datasets: view counts, the unchanged held-out split, brightness and pose perturbations, the
atomic write and the ``real:NAME@FAMILY`` scene specs."""

from __future__ import annotations

import numpy as np
import pytest

from freescale_core.eval.real_variants import parse_family, write_real_variant
from freescale_core.eval.scenes import describe, resolve_scenes, write_eval_scene
from freescale_core.scene.io import load_scene


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("real_variants")
    p = write_eval_scene("tiny", root / "datasets" / "tinybase")  # 12 views: 8 train, 4 held out
    (p / "scene.json").unlink()  # a "real" scene: no oracle
    return p


def _names(scene, idx):
    return [scene.image_names[i] for i in idx]


def _rot_deg(a, b):
    cos = (np.einsum("nij,nij->n", a[:, :3, :3], b[:, :3, :3]) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_few_keeps_n_training_views_and_the_heldout_split(base, tmp_path):
    ref = load_scene(base)
    tr, te = ref.split("ood")
    assert (len(tr), len(te)) == (8, 4)
    p = write_real_variant(base, "few3", tmp_path / "tinybase--few3")
    sc = load_scene(p)
    a, b = sc.split("ood")
    assert len(sc) == 7 and len(a) == 3
    assert _names(sc, a) == _names(ref, tr[[0, 4, 7]])  # evenly spaced over the training views
    assert _names(sc, b) == _names(ref, te)  # the held-out views are the base's
    np.testing.assert_allclose(sc.cameras.world_from_cam[b], ref.cameras.world_from_cam[te],
                               atol=1e-9)
    assert sc.split("every8")[1].tolist() == b.tolist()  # heldout.txt, whatever the rule
    with pytest.raises(ValueError, match="8 training views"):
        write_real_variant(base, "few8", tmp_path / "tinybase--few8")
    assert not (tmp_path / "tinybase--few8").exists()
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]  # no staging left
    mtime = (p / "variant.json").stat().st_mtime_ns  # written once, then reused
    assert write_real_variant(base, "few3", p) == p and \
        (p / "variant.json").stat().st_mtime_ns == mtime


def test_dark_scales_brightness_and_adds_noise(base, tmp_path):
    ref = load_scene(base)
    sc = load_scene(write_real_variant(base, "dark", tmp_path / "tinybase--dark"))
    assert len(sc) == 12 and _names(sc, sc.split("ood")[1]) == _names(ref, ref.split("ood")[1])
    x = np.stack([ref.load_image(i) for i in range(12)]).astype(float)
    y = np.stack([sc.load_image(i) for i in range(12)]).astype(float)
    assert y.mean() / x.mean() == pytest.approx(0.15, abs=0.02)
    resid = (y - 0.15 * x)[0.15 * x > 8]  # away from the clip at 0
    assert 1.0 < resid.std() < 3.0


@pytest.mark.parametrize("family", ["rotnoise3", "transnoise0.05"])
def test_pose_noise_on_training_views_only(base, tmp_path, family):
    ref = load_scene(base)
    tr, te = ref.split("ood")
    sc = load_scene(write_real_variant(base, family, tmp_path / f"tinybase--{family}"))
    a, b = sc.split("ood")
    assert _names(sc, a) == _names(ref, tr) and _names(sc, b) == _names(ref, te)
    w0, w1 = ref.cameras.world_from_cam, sc.cameras.world_from_cam
    np.testing.assert_allclose(w1[b], w0[te], atol=1e-9)  # held-out poses exact
    deg = _rot_deg(w0[tr], w1[a])
    move = np.linalg.norm(w0[tr, :3, 3] - w1[a, :3, 3], axis=1)
    if family.startswith("rot"):
        assert 0.3 < deg.mean() < 10 and move.max() < 1e-6
    else:
        assert deg.max() < 1e-4 and move.mean() > 1e-3


def test_real_specs_write_variants_and_skip_with_reasons(base, tmp_path, monkeypatch):
    monkeypatch.setenv("FREESCALE_DATASETS", str(base.parent))
    paths, skipped = resolve_scenes(["real:tinybase@few3", "real:tinybase@few20",
                                     "real:nosuch@dark"], tmp_path / "out")
    assert [p.name for p in paths] == ["tinybase--few3"]
    assert paths[0].parent == (tmp_path / "out" / "scenes").resolve()
    assert any(s.startswith("tinybase--few20:") for s in skipped)
    assert any(s.startswith("nosuch:") for s in skipped)
    assert "tinybase" in describe("tinybase--few3") and "3 evenly spaced" in \
        describe("tinybase--few3")
    assert parse_family("transnoise0.02") == ("transnoise", 0.02)
    with pytest.raises(ValueError):
        parse_family("bright")


def test_heldout_list_must_name_scene_images(base, tmp_path):
    import shutil

    from freescale_core.errors import MissingInputError

    p = tmp_path / "s"
    shutil.copytree(base, p)
    (p / "heldout.txt").write_text("frame_00011.png\nnot_there.png\n")
    with pytest.raises(MissingInputError, match="not_there"):
        load_scene(p)
    (p / "heldout.txt").write_text("# comment\nframe_00000.png\n")
    sc = load_scene(p)
    assert _names(sc, sc.split("ood")[1]) == ["frame_00000.png"]
    assert len(sc.split("all")[1]) == 0
