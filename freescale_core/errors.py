"""Typed, actionable errors raised at the engine's boundaries.

Every error that concerns input data names the scene and, where there is one, the file,
so that a failed scene in a run of thousands can be found and fixed without a debugger.
"""

from __future__ import annotations

from pathlib import Path


class FreeScaleError(Exception):
    """Base class of every error the engine raises on purpose."""


class SceneError(FreeScaleError):
    """Something is wrong with one scene's input; other scenes are unaffected.

    Args:
        scene: scene id (usually the scene folder's name).
        message: what was found and what was expected.
        path: the offending file or folder, if there is one.
    """

    def __init__(self, scene: str, message: str, path: str | Path | None = None):
        self.scene = scene
        self.path = None if path is None else str(path)
        self.reason = message
        where = f" [{self.path}]" if self.path else ""
        super().__init__(f"scene '{scene}': {message}{where}")


class MissingInputError(SceneError, FileNotFoundError):
    """A file or folder the scene needs does not exist."""


class CorruptImageError(SceneError):
    """An image exists but cannot be decoded."""


class CameraModelError(SceneError):
    """A camera model the engine cannot use (unknown, or distorted without undistortion)."""


class ImageCountMismatchError(SceneError):
    """The image folder and the camera model disagree about which images exist."""


class DegenerateSceneError(SceneError):
    """Too few registered views, no points, NaN Gaussians, a flat or empty scene box."""


class UnsafePathError(SceneError):
    """A file named by the scene's model lies outside the scene folder (``..`` or an absolute
    path): refused unless ``ingest.allow_outside_paths`` is set."""


class MaskError(SceneError):
    """Object masks that cannot be used: another size than their image, or only some images
    have one (``ingest.masks=ignore`` trains on every pixel instead)."""


class ResourceLimitError(SceneError):
    """A setting would need more memory (or time) than allowed; says the estimate."""


class ShapeError(FreeScaleError, ValueError):
    """An array has the wrong shape: says what was found and what was expected."""

    def __init__(self, name: str, actual: tuple, expected: str):
        self.name, self.actual, self.expected = name, tuple(actual), expected
        super().__init__(f"{name}: shape {tuple(actual)}, expected {expected}")


class StoreError(FreeScaleError):
    """The output store is unreadable or inconsistent."""
