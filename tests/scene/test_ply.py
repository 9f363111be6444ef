"""3DGS PLY I/O: round trip (property), golden byte layout, errors naming the file."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.errors import MissingInputError, SceneError
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.ply import (
    PlyError,
    read_element,
    read_ply,
    read_ply_points,
    write_element,
    write_ply,
    write_ply_points,
)


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 3,
                     rng.normal(size=(n, 4)), rng.normal(size=n), rng.normal(size=(n, k, 3)))


def assert_same(a: Gaussians, b: Gaussians) -> None:
    for name in ("means", "log_scales", "quats_wxyz", "opacity_logits", "sh"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape, name
        assert np.array_equal(x, y), name


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 40), st.integers(0, 3), st.booleans(), st.integers(0, 1000))
def test_round_trip(tmp_path_factory, n, degree, normals, seed):
    g = random_gaussians(n, degree, seed)
    p = tmp_path_factory.mktemp("ply") / "g.ply"
    write_ply(p, g, normals=normals)
    assert_same(read_ply(p), g)


def test_golden_byte_layout(tmp_path):
    """Hand-built 3DGS file (degree 1, N=2): header text and float order must match exactly."""
    n, k = 2, 4
    means = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    sh = np.arange(n * k * 3, dtype=np.float32).reshape(n, k, 3) / 10  # sh[i, coef, channel]
    opac = np.array([0.5, -0.5], np.float32)
    scales = np.array([[-1, -2, -3], [-4, -5, -6]], np.float32)
    quats = np.array([[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]], np.float32)
    g = Gaussians(means, scales, quats, opac, sh)
    write_ply(tmp_path / "g.ply", g)

    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] \
        + [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                "rot_0", "rot_1", "rot_2", "rot_3"]
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 2\n" \
        + "".join(f"property float {nm}\n" for nm in names) + "end_header\n"
    body = b""
    for i in range(n):
        row = list(means[i]) + [0, 0, 0] + list(sh[i, 0])
        for c in range(3):  # channel-major f_rest: R coeffs 1..3, then G, then B
            row += [sh[i, j, c] for j in range(1, k)]
        row += [opac[i], *scales[i], *quats[i]]
        body += struct.pack("<" + "f" * len(row), *row)
    expected = header.encode() + body
    assert (tmp_path / "g.ply").read_bytes() == expected
    # and the hand-built bytes read back to the same Gaussians
    (tmp_path / "h.ply").write_bytes(expected)
    assert_same(read_ply(tmp_path / "h.ply"), g)


def test_reads_any_property_order_double_and_big_endian(tmp_path):
    g = random_gaussians(7, 1, seed=3)
    v = read_element(_written(tmp_path, g), "vertex")
    names = list(v.dtype.names)[::-1]
    dt = np.dtype([(nm, ">f8") for nm in names])  # reversed order, big-endian doubles
    data = np.zeros(len(v), dt)
    for nm in names:
        data[nm] = v[nm]
    hdr = "ply\nformat binary_big_endian 1.0\ncomment reversed\nelement vertex 7\n" + \
        "".join(f"property double {nm}\n" for nm in names) + "end_header\n"
    p = tmp_path / "be.ply"
    p.write_bytes(hdr.encode() + data.tobytes())
    assert_same(read_ply(p), g)


def _written(tmp_path, g, name="g.ply"):
    p = tmp_path / name
    write_ply(p, g)
    return p


def test_truncated_file_names_file(tmp_path):
    p = _written(tmp_path, random_gaussians(10, 2))
    data = p.read_bytes()
    p.write_bytes(data[:-30])
    with pytest.raises(PlyError) as e:
        read_ply(p, scene_id="sceneX")
    assert "truncated" in str(e.value) and "sceneX" in str(e.value) and str(p) in str(e.value)


def test_missing_property_names_file(tmp_path):
    g = random_gaussians(3, 0)
    v = read_element(_written(tmp_path, g), "vertex")
    keep = [nm for nm in v.dtype.names if nm != "rot_2"]
    p = tmp_path / "missing.ply"
    write_element(p, _select(v, keep))
    with pytest.raises(PlyError) as e:
        read_ply(p, scene_id="s1")
    assert "rot_2" in str(e.value) and str(p) in str(e.value)


def _select(v, keep):
    out = np.zeros(len(v), np.dtype([(nm, v.dtype[nm]) for nm in keep]))
    for nm in keep:
        out[nm] = v[nm]
    return out


def test_bad_f_rest_count_and_not_ply(tmp_path):
    g = random_gaussians(3, 1)
    v = read_element(_written(tmp_path, g), "vertex")
    keep = [nm for nm in v.dtype.names if nm != "f_rest_8"]
    p = tmp_path / "rest.ply"
    write_element(p, _select(v, keep))
    with pytest.raises(PlyError, match="f_rest"):
        read_ply(p)
    q = tmp_path / "junk.ply"
    q.write_bytes(b"not a ply at all")
    with pytest.raises(PlyError, match="magic"):
        read_ply(q)
    with pytest.raises(MissingInputError):
        read_ply(tmp_path / "nope.ply", scene_id="s")
    assert issubclass(PlyError, SceneError)


def test_atomic_write_leaves_no_temp_files(tmp_path):
    write_ply(tmp_path / "a.ply", random_gaussians(5, 0))
    write_ply(tmp_path / "a.ply", random_gaussians(6, 0))  # overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply"]
    assert len(read_ply(tmp_path / "a.ply")) == 6


@pytest.mark.parametrize("ascii_", [False, True])
def test_points_round_trip(tmp_path, ascii_):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32).astype(np.float64)
    rgb = rng.integers(0, 256, size=(50, 3)).astype(np.uint8)
    p = tmp_path / "pts.ply"
    write_ply_points(p, xyz, rgb, ascii=ascii_)
    x2, c2 = read_ply_points(p)
    assert np.allclose(x2, xyz, atol=1e-6 if ascii_ else 0)
    assert np.array_equal(c2, rgb)


def test_reads_nerfstudio_ascii_point_cloud(tmp_path):
    """The exact header ns-process-data writes for sparse_pc.ply (ASCII, uint8 colours)."""
    p = tmp_path / "sparse_pc.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                 "property float z\nproperty uint8 red\nproperty uint8 green\n"
                 "property uint8 blue\nend_header\n"
                 "0.100000 -2.000000 3.500000 255 0 7\n1.000000 2.000000 3.000000 1 2 3\n")
    xyz, rgb = read_ply_points(p)
    assert np.allclose(xyz, [[0.1, -2, 3.5], [1, 2, 3]])
    assert rgb.tolist() == [[255, 0, 7], [1, 2, 3]]
