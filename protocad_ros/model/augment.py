"""Image augmentation for the two views of ProtoCAD (pure PyTorch, no ROS imports).

Paper, sec. 4.1: "Following DreamerPro, we perform bilinear interpolation of the random shifts
and ensure consistency of the augmentation across time steps."  DreamerPro (DMC) shifts by up
to +-3 px with nearest ("replicate") fill.  Here:

    1. pad every frame by `pad` px, replicating the border pixels;
    2. draw ONE continuous shift (dx, dy) ~ U[-pad, pad]^2 per sequence;
    3. resample the original H x W window moved by (dx, dy) with bilinear interpolation
       (grid_sample, align_corners=False), at every time step of that sequence.

The shift is held over time because ProtoCAD's TC-SwAV loss compares the first and second half
of a sequence: a shift that changed over time would be a nuisance the context must ignore,
while a per-sequence shift is a spatial perturbation both halves share.  The shift is
continuous (not integer pixels) so the views also differ by sub-pixel interpolation, as with
DreamerPro's bilinear translation.

Layout convention: channels-first float images, (B, T, C, H, W) (or (B, C, H, W) single frames,
treated as T = 1).  Convert uint8 (B, T, H, W, C) replay images first, e.g.
`images.permute(0, 1, 4, 2, 3).float() / 255 - 0.5`; the shift commutes with any per-pixel
affine scaling, so it does not matter whether you scale before or after.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["random_shift", "shift_images", "sample_shifts", "random_crop", "crop_images"]


def sample_shifts(batch_size: int, pad: int = 3, generator: torch.Generator | None = None,
                  device: torch.device | str | None = None) -> torch.Tensor:
    """One continuous shift per sequence: (B, 2) float32 pixels (dx, dy) ~ U[-pad, pad].

    Drawn on the generator's device (a CPU generator cannot fill a CUDA tensor) and then moved
    to `device`, so a CPU generator gives the same shifts whatever device the images are on.
    """
    gen_device = generator.device if generator is not None else device
    u = torch.rand((batch_size, 2), generator=generator, device=gen_device)  # (B, 2) in [0, 1)
    return ((2.0 * u - 1.0) * pad).to(device=device)


def shift_images(images: torch.Tensor, shifts: torch.Tensor, pad: int = 3) -> torch.Tensor:
    """Translate each sequence by its own (dx, dy) pixels with replicate fill + bilinear.

    images: (B, T, C, H, W) or (B, C, H, W) float.  shifts: (B, 2) pixels, |shift| <= pad;
    output pixel (y, x) of sequence b takes the value at (y + dy_b, x + dx_b) of the input
    (positive dx looks further right, i.e. the content moves left).  Zero shift is the identity
    and a half-pixel shift averages neighbouring pixels (bilinear).
    """
    if not torch.is_floating_point(images):
        raise TypeError(f"shift_images expects float images (B,T,C,H,W), got {images.dtype}; "
                        "convert uint8 frames with .float() first")
    single = images.dim() == 4
    if single:
        images = images.unsqueeze(1)
    if images.dim() != 5:
        raise ValueError(f"expected images (B,T,C,H,W) or (B,C,H,W), got {tuple(images.shape)}")
    B, T, C, H, W = images.shape
    if shifts.shape != (B, 2):
        raise ValueError(f"expected shifts (B,2)=({B},2), got {tuple(shifts.shape)}")
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    if shifts.numel() and shifts.abs().max().item() > pad + 1e-6:
        raise ValueError(f"|shift| must be <= pad={pad}, got max {shifts.abs().max().item()}")

    x = images.reshape(B * T, C, H, W)
    if pad > 0:
        x = F.pad(x, (pad, pad, pad, pad), mode="replicate")  # (B*T, C, H+2p, W+2p)
    Hp, Wp = H + 2 * pad, W + 2 * pad

    # Sampling location of output pixel j in padded pixel coordinates: j + pad + shift.
    # align_corners=False maps pixel centre i of a size-n axis to (2i + 1)/n - 1 in [-1, 1].
    dtype, device = images.dtype, images.device
    shifts = shifts.to(device=device, dtype=dtype)
    xs = torch.arange(W, device=device, dtype=dtype) + pad  # (W,)
    ys = torch.arange(H, device=device, dtype=dtype) + pad  # (H,)
    gx = (2.0 * (xs[None, :] + shifts[:, 0:1]) + 1.0) / Wp - 1.0  # (B, W)
    gy = (2.0 * (ys[None, :] + shifts[:, 1:2]) + 1.0) / Hp - 1.0  # (B, H)
    grid = torch.stack([gx[:, None, :].expand(B, H, W),  # grid[..., 0] = x (width)
                        gy[:, :, None].expand(B, H, W)], dim=-1)  # (B, H, W, 2)
    # Same grid for all T steps of a sequence: repeat per time step (B*T, H, W, 2).
    grid = grid[:, None].expand(B, T, H, W, 2).reshape(B * T, H, W, 2)
    # padding_mode="border" only guards float round-off at |shift| == pad; the replicate pad
    # already holds every location we sample.
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
    out = out.reshape(B, T, C, H, W)
    return out[:, 0] if single else out


def random_shift(images: torch.Tensor, pad: int = 3,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """DreamerPro-style augmentation: one random continuous shift per sequence, held over time.

    images: (B, T, C, H, W) float, channels first (or (B, C, H, W)).  Returns the same shape.
    Deterministic given `generator` (a torch.Generator; CPU or on the images' device).
    Call it twice on the same batch to get ProtoCAD's two views o^(1), o^(2).
    """
    shifts = sample_shifts(images.shape[0], pad, generator, images.device)  # (B, 2)
    return shift_images(images, shifts, pad)


def random_crop(images: torch.Tensor, pad: int = 4,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ's augmentation: replicate-pad by `pad` px, then crop the original size back at an
    integer offset drawn per sample, (ox, oy) ~ U{0, ..., 2 pad}^2 (nn.ReplicationPad2d +
    kornia RandomCrop in denisyarats/drq).  Unlike random_shift, every image of the batch gets
    its own offset: DrQ's observations are single frame stacks, not sequences.

    images: (N, C, H, W) float.  Deterministic given `generator` (CPU or the images' device).
    """
    if images.dim() != 4 or not torch.is_floating_point(images):
        raise ValueError(f"random_crop expects float (N, C, H, W), got {images.dtype} "
                         f"{tuple(images.shape)}")
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    if pad == 0:
        return images
    gen_device = generator.device if generator is not None else images.device
    offsets = torch.randint(0, 2 * pad + 1, (images.shape[0], 2), generator=generator,
                            device=gen_device).to(images.device)
    return crop_images(F.pad(images, (pad, pad, pad, pad), mode="replicate"), offsets,
                       images.shape[-2], images.shape[-1])


def crop_images(padded: torch.Tensor, offsets: torch.Tensor, height: int,
                width: int) -> torch.Tensor:
    """out[n, :, y, x] = padded[n, :, oy_n + y, ox_n + x] for offsets (N, 2) = (ox, oy)."""
    N = padded.shape[0]
    dev = padded.device
    rows = offsets[:, 1:2] + torch.arange(height, device=dev)   # (N, H)
    cols = offsets[:, 0:1] + torch.arange(width, device=dev)    # (N, W)
    n = torch.arange(N, device=dev)[:, None, None]
    return padded.permute(0, 2, 3, 1)[n, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)
