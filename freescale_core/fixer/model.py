"""The fixer network: a small residual U-Net in plain torch (CPU first).

Input ``x [B, 4 + 4k, H, W]`` (:func:`freescale_core.fixer.data.model_input`: render RGB,
alpha, then per warped photo its RGB and weight). Output:

* ``fixed [B, 3, H, W]`` = ``clamp(render + residual, 0, 1)``: the corrected image;
* ``conf [B, 1, H, W]`` = ``sigmoid(logit)`` in (0, 1): how likely the corrected pixel is
  right (trained to predict ``exp(-|error| / tau)``, see :mod:`freescale_core.fixer.train`).

The head is zero-initialised, so at init ``fixed == render`` exactly (residual 0) and
``conf == 0.5``: an untrained fixer changes nothing. Sizes not divisible by
``2**(levels - 1)`` are reflect-padded and cropped back.

Layout: stem conv -> per level ``blocks`` residual blocks (conv-ReLU-conv + skip), a stride-2
conv to the next level (channels doubled) -> bottleneck -> per level nearest upsample + conv,
*added* to the skip (cheaper than concatenation), ``blocks`` residual blocks -> 3x3 head.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from schemas.fixer import FixerModelConfig

__all__ = ["FixerNet", "FixerCheckpointError", "load_fixer", "CHECKPOINT_FORMAT", "n_params"]

CHECKPOINT_FORMAT = "freescale-fixer/1"
RENDER_LOGIT = 4.0  # blend head at init: the render's weight is e^4 / (e^4 + k) (0.96 at k=2)


class FixerCheckpointError(ValueError):
    """A fixer checkpoint that is missing, not a fixer checkpoint, or does not fit."""


def _norm(c: int, kind: str) -> nn.Module:
    return nn.GroupNorm(min(4, c), c) if kind == "group" else nn.Identity()


class _ResBlock(nn.Module):
    def __init__(self, c: int, norm: str):
        super().__init__()
        self.c1 = nn.Conv2d(c, c, 3, padding=1)
        self.n1 = _norm(c, norm)
        self.c2 = nn.Conv2d(c, c, 3, padding=1)
        self.n2 = _norm(c, norm)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.n1(self.c1(x)), inplace=True)
        return F.relu(x + self.n2(self.c2(h)), inplace=True)


class FixerNet(nn.Module):
    """Residual U-Net ``[B, 4+4k, H, W] -> (fixed [B, 3, H, W], conf [B, 1, H, W])``."""

    def __init__(self, cfg: FixerModelConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or FixerModelConfig()
        ch = [cfg.base_channels * 2 ** i for i in range(cfg.levels)]
        u = cfg.unshuffle
        self.stem = nn.Conv2d(cfg.in_channels * u * u, ch[0], 3, padding=1)
        self.enc = nn.ModuleList(
            nn.Sequential(*[_ResBlock(ch[i], cfg.norm) for _ in range(cfg.blocks)])
            for i in range(cfg.levels - 1))
        self.down = nn.ModuleList(nn.Conv2d(ch[i], ch[i + 1], 3, stride=2, padding=1)
                                  for i in range(cfg.levels - 1))
        self.mid = nn.Sequential(*[_ResBlock(ch[-1], cfg.norm) for _ in range(cfg.blocks)])
        self.up = nn.ModuleList(nn.Conv2d(ch[i + 1], ch[i], 3, padding=1)
                                for i in range(cfg.levels - 1))
        self.dec = nn.ModuleList(
            nn.Sequential(*[_ResBlock(ch[i], cfg.norm) for _ in range(cfg.blocks)])
            for i in range(cfg.levels - 1))
        self.n_out = 4 + (cfg.k + 1 if cfg.head == "blend" else 0)
        self.head = nn.Conv2d(ch[0], self.n_out * u * u, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        if cfg.head == "blend":  # start on the render: its logit RENDER_LOGIT above the warps'
            with torch.no_grad():
                self.head.bias.view(self.n_out, u * u)[4] = RENDER_LOGIT

    @property
    def multiple(self) -> int:
        """Input sides are padded to a multiple of this."""
        return self.cfg.unshuffle * 2 ** (self.cfg.levels - 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, C, H, W = x.shape
        if C != self.cfg.in_channels:
            raise ValueError(f"fixer: input has {C} channels, the model expects "
                             f"{self.cfg.in_channels} (k={self.cfg.k})")
        m = self.multiple
        ph, pw = (-H) % m, (-W) % m
        if ph or pw:
            mode = "reflect" if ph < H and pw < W else "replicate"
            x = F.pad(x, (0, pw, 0, ph), mode=mode)
        render = x[:, :3]
        u = self.cfg.unshuffle
        h = F.relu(self.stem(F.pixel_unshuffle(x, u) if u > 1 else x), inplace=True)
        skips = []
        for enc, down in zip(self.enc, self.down):
            h = enc(h)
            skips.append(h)
            h = F.relu(down(h), inplace=True)
        h = self.mid(h)
        for i in reversed(range(len(self.up))):
            h = F.interpolate(h, scale_factor=2.0, mode="nearest")
            h = self.dec[i](F.relu(self.up[i](h), inplace=True) + skips[i])
        out = self.head(h)
        if u > 1:
            out = F.pixel_shuffle(out, u)
        if self.cfg.head == "blend":
            k = self.cfg.k
            srcs = [render] + [x[:, 4 + 4 * i:7 + 4 * i] for i in range(k)]
            logit = out[:, 4:5 + k].clone()
            for i in range(k):
                w = x[:, 7 + 4 * i:8 + 4 * i]
                logit[:, 1 + i:2 + i] = torch.where(
                    w > 0, logit[:, 1 + i:2 + i] + torch.log(w.clamp_min(1e-4)),
                    torch.full_like(w, -1e4))
            a = torch.softmax(logit, dim=1)
            base = sum(a[:, i:i + 1] * srcs[i] for i in range(k + 1))
            fixed = (base + out[:, :3]).clamp(0.0, 1.0)
        else:
            fixed = (render + out[:, :3]).clamp(0.0, 1.0)
        conf = torch.sigmoid(out[:, 3:4])
        return fixed[:, :, :H, :W], conf[:, :, :H, :W]


def n_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def load_fixer(path: str | Path, k: int | None = None, map_location: str = "cpu"
               ) -> tuple[FixerNet, dict]:
    """A trained fixer from ``path`` (``fixer.pt`` of :func:`freescale_core.fixer.train
    .train_fixer`), in eval mode, and its meta (config, scenes, data hash, ...).

    Raises :class:`FixerCheckpointError` (one line) for a missing file, a file that is not a
    fixer checkpoint, weights that do not fit the recorded config, or ``k`` given and not the
    checkpoint's."""
    p = Path(path)
    if not p.is_file():
        raise FixerCheckpointError(f"fixer checkpoint not found: {p}")
    try:
        st = torch.load(p, map_location=map_location, weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unreadable file is "not a checkpoint"
        raise FixerCheckpointError(f"{p} is not a fixer checkpoint (unreadable by torch: "
                                   f"{type(e).__name__})") from None
    if not isinstance(st, dict) or st.get("format") != CHECKPOINT_FORMAT:
        raise FixerCheckpointError(f"{p} is not a fixer checkpoint (no format "
                                   f"{CHECKPOINT_FORMAT!r})")
    try:
        cfg = FixerModelConfig.model_validate(st["model_config"])
    except Exception as e:  # noqa: BLE001
        raise FixerCheckpointError(f"{p}: bad model config in the checkpoint: "
                                   f"{str(e).splitlines()[0]}") from None
    if k is not None and int(k) != cfg.k:
        raise FixerCheckpointError(f"{p}: the fixer was trained with k={cfg.k} warped photos "
                                   f"({cfg.in_channels} input channels); asked for k={k} "
                                   f"({4 + 4 * int(k)} channels)")
    model = FixerNet(cfg)
    w = st.get("model", {})
    stem = w.get("stem.weight")
    u2 = cfg.unshuffle ** 2
    if stem is not None and tuple(stem.shape[:2]) != (cfg.base_channels, cfg.in_channels * u2):
        raise FixerCheckpointError(
            f"{p}: weights take {stem.shape[1] // u2} input channels, the recorded config "
            f"{cfg.in_channels} (k={cfg.k})")
    try:
        model.load_state_dict(w)
    except Exception as e:  # noqa: BLE001
        raise FixerCheckpointError(f"{p}: weights do not fit the recorded config: "
                                   f"{str(e).splitlines()[0]}") from None
    model.eval()
    meta = {kk: v for kk, v in st.items() if kk != "model"}
    return model, meta
