"""Stage 7 quality scores: BRISQUE (offline), black ratio, depth-range validity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.freeviews.quality import (QualityScores, black_ratio, brisque_features,
                                    brisque_score, depth_validity, failure_reasons, passes,
                                    score_view)
from schemas.freeview import QualityConfig

from tests.conftest import real_scene_dir


@pytest.fixture(scope="module")
def astronaut():
    """A real photo that is always there (bundled with scikit-image), 256 x 256."""
    return cv2.resize(skimage.data.astronaut(), (256, 256), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def dataset_photo():
    """A real photo from the shared datasets (skipped when absent), longest side 256."""
    d = real_scene_dir("kermit")
    img = cv2.imread(str(sorted((d / "images").glob("*.jpg"))[0]))[..., ::-1]
    h, w = img.shape[:2]
    s = 256 / max(h, w)
    return np.ascontiguousarray(cv2.resize(img, (round(w * s), round(h * s)),
                                           interpolation=cv2.INTER_AREA))


# --------------------------------------------------------------------------- BRISQUE
def test_brisque_matches_the_package(astronaut):
    """Reference test: our fast path equals the package's own pipeline (scipy convolutions,
    with only its numpy-2 feature flattening fixed) to float precision."""
    from brisque import BRISQUE

    class Ref(BRISQUE):
        def scale_features(self, features):
            flat = np.concatenate([np.ravel(np.asarray(f, np.float64)) for f in features])
            return super().scale_features(flat)

    img = astronaut[:200, :240]
    assert brisque_score(img) == pytest.approx(Ref(url=False).score(img) / 100.0, abs=1e-9)
    assert brisque_features(img).shape == (36,)


def test_brisque_is_deterministic(astronaut):
    img = astronaut[:96, :128]
    assert len({brisque_score(img) for _ in range(10)}) == 1


def _blur_curve(img):
    return [brisque_score(img if s == 0 else cv2.GaussianBlur(img, (0, 0), s))
            for s in (0, 0.8, 1.5, 2.5, 4.0)]


def test_blur_raises_brisque_monotonically(astronaut):
    b = _blur_curve(astronaut)
    assert all(y > x for x, y in zip(b, b[1:])), b
    assert b[0] < 0.5 <= b[-1]  # a sharp photo passes, a strongly blurred one is rejected


def test_blur_raises_brisque_on_a_dataset_photo(dataset_photo):
    b = _blur_curve(dataset_photo)
    assert all(y > x for x, y in zip(b, b[1:])), b


def test_noise_raises_brisque(astronaut):
    rng = np.random.default_rng(0)
    clean = brisque_score(astronaut)
    scores = []
    for sigma in (20, 40, 60):
        noisy = np.clip(astronaut + rng.normal(0, sigma, astronaut.shape), 0, 255)
        scores.append(brisque_score(noisy.astype(np.uint8)))
    assert clean < scores[0] < scores[1] < scores[2], (clean, scores)


def test_brisque_float_input_is_quantised_like_uint8(astronaut):
    assert brisque_score(astronaut.astype(np.float32) / 255.0) == brisque_score(astronaut)


def test_brisque_constant_image_is_worst():
    assert brisque_score(np.zeros((64, 64, 3), np.uint8)) == 1.0
    assert brisque_score(np.full((64, 64, 3), 0.5, np.float32)) == 1.0


# --------------------------------------------------------------------------- black ratio
def test_black_ratio_counts_black_and_empty_pixels(astronaut):
    astronaut = np.maximum(astronaut, 1)  # the photo has ~10% pure black pixels of its own
    img = astronaut.copy()
    assert black_ratio(np.zeros_like(img)) == 1.0
    img[:64] = 0  # a quarter exactly black
    assert black_ratio(img) == pytest.approx(0.25, abs=0.01)
    alpha = np.ones(img.shape[:2], np.float32)
    alpha[:, :64] = 0.0  # a quarter empty, composited over grey: not black, still empty
    img2 = astronaut.copy()
    img2[:, :64] = 128
    assert black_ratio(img2) < 0.01
    assert black_ratio(img2, alpha) == pytest.approx(0.25, abs=0.01)
    # float input: anything that rounds to 0 in uint8 is black
    f = np.full((10, 10, 3), 0.001, np.float32)
    assert black_ratio(f) == 1.0


def test_black_image_fails_the_filter():
    rgb = np.zeros((64, 64, 3), np.float32)
    depth = np.tile(np.linspace(1, 3, 64, dtype=np.float32), (64, 1))
    s = score_view(rgb, depth, np.ones((64, 64), np.float32))
    assert not passes(s)
    assert "black" in failure_reasons(s)


# --------------------------------------------------------------------------- depth validity
def _ramp(h=64, w=64):
    return np.tile(np.linspace(1.0, 3.0, w, dtype=np.float32), (h, 1))


def test_flat_depth_fails():
    assert depth_validity(np.full((64, 64), 2.0, np.float32)) == 0.0
    s = QualityScores(brisque=0.2, black_ratio=0.0, depth_validity=depth_validity(
        np.full((64, 64), 2.0, np.float32)))
    assert failure_reasons(s) == ["depth"]


def test_depth_validity_of_a_ramp_and_the_crop():
    d = _ramp()
    # central 70% of a linear ramp, min-max normalised: uniform on [0, 1] -> 0.95 - 0.05
    assert depth_validity(d) == pytest.approx(0.9, abs=0.02)
    # structure only outside the central crop does not count
    d2 = np.full((100, 100), 2.0, np.float32)
    d2[:, :10] = 5.0
    assert depth_validity(d2, crop=0.7) == 0.0
    assert depth_validity(d2, crop=1.0) > 0


def test_depth_validity_needs_ten_percent_valid_pixels():
    d = _ramp()
    alpha = np.zeros_like(d)
    alpha[30:33, :] = 1.0  # ~5% of the crop valid
    assert depth_validity(d, alpha) == 0.0
    alpha[20:45, :] = 1.0
    assert depth_validity(d, alpha) > 0.5
    d_bad = d.copy()
    d_bad[:] = np.nan
    assert depth_validity(d_bad) == 0.0


@settings(max_examples=25, deadline=None)
@given(st.floats(0.01, 100.0), st.floats(0.0, 50.0), st.integers(0, 1000))
def test_depth_validity_is_affine_invariant_and_bounded(a, b, seed):
    d = np.random.default_rng(seed).uniform(1, 5, (40, 50)).astype(np.float64)
    v = depth_validity(d)
    assert 0.0 <= v <= 1.0
    assert depth_validity(a * d + b) == pytest.approx(v, abs=1e-6)


# --------------------------------------------------------------------------- the rule
def test_thresholds_are_the_papers():
    cfg = QualityConfig()
    ok = QualityScores(0.49, 0.2, 0.11)
    assert passes(ok, cfg)
    assert failure_reasons(QualityScores(0.5, 0.2, 0.11), cfg) == ["brisque"]
    assert failure_reasons(QualityScores(0.49, 0.21, 0.11), cfg) == ["black"]
    assert failure_reasons(QualityScores(0.49, 0.2, 0.1), cfg) == ["depth"]
    assert not passes(QualityScores(float("nan"), 0.0, 0.5), cfg)


def test_good_render_passes(astronaut):
    d = _ramp(*astronaut.shape[:2])
    s = score_view(astronaut.astype(np.float32) / 255, d, np.ones(d.shape, np.float32))
    assert passes(s), s


def test_brisque_model_loads_safely_from_concurrent_threads():
    """Scenes run in threads; libsvm's model loader is not thread-safe (a segfault in the flow
    tests when two scenes first scored at once). Eight threads race for the first load."""
    import subprocess
    import sys

    code = (
        "import threading, numpy as np\n"
        "from freescale_core.freeviews import quality\n"
        "img = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)\n"
        "out = []\n"
        "def go():\n"
        "    out.append(quality.brisque_score(img))\n"
        "ts = [threading.Thread(target=go) for _ in range(8)]\n"
        "[t.start() for t in ts]; [t.join() for t in ts]\n"
        "assert len(out) == 8 and len(set(out)) == 1, out\n"
        "print('ok')\n")
    for _ in range(3):  # a fresh process each time: the race is on the first load
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           cwd=str(__import__("pathlib").Path(__file__).resolve().parents[2]))
        assert r.returncode == 0 and "ok" in r.stdout, (r.returncode, r.stderr[-2000:])


@pytest.mark.parametrize("blur", [0.0, 3.0])
def test_brisque_features_one_pass_equal_the_package_fits(astronaut, blur):
    """The AGGD fits fed by the one-pass numba sums equal the package's own fits (masked
    copies, numpy sums) to 1e-10 relative on every one of the 36 features."""
    import cv2

    from freescale_core.freeviews.quality import _brisque_model, _gray

    img = astronaut if blur == 0 else cv2.GaussianBlur(astronaut, (0, 0), blur)
    m = _brisque_model()
    g = _gray(img)
    for gray in (g, cv2.resize(g, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_CUBIC)):
        new = m.calculate_brisque_features(gray)
        old = np.array([float(np.ravel(x)[0])
                        for x in super(type(m), m).calculate_brisque_features(gray)])
        np.testing.assert_allclose(new, old, rtol=1e-10, atol=0)
