"""Image files: reading with scene- and file-naming errors, natural name order.

A leaf module: the scene record and every reader import it, it imports neither.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from freescale_core.errors import CorruptImageError, MissingInputError


def natural_key(name: str) -> tuple:
    """Sort key that orders ``img2`` before ``img10`` (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), p) if p.isdigit() else (1, 0, p.lower()) for p in parts)


def natural_order(names: list[str]) -> np.ndarray:
    """``[N]`` indices that sort ``names`` naturally (stable)."""
    keys = [natural_key(n) for n in names]
    return np.array(sorted(range(len(names)), key=lambda i: keys[i]), dtype=np.int64)


def _decode(path: Path, scene_id: str, what: str, flags: int) -> tuple[np.ndarray, np.ndarray]:
    """The file's bytes and ``cv2.imdecode(bytes, flags)``; a missing or undecodable file is an
    error naming the scene and the file (``what``: "image" or "mask")."""
    import cv2

    if not path.is_file():
        raise MissingInputError(scene_id, f"{what} file is missing", path)
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise CorruptImageError(scene_id, f"{what} cannot be decoded (corrupt or not an image)",
                                path)
    return data, img


def read_rgb(path: str | Path, scene_id: str = "?") -> np.ndarray:
    """Read an image file as ``[H, W, 3]`` uint8 RGB, with scene- and file-naming errors."""
    import cv2

    path = Path(path)
    data, img = _decode(path, scene_id, "image", cv2.IMREAD_COLOR)
    # cv2 decodes truncated JPEGs with a warning and a grey tail; check the end marker.
    if path.suffix.lower() in (".jpg", ".jpeg") and not data[-2:].tobytes() == b"\xff\xd9":
        tail = data[-64:].tobytes()
        if b"\xff\xd9" not in tail:
            raise CorruptImageError(scene_id, "JPEG is truncated (no end-of-image marker)", path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_mask(path: str | Path, scene_id: str = "?") -> np.ndarray:
    """Read an object mask as ``[H, W]`` bool: nonzero = object (keep), zero = ignore.

    Masks are single-channel (nerfstudio, COLMAP), 8 or 16 bit; a colour mask keeps a pixel
    where any colour channel is nonzero (an alpha channel is not read). Errors name the scene
    and the file."""
    import cv2

    _, m = _decode(Path(path), scene_id, "mask", cv2.IMREAD_UNCHANGED)
    if m.ndim == 3:
        m = m[..., :3].max(axis=-1)
    return m > 0


def resize_area(img: np.ndarray, w: int, h: int) -> np.ndarray:
    """``img`` ``[H, W, C]`` resized to ``[h, w, C]`` by area averaging (OpenCV ``INTER_AREA``);
    returned unchanged when it already has that size. The one resize rule of training images
    (recon, refinement, the PLY alignment check)."""
    import cv2

    if img.shape[1] == w and img.shape[0] == h:
        return img
    return cv2.resize(img, (int(w), int(h)), interpolation=cv2.INTER_AREA)


def psnr_u8(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 images of one shape (peak 255); ``inf`` when equal."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))
