"""Decoder-only LVSM (Large View Synthesis Model, Jin et al., ICLR 2025) in plain torch.

Conventions:

* Cameras are ``world_from_cam`` 4x4 matrices (OpenCV: x right, y down, z forward), i.e. a
  camera-frame point ``x_c`` maps to ``x_w = R x_c + t``; ``t`` is the camera centre in world.
* Intrinsics are ``fxfycxcy`` in pixels of the image the model sees; pixel ``(u, v)`` (column,
  row) covers ``[u, u+1) x [v, v+1)``, so its centre is ``(u + 0.5, v + 0.5)``.
* Images are float RGB in [0, 1], ``[B, V, 3, H, W]``.

The model: every view becomes ``(H/p)(W/p)`` patch tokens. Input views carry their Plücker rays
and RGB (mapped to [-1, 1]); target views carry only their Plücker rays. Each target is decoded
independently: its sequence is ``[all input tokens ; the target's tokens]`` with full
self-attention (targets are folded into the batch), and the target's output tokens are mapped
back to pixels. There is no positional embedding: the rays say where every patch looks.

The same code runs on CUDA; the caller picks the device (``model.to(device)``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from schemas.lvsm import LVSMModelConfig

__all__ = ["plucker_rays", "normalize_poses", "attention_reference", "attention", "patchify",
           "unpatchify", "Block", "LVSM", "loss", "psnr"]


# --------------------------------------------------------------------------- geometry

def plucker_rays(world_from_cam: torch.Tensor, fxfycxcy: torch.Tensor, H: int,
                 W: int) -> torch.Tensor:
    """Per-pixel Plücker coordinates (d, o x d) of the rays through the pixel centres.

    Args:
        world_from_cam: ``[B, V, 4, 4]`` camera-to-world (OpenCV convention).
        fxfycxcy: ``[B, V, 4]`` focal lengths and principal point, pixels.
        H, W: image height and width, pixels.

    Returns:
        ``[B, V, 6, H, W]``: channels 0-2 the unit ray direction d in world, channels 3-5 the
        moment o x d with o the camera centre in world (scene units).
    """
    dtype, device = world_from_cam.dtype, world_from_cam.device
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype, device=device) + 0.5,
                          torch.arange(W, dtype=dtype, device=device) + 0.5,
                          indexing="ij")  # [H, W] each
    fx, fy, cx, cy = (c[..., None, None] for c in fxfycxcy.to(dtype).unbind(-1))  # [B, V, 1, 1]
    x = (u - cx) / fx  # [B, V, H, W]
    y = (v - cy) / fy  # [B, V, H, W]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [B, V, H, W, 3]
    R = world_from_cam[..., :3, :3]  # [B, V, 3, 3]
    o = world_from_cam[..., :3, 3]  # [B, V, 3]
    d = torch.einsum("bvij,bvhwj->bvhwi", R, d_cam)  # [B, V, H, W, 3]
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)  # [B, V, H, W, 3]
    m = torch.cross(o[:, :, None, None, :].expand_as(d), d, dim=-1)  # [B, V, H, W, 3]
    return torch.cat([d, m], dim=-1).permute(0, 1, 4, 2, 3)  # [B, V, 6, H, W]


def _unit(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """``x / |x|`` over the last axis (zero stays zero)."""
    return x / torch.linalg.vector_norm(x, dim=-1, keepdim=True).clamp_min(eps)


def normalize_poses(world_from_cam: torch.Tensor, n_input: int,
                    eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """Express every sample's cameras in a frame fixed by its first ``n_input`` (input) cameras.

    Per sample (as LVSM does): the new origin is the mean input camera centre; the new axes are
    the mean input orientation (z = mean input forward axis, x = mean input down axis crossed
    with z, y = z x x, Gram-Schmidt); distances are scaled so the farthest input camera lies at
    distance 1 from the origin (scale 1 when all input centres coincide). The map is a
    similarity, so any translation, rotation or scaling of the whole scene leaves the result
    unchanged (up to rounding). When the mean forward axis vanishes (inputs facing opposite
    ways) or is parallel to the mean down axis, the rotation falls back to the identity.

    Args:
        world_from_cam: ``[B, V, 4, 4]`` camera-to-world; views ``:n_input`` are the inputs.
        n_input: number of leading input views (>= 1).
        eps: degeneracy threshold (scene units / unit vectors).

    Returns:
        ``([B, V, 4, 4], scale [B])``: the normalised camera-to-world matrices and the factor
        applied to distances (normalised = scale * (R_mean^T (x_world - centre))).
    """
    T = world_from_cam  # [B, V, 4, 4]
    R = T[..., :3, :3]  # [B, V, 3, 3]
    t = T[..., :3, 3]  # [B, V, 3]
    centre = t[:, :n_input].mean(dim=1)  # [B, 3]
    z = R[:, :n_input, :, 2].mean(dim=1)  # [B, 3] mean forward axis in world
    down = R[:, :n_input, :, 1].mean(dim=1)  # [B, 3] mean down axis in world
    x = torch.cross(down, z, dim=-1)  # [B, 3]
    ok = ((torch.linalg.vector_norm(z, dim=-1) > eps)
          & (torch.linalg.vector_norm(x, dim=-1) > eps))  # [B]
    z, x = _unit(z), _unit(x)  # [B, 3] each
    y = torch.cross(z, x, dim=-1)  # [B, 3]
    R_mean = torch.stack([x, y, z], dim=-1)  # [B, 3, 3] columns = new axes in world
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(R_mean)  # [B, 3, 3]
    R_mean = torch.where(ok[:, None, None], R_mean, eye)  # [B, 3, 3]

    dist = torch.linalg.vector_norm(t[:, :n_input] - centre[:, None], dim=-1)  # [B, n_input]
    far = dist.max(dim=1).values  # [B]
    scale = torch.where(far > eps, 1.0 / far.clamp_min(eps), torch.ones_like(far))  # [B]

    R_new = R_mean.transpose(-1, -2)[:, None] @ R  # [B, V, 3, 3]
    t_new = torch.einsum("bji,bvj->bvi", R_mean, t - centre[:, None])  # [B, V, 3] = R_mean^T(..)
    t_new = t_new * scale[:, None, None]  # [B, V, 3]
    out = torch.zeros_like(T)  # [B, V, 4, 4]
    out[..., :3, :3] = R_new
    out[..., :3, 3] = t_new
    out[..., 3, 3] = 1.0
    return out, scale


# --------------------------------------------------------------------------- tokens

def patchify(x: torch.Tensor, p: int) -> torch.Tensor:
    """``[N, C, H, W]`` -> ``[N, (H/p)(W/p), C p p]`` (row-major patches, channel-major inside)."""
    N, C, H, W = x.shape
    h, w = H // p, W // p
    x = x.reshape(N, C, h, p, w, p)  # [N, C, h, p, w, p]
    return x.permute(0, 2, 4, 1, 3, 5).reshape(N, h * w, C * p * p)  # [N, h w, C p p]


def unpatchify(tokens: torch.Tensor, p: int, C: int, H: int, W: int) -> torch.Tensor:
    """Inverse of :func:`patchify`: ``[N, (H/p)(W/p), C p p]`` -> ``[N, C, H, W]``."""
    N = tokens.shape[0]
    h, w = H // p, W // p
    x = tokens.reshape(N, h, w, C, p, p)  # [N, h, w, C, p, p]
    return x.permute(0, 3, 1, 4, 2, 5).reshape(N, C, H, W)  # [N, C, H, W]


# --------------------------------------------------------------------------- attention

def attention_reference(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Obvious attention ``softmax(q k^T / sqrt(d)) v`` (slow; the oracle for tests).

    Args:
        q, k, v: ``[N, heads, L, d]``.

    Returns:
        ``[N, heads, L, d]``.
    """
    scores = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])  # [N, heads, L, L]
    return torch.softmax(scores, dim=-1) @ v  # [N, heads, L, d]


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
              impl: str = "sdpa") -> torch.Tensor:
    """Full (non-causal) attention, ``[N, heads, L, d]`` x3 -> ``[N, heads, L, d]``.

    ``impl``: "sdpa" (``F.scaled_dot_product_attention``: fused kernels on CPU / CUDA) or
    "reference" (:func:`attention_reference`).
    """
    if impl == "sdpa":
        return F.scaled_dot_product_attention(q, k, v)  # [N, heads, L, d]
    if impl == "reference":
        return attention_reference(q, k, v)  # [N, heads, L, d]
    raise ValueError(f"unknown attention impl {impl!r}")


class Block(nn.Module):
    """Pre-LN transformer block with per-head QK normalisation.

    ``x + proj(attn(qk_norm(q), qk_norm(k), v))`` with q, k, v from ``LayerNorm(x)``, then
    ``x + MLP(LayerNorm(x))`` (GELU, hidden ``mlp_ratio * d``).
    """

    def __init__(self, d: int, n_heads: int, mlp_ratio: float = 4.0,
                 qk_norm: str = "layernorm", attention_impl: str = "sdpa",
                 eps: float = 1e-5) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.head_dim = d // n_heads
        self.attention_impl = attention_impl  # "sdpa" | "reference"; may be changed at run time
        self.norm1 = nn.LayerNorm(d, eps=eps)
        self.qkv = nn.Linear(d, 3 * d, bias=False)
        norm = {"layernorm": nn.LayerNorm, "rmsnorm": nn.RMSNorm}[qk_norm]
        self.q_norm = norm(self.head_dim, eps=eps)
        self.k_norm = norm(self.head_dim, eps=eps)
        self.proj = nn.Linear(d, d)
        self.norm2 = nn.LayerNorm(d, eps=eps)
        hidden = int(round(mlp_ratio * d))
        self.mlp = nn.Sequential(nn.Linear(d, hidden), nn.GELU(), nn.Linear(hidden, d))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[N, L, d]`` -> ``[N, L, d]``."""
        N, L, d = x.shape
        qkv = self.qkv(self.norm1(x))  # [N, L, 3 d]
        q, k, v = qkv.reshape(N, L, 3, self.n_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k = self.q_norm(q), self.k_norm(k)  # [N, heads, L, head_dim] each (v too)
        a = attention(q, k, v, self.attention_impl)  # [N, heads, L, head_dim]
        x = x + self.proj(a.transpose(1, 2).reshape(N, L, d))  # [N, L, d]
        return x + self.mlp(self.norm2(x))  # [N, L, d]


# --------------------------------------------------------------------------- model

class LVSM(nn.Module):
    """Decoder-only LVSM: input views + target cameras -> target images.

    Args:
        config: model size and options (default: ``LVSMModelConfig()`` = the "cpu" preset).
        **overrides: config fields to override (``LVSM(d_model=8, n_layers=1)``).
    """

    def __init__(self, config: LVSMModelConfig | None = None, **overrides) -> None:
        super().__init__()
        cfg = config or LVSMModelConfig()
        if overrides:
            cfg = cfg.model_copy(update=overrides)
            cfg = LVSMModelConfig.model_validate(cfg.model_dump())
        self.config = cfg
        d, p = cfg.d_model, cfg.patch_size
        self.input_embed = nn.Linear((6 + 3) * p * p, d)
        self.target_embed = nn.Linear(6 * p * p, d)
        self.blocks = nn.ModuleList(
            Block(d, cfg.n_heads, cfg.mlp_ratio, cfg.qk_norm, cfg.attention, cfg.norm_eps)
            for _ in range(cfg.n_layers))
        self.norm_out = nn.LayerNorm(d, eps=cfg.norm_eps)
        self.head = nn.Linear(d, 3 * p * p)
        self.apply(self._init)

    def _init(self, m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=self.config.init_std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)

    def set_attention(self, impl: str) -> None:
        """Switch every block between "sdpa" and "reference" attention."""
        for b in self.blocks:
            b.attention_impl = impl

    def forward(self, images: torch.Tensor, input_world_from_cam: torch.Tensor,
                input_fxfycxcy: torch.Tensor, target_world_from_cam: torch.Tensor,
                target_fxfycxcy: torch.Tensor) -> torch.Tensor:
        """Render the target views.

        Args:
            images: ``[B, Vi, 3, H, W]`` input RGB in [0, 1]; H, W divisible by patch_size.
            input_world_from_cam: ``[B, Vi, 4, 4]`` input camera-to-world (OpenCV); float64
                poses keep their precision through the normalisation (large world offsets).
            input_fxfycxcy: ``[B, Vi, 4]`` input intrinsics, pixels of ``images``.
            target_world_from_cam: ``[B, Vt, 4, 4]`` target camera-to-world (same world).
            target_fxfycxcy: ``[B, Vt, 4]`` target intrinsics, pixels of an ``H x W`` image.

        Returns:
            ``[B, Vt, 3, H, W]`` predicted target RGB in (0, 1).
        """
        B, Vi, _, H, W = images.shape
        Vt = target_world_from_cam.shape[1]
        p, d = self.config.patch_size, self.config.d_model
        if H % p or W % p:
            raise ValueError(f"image size {H}x{W} is not divisible by patch_size={p}")
        dtype = images.dtype
        # geometry in the cameras' precision (at least float32), tokens in the images' dtype
        geo = torch.promote_types(input_world_from_cam.dtype, torch.float32)
        poses = torch.cat([input_world_from_cam, target_world_from_cam], 1).to(geo)
        # poses: [B, Vi + Vt, 4, 4]
        if self.config.normalize_poses:
            poses, _ = normalize_poses(poses, Vi)  # [B, Vi + Vt, 4, 4]
        K = torch.cat([input_fxfycxcy, target_fxfycxcy], 1).to(geo)  # [B, Vi + Vt, 4]
        rays = plucker_rays(poses, K, H, W).to(dtype)  # [B, Vi + Vt, 6, H, W]

        x_in = torch.cat([rays[:, :Vi], images * 2.0 - 1.0], dim=2)  # [B, Vi, 9, H, W]
        tok_in = self.input_embed(patchify(x_in.flatten(0, 1), p))  # [B Vi, n, d]
        n = tok_in.shape[1]
        tok_in = tok_in.reshape(B, 1, Vi * n, d).expand(B, Vt, Vi * n, d)  # [B, Vt, Vi n, d]
        tok_tg = self.target_embed(patchify(rays[:, Vi:].flatten(0, 1), p))  # [B Vt, n, d]
        x = torch.cat([tok_in.reshape(B * Vt, Vi * n, d), tok_tg], dim=1)  # [B Vt, (Vi+1) n, d]
        for block in self.blocks:
            x = block(x)  # [B Vt, (Vi+1) n, d]
        out = self.head(self.norm_out(x[:, Vi * n:]))  # [B Vt, n, 3 p p]
        img = unpatchify(out, p, 3, H, W)  # [B Vt, 3, H, W]
        return torch.sigmoid(img).reshape(B, Vt, 3, H, W)  # [B, Vt, 3, H, W]


# --------------------------------------------------------------------------- metrics

def loss(pred: torch.Tensor, target: torch.Tensor,
         weight: torch.Tensor | None = None,
         pixel_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted mean of per-view MSE.

    Args:
        pred, target: ``[B, Vt, 3, H, W]`` in [0, 1].
        weight: ``[B, Vt]`` per-target weights (e.g. ``Sample.target_weight``: 1 for captured
            targets, ``novel_target_weight`` for free views); None = all 1.
        pixel_weight: ``[B, Vt, H, W]`` per-pixel weights in [0, 1] (e.g. the fixer's
            confidence; 1 for photos); a view's MSE is then ``mean(c * (pred - target)^2)``,
            so a pixel of confidence 0 teaches nothing and a view of confidence 1 everywhere
            counts as without it. None = all 1.

    Returns:
        Scalar ``sum(w * mse) / sum(w)`` (0 when every weight is 0).
    """
    se = (pred - target).square()
    if pixel_weight is not None:
        se = se * pixel_weight.to(se).unsqueeze(2)
    mse = se.flatten(2).mean(dim=2)  # [B, Vt]
    if weight is None:
        return mse.mean()
    w = weight.to(mse)  # [B, Vt]
    return (w * mse).sum() / w.sum().clamp_min(1e-12)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-view PSNR in dB for images in [0, 1]: ``[B, Vt, 3, H, W]`` x2 -> ``[B, Vt]``."""
    mse = (pred - target).square().flatten(2).mean(dim=2)  # [B, Vt]
    return -10.0 * torch.log10(mse.clamp_min(1e-10))  # [B, Vt]
