"""PLY files: 3D Gaussian Splatting scenes (stage 1 output) and sparse point clouds.

The 3DGS layout (original 3DGS ``save_ply``, gsplat and nerfstudio exports), one ``vertex``
element, all properties ``float`` (float32), binary little endian, in this order:

``x y z  nx ny nz  f_dc_0..2  f_rest_0..f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3``

* ``f_dc_c`` is the DC SH coefficient of colour channel c;
* ``f_rest`` is **channel-major**: the K-1 higher-order coefficients of R, then those of G,
  then those of B (3DGS stores ``features_rest [N, K-1, 3]`` transposed to ``[N, 3, K-1]``);
* ``opacity`` is the logit, ``scale_*`` the log scales, ``rot_*`` the quaternion (w, x, y, z),
  all unactivated (as :class:`~freescale_core.scene.gaussians.Gaussians` stores them);
* ``nx ny nz`` are zeros (3DGS writes them; readers ignore them).

Readers accept any property order, ``float``/``double``/integer types, binary (either
endianness) and ASCII files, and other elements before or after ``vertex`` as long as they
have no list properties before it. Writes are atomic (temporary file + ``os.replace``).

The background colour the Gaussians were trained on (learned, or the configured one) is saved
with them as one header line, ``comment background R G B`` (floats in [0, 1]; other readers
skip comments). :func:`read_background` is the one reader; a PLY without the line (trained
elsewhere, or written before the line existed) reads the default it is given.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freescale_core.errors import SceneError
from freescale_core.files import temp_name
from freescale_core.scene.gaussians import Gaussians

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "ascii"}


class PlyError(SceneError):
    """A PLY file is malformed, truncated or lacks required properties (names the file)."""


@dataclass
class PlyElement:
    """One element of a PLY header."""

    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code without byte order)
    has_list: bool = False

    def dtype(self, order: str) -> np.dtype:
        bo = "<" if order == "ascii" else order
        return np.dtype([(n, bo + t) for n, t in self.properties])


def read_header(path: Path, scene_id: str = "?") -> tuple[str, list[PlyElement], int]:
    """Parse a PLY header.

    Returns:
        ``(byte_order_or_'ascii', elements, header_length_in_bytes)``.
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if not head.startswith(b"ply"):
        raise PlyError(scene_id, "not a PLY file (missing 'ply' magic)", path)
    m = re.search(rb"end_header\r?\n", head)
    if m is None:
        raise PlyError(scene_id, "PLY header has no end_header line (truncated?)", path)
    text = head[: m.start()].decode("ascii", errors="replace")
    fmt, elements = None, []
    for line in text.splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in FORMATS:
                raise PlyError(scene_id, f"unsupported PLY format line {line!r}", path)
            fmt = FORMATS[parts[1]]
        elif parts[0] == "element":
            elements.append(PlyElement(parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise PlyError(scene_id, "property before any element in the PLY header", path)
            if parts[1] == "list":
                elements[-1].has_list = True
                elements[-1].properties.append((parts[-1], "list"))
                continue
            if parts[1] not in PLY_TYPES:
                raise PlyError(scene_id, f"unknown PLY property type {parts[1]!r}", path)
            elements[-1].properties.append((parts[2], PLY_TYPES[parts[1]]))
    if fmt is None:
        raise PlyError(scene_id, "PLY header has no format line", path)
    return fmt, elements, m.end()


def read_element(path: str | Path, name: str = "vertex", scene_id: str = "?") -> np.ndarray:
    """One element of a PLY file as a structured array ``[count]`` (native byte order).

    Raises:
        PlyError: missing element, list properties before it, or truncated data.
    """
    path = Path(path)
    if not path.is_file():
        from freescale_core.errors import MissingInputError

        raise MissingInputError(scene_id, "PLY file is missing", path)
    order, elements, offset = read_header(path, scene_id)
    names = [e.name for e in elements]
    if name not in names:
        raise PlyError(scene_id, f"PLY has no '{name}' element (elements: {names})", path)
    idx = names.index(name)
    el = elements[idx]
    if el.has_list or any(e.has_list for e in elements[:idx]):
        raise PlyError(scene_id, f"list properties in/before '{name}' are not supported", path)
    if order == "ascii":
        return _read_ascii(path, elements, idx, offset, scene_id)
    skip = sum(e.count * e.dtype(order).itemsize for e in elements[:idx])
    dt = el.dtype(order)
    need = offset + skip + el.count * dt.itemsize
    size = path.stat().st_size
    if size < need:
        raise PlyError(scene_id, f"PLY is truncated: header promises {el.count} '{name}' rows "
                       f"({need} bytes), file has {size} bytes", path)
    arr = np.fromfile(path, dtype=dt, count=el.count, offset=offset + skip)
    return arr.astype(dt.newbyteorder("="), copy=False)


def _read_ascii(path: Path, elements: list[PlyElement], idx: int, offset: int,
                scene_id: str) -> np.ndarray:
    with open(path, "rb") as f:
        f.seek(offset)
        lines = f.read().decode("ascii", errors="replace").splitlines()
    start = sum(e.count for e in elements[:idx])
    el = elements[idx]
    rows = [ln for ln in lines[start:start + el.count]]
    if len(rows) < el.count:
        raise PlyError(scene_id, f"PLY is truncated: header promises {el.count} '{el.name}' "
                       f"rows, found {len(rows)}", path)
    dt = el.dtype("ascii")
    out = np.zeros(el.count, dtype=dt)
    try:
        vals = np.array([r.split()[: len(el.properties)] for r in rows], dtype=np.float64)
    except ValueError as e:
        raise PlyError(scene_id, f"bad ASCII PLY row ({e})", path) from e
    if vals.ndim != 2 or vals.shape[1] != len(el.properties):
        raise PlyError(scene_id, f"ASCII PLY rows do not have {len(el.properties)} values", path)
    for j, (n, _) in enumerate(el.properties):
        out[n] = vals[:, j]
    return out


def write_element(path: str | Path, data: np.ndarray, name: str = "vertex",
                  comments: tuple[str, ...] = (), ascii: bool = False) -> None:
    """Write one structured array as a PLY element (binary little endian or ASCII), atomically."""
    rev = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
           "u4": "uint", "f4": "float", "f8": "double"}
    lines = ["ply", "format ascii 1.0" if ascii else "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element {name} {len(data)}")
    for n in data.dtype.names:
        code = data.dtype[n].str[1:]
        lines.append(f"property {rev[code]} {n}")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    if ascii:
        cols = [data[n] for n in data.dtype.names]
        body = "".join(" ".join(_fmt(c[i]) for c in cols) + "\n" for i in range(len(data)))
        payload = body.encode("ascii")
    else:
        le = np.dtype([(n, "<" + data.dtype[n].str[1:]) for n in data.dtype.names])
        payload = np.ascontiguousarray(data.astype(le)).tobytes()
    _atomic_write(Path(path), header + payload)


def _fmt(v) -> str:
    return repr(float(v)) if isinstance(v, np.floating) else str(int(v))


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


# --------------------------------------------------------------------------- Gaussians
def gaussian_dtype(sh_degree: int, normals: bool = True) -> np.dtype:
    """Structured dtype of the 3DGS vertex layout for SH degree ``sh_degree``."""
    k = (sh_degree + 1) ** 2
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])
    names += [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    return np.dtype([(n, "<f4") for n in names])


def gaussians_to_struct(g: Gaussians, normals: bool = True) -> np.ndarray:
    """``[N]`` structured array in the 3DGS layout (f_rest channel-major)."""
    n, k = len(g), g.sh.shape[1]
    flat = np.concatenate([
        g.means,
        *([np.zeros((n, 3), np.float32)] if normals else []),
        g.sh[:, 0, :],                                              # [N, 3]
        # [N, 3*(K-1)] channel-major: R coefficients, then G, then B
        np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(n, 3 * (k - 1)),
        g.opacity_logits[:, None], g.log_scales, g.quats_wxyz,
    ], axis=1).astype("<f4")
    return np.ascontiguousarray(flat).view(gaussian_dtype(g.sh_degree, normals)).reshape(n)


BACKGROUND_COMMENT = "background"  # header line ``comment background R G B``


def write_ply(path: str | Path, g: Gaussians, normals: bool = True,
              background: tuple[float, float, float] | None = None) -> None:
    """Write Gaussians as a 3DGS PLY (binary little endian, float32), atomically.

    Args:
        path: output file.
        g: Gaussians (unactivated parameters, as stored).
        normals: write ``nx ny nz`` zeros like the original 3DGS (viewers expect them).
        background: the RGB colour in [0, 1] the Gaussians are rendered on (the training
            background, learned or fixed), saved as ``comment background R G B`` and read
            back exactly by :func:`read_background`; None writes no such line.
    """
    comments: tuple[str, ...] = ()
    if background is not None:
        rgb = [float(c) for c in background]
        if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
            raise ValueError(f"{path}: background must be three values in [0, 1], got "
                             f"{list(background)}")
        comments = (" ".join([BACKGROUND_COMMENT, *map(repr, rgb)]),)
    write_element(path, gaussians_to_struct(g, normals), comments=comments)


def read_comments(path: str | Path, scene_id: str = "?") -> list[str]:
    """The ``comment`` lines of a PLY header, without the keyword, in file order."""
    path = Path(path)
    if not path.is_file():
        from freescale_core.errors import MissingInputError

        raise MissingInputError(scene_id, "PLY file is missing", path)
    _, _, end = read_header(path, scene_id)
    with open(path, "rb") as f:
        text = f.read(end).decode("ascii", errors="replace")
    return [ln[len("comment"):].strip() for ln in text.splitlines()
            if ln.split(maxsplit=1)[:1] == ["comment"]]


def read_background(path: str | Path, default: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    scene_id: str = "?") -> tuple[float, float, float]:
    """The background colour saved with the Gaussians of ``path`` (:func:`write_ply`).

    Args:
        path: a 3DGS PLY.
        default: returned when the file has no ``comment background`` line (a PLY trained
            elsewhere or written before the line existed): the configured background.

    Returns:
        ``(r, g, b)`` in [0, 1], exactly as written.

    Raises:
        PlyError: the line is there but is not three numbers in [0, 1].
    """
    for c in read_comments(path, scene_id):
        parts = c.split()
        if parts[:1] != [BACKGROUND_COMMENT]:
            continue
        try:
            rgb = tuple(float(v) for v in parts[1:])
        except ValueError:
            rgb = ()
        if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
            raise PlyError(scene_id, f"bad background line {'comment ' + c!r} in the PLY header "
                           "(expected three numbers in [0, 1])", Path(path))
        return rgb  # type: ignore[return-value]
    return tuple(float(v) for v in default)  # type: ignore[return-value]


def read_ply(path: str | Path, scene_id: str = "?") -> Gaussians:
    """Read a 3DGS PLY into :class:`Gaussians` (unactivated parameters).

    Raises:
        PlyError: a required property is missing, the f_rest count is not 3((d+1)^2 - 1), or
            the file is truncated; MissingInputError when the file does not exist.
    """
    path = Path(path)
    v = read_element(path, "vertex", scene_id)
    props = set(v.dtype.names)
    required = ["x", "y", "z", "opacity"] + [f"f_dc_{i}" for i in range(3)] \
        + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [p for p in required if p not in props]
    if missing:
        raise PlyError(scene_id, f"3DGS PLY lacks properties {missing}", path)
    rest = sorted((p for p in props if p.startswith("f_rest_")), key=lambda p: int(p[7:]))
    n_rest = len(rest)
    if rest != [f"f_rest_{i}" for i in range(n_rest)] or n_rest % 3:
        raise PlyError(scene_id, f"f_rest_* properties are not f_rest_0..f_rest_{{3m-1}} "
                       f"(found {n_rest})", path)
    k = 1 + n_rest // 3
    if int(round(np.sqrt(k))) ** 2 != k:
        raise PlyError(scene_id, f"{n_rest} f_rest values do not match an SH degree "
                       "(expected 3((d+1)^2 - 1): 0, 9, 24, 45)", path)
    n = len(v)

    def cols(names):
        return np.stack([v[c].astype(np.float32) for c in names], axis=1) if names \
            else np.zeros((n, 0), np.float32)

    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = cols([f"f_dc_{i}" for i in range(3)])
    sh[:, 1:] = np.transpose(cols(rest).reshape(n, 3, k - 1), (0, 2, 1))
    return Gaussians(
        means=cols(["x", "y", "z"]),
        log_scales=cols([f"scale_{i}" for i in range(3)]),
        quats_wxyz=cols([f"rot_{i}" for i in range(4)]),
        opacity_logits=v["opacity"].astype(np.float32),
        sh=sh,
    )


# --------------------------------------------------------------------------- points
def read_ply_points(path: str | Path, scene_id: str = "?") -> tuple[np.ndarray, np.ndarray]:
    """Point cloud PLY to ``(xyz [P, 3] float64, rgb [P, 3] uint8)``.

    Colours come from ``red green blue`` (uchar, or float in [0, 1]); grey 128 if absent.
    """
    v = read_element(path, "vertex", scene_id)
    props = v.dtype.names
    for c in ("x", "y", "z"):
        if c not in props:
            raise PlyError(scene_id, f"point PLY lacks property {c!r}", path)
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    if all(c in props for c in ("red", "green", "blue")):
        rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
        if rgb.dtype.kind == "f":
            rgb = np.round(np.clip(rgb, 0, 1) * 255)
        rgb = rgb.astype(np.uint8)
    else:
        rgb = np.full((len(v), 3), 128, np.uint8)
    return xyz, rgb


def write_ply_points(path: str | Path, xyz: np.ndarray, rgb: np.ndarray,
                     ascii: bool = False) -> None:
    """Write a point cloud ``xyz [P, 3]`` (float32) with ``rgb [P, 3]`` (uchar) colours."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rgb = np.asarray(rgb, dtype=np.uint8)
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                   ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    data = np.zeros(len(xyz), dt)
    for j, c in enumerate("xyz"):
        data[c] = xyz[:, j]
    for j, c in enumerate(("red", "green", "blue")):
        data[c] = rgb[:, j]
    write_element(path, data, ascii=ascii)
