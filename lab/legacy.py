"""The old trainer's switches as plug-ins of today's loop (``python -m lab.recon_compare``).

Three things only the legacy arms (``lab/arms/old.json``, ``old-fast.json``) change are not
fields of the product's ``ReconConfig``; a frozen dump keeps them beside its ``ReconConfig``
fields and :func:`split` takes them out. :func:`plugins` turns them into the ``strategy``,
``photometric`` and ``rasterizer`` arguments of ``freescale_core.recon.trainer.train`` /
``reconstruct``:

* ``mcmc_scale_invariant=false``: the MCMC position noise and scale regulariser in world
  units (before issue 17; far scenes threw Gaussians out), :class:`WorldUnitsMCMC`;
* ``raster_exact_tiles=false``: the cpu rasterizer's bounding-box binning (same images, more
  tile pairs);
* ``ssim_impl="torch"``: the SSIM loss by ``F.conv2d`` blurs and autograd (before the fused
  kernels; same value, slower).

Today's values (``SWITCHES``) need no plug-in. ``budget_clock`` (in every dump, ``"wall"``)
left the schema too: the clock is an argument of the trainer (``clock=``), which the harness
sets (``--cpu-minutes``: the CPU clock); :func:`split` drops it.
"""

from __future__ import annotations

import functools
from typing import Any

from freescale_core.recon.losses import masked_photometric_loss
from freescale_core.recon.strategy import MCMCStrategy

# switch -> today's value (what the product's trainer always does)
SWITCHES: dict[str, Any] = {"mcmc_scale_invariant": True, "raster_exact_tiles": True,
                            "ssim_impl": "fused"}
# keys of old dumps that are call arguments now (set by the harness, not by the arm)
HARNESS_KEYS = ("budget_clock",)
_CHOICES = {"mcmc_scale_invariant": (True, False), "raster_exact_tiles": (True, False),
            "ssim_impl": ("fused", "torch")}


def split(fields: dict) -> tuple[dict, dict]:
    """``fields`` -> (the ``ReconConfig`` fields, the legacy switches that differ from today's).
    Raises ``ValueError`` for a switch value the old trainer did not have."""
    recon = {k: v for k, v in fields.items() if k not in SWITCHES and k not in HARNESS_KEYS}
    switches = {}
    for k in SWITCHES:
        if k in fields:
            v = fields[k]
            if v not in _CHOICES[k] or type(v) is not type(SWITCHES[k]):
                raise ValueError(f"{k}={v!r}: expected one of {list(_CHOICES[k])}")
            if v != SWITCHES[k]:
                switches[k] = v
    return recon, switches


class WorldUnitsMCMC(MCMCStrategy):
    """3DGS-MCMC with its constants in world units (the trainer before issue 17)."""

    def _unit(self, state: Any) -> float:
        return 1.0


def _torch_ssim_loss(rgb, target, mask, lambda_ssim):
    return masked_photometric_loss(rgb, target, mask, lambda_ssim, "torch")


def plugins(cfg, switches: dict) -> dict:
    """The ``train`` / ``reconstruct`` keyword arguments that make today's loop run ``cfg`` with
    the legacy ``switches`` (``{}``: none, today's trainer)."""
    out: dict = {}
    if switches.get("mcmc_scale_invariant") is False and cfg.densify == "mcmc":
        out["strategy"] = WorldUnitsMCMC(cfg)
    if switches.get("ssim_impl") == "torch":
        out["photometric"] = _torch_ssim_loss
    if switches.get("raster_exact_tiles") is False:
        from freescale_core.raster import rasterize

        out["rasterizer"] = functools.partial(rasterize, exact_tiles=False)
    return out
