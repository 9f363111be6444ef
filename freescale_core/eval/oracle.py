"""The sample scene's exact renderer (defined in :mod:`freescale_core.scene.oracle`, the layer
below every user; re-exported here under its old name)."""

from __future__ import annotations

from freescale_core.scene.oracle import ground_truth_oracle

__all__ = ["ground_truth_oracle"]
