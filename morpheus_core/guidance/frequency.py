"""Frequency-domain core of the method: the orthonormal 2-D DCT and the band masks Λ.

The paper writes u = Vᵀx for the DCT of an image x; here ``dct2(x)`` is that Vᵀx and
``idct2(u)`` is V u. Both act on the last two dimensions of any tensor, so a batch of latents
(B×4×64×64) or RGB renders (B×3×H×W) is transformed per channel over H×W.

Two equivalent implementations exist: a cached matrix form (two small matrix products, fastest
for latent-sized grids) and an FFT form (Makhoul's N-point reordering, O(N log N), used for
large images). Both are exact to round-off; half-precision inputs are computed in float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

DctMethod = Literal["auto", "matrix", "fft"]

# Measured (benchmarks/results/dct_speed_*.md): the matrix form is faster through 1024 px on the
# CPU and on an H200; beyond that the FFT form (O(N² log N), no N×N matrices) takes over.
MATRIX_FORM_MAX_SIDE = 1024


def _compute_dtype(x: Tensor) -> torch.dtype:
    """float64 stays float64; everything else is computed in float32."""
    if not x.is_floating_point():
        raise TypeError(f"DCT needs a floating-point tensor, got {x.dtype}")
    if x.dtype in (torch.float16, torch.bfloat16):
        return torch.float32
    return x.dtype


_MATRIX_CACHE: dict[tuple[int, torch.dtype, torch.device], Tensor] = {}


def dct_matrix(n: int, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> Tensor:
    """The n×n orthonormal DCT-II matrix C[k, j] = s_k cos(πk(2j+1)/2n), cached per size, dtype, device."""
    if n < 1:
        raise ValueError(f"DCT size must be positive, got {n}")
    key = (n, dtype, torch.device(device))
    mat = _MATRIX_CACHE.get(key)
    if mat is None:
        k = torch.arange(n, dtype=torch.float64)[:, None]
        j = torch.arange(n, dtype=torch.float64)[None, :]
        basis = torch.cos(math.pi * k * (2 * j + 1) / (2 * n)) * math.sqrt(2.0 / n)
        basis[0] /= math.sqrt(2.0)
        mat = basis.to(dtype=dtype, device=device)
        if len(_MATRIX_CACHE) > 256:
            _MATRIX_CACHE.clear()
        _MATRIX_CACHE[key] = mat
    return mat


def _matmul_dtype(x: Tensor, dtype: torch.dtype) -> torch.dtype:
    # TF32 (CUDA) or reduced-precision CPU matmul would cost ~1e-3 relative error; float64
    # products on latent-sized grids are cheap and keep the transform exact.
    if dtype == torch.float32 and (x.is_cuda or torch.get_float32_matmul_precision() != "highest"):
        return torch.float64
    return dtype


def _dct2_matrix(x: Tensor, inverse: bool) -> Tensor:
    dtype = _compute_dtype(x)
    mdtype = _matmul_dtype(x, dtype)
    h, w = x.shape[-2], x.shape[-1]
    ch = dct_matrix(h, mdtype, x.device)
    cw = dct_matrix(w, mdtype, x.device)
    xm = x.to(mdtype)
    out = ch.T @ xm @ cw if inverse else ch @ xm @ cw.T
    return out.to(dtype)


def _dct1_fft_last(x: Tensor) -> Tensor:
    """Orthonormal DCT-II along the last dim via an N-point FFT of the even/odd reordering."""
    n = x.shape[-1]
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], dim=-1)
    spec = torch.fft.fft(v, dim=-1)
    k = torch.arange(n, dtype=x.dtype, device=x.device)
    phase = torch.polar(torch.ones_like(k), -math.pi * k / (2 * n))
    out = (spec * phase).real
    scale = torch.full((n,), math.sqrt(2.0 / n), dtype=x.dtype, device=x.device)
    scale[0] = math.sqrt(1.0 / n)
    return out * scale


def _idct1_fft_last(u: Tensor) -> Tensor:
    """Inverse of ``_dct1_fft_last``.

    With W_k = e^{-iπk/2N} V_k (V the FFT of the reordered signal) the DCT is Re(W_k), and the
    Hermitian symmetry of V gives Im(W_k) = -C_{N-k}; so W, then V, then the signal follow.
    """
    n = u.shape[-1]
    scale = torch.full((n,), math.sqrt(n / 2.0), dtype=u.dtype, device=u.device)
    scale[0] = math.sqrt(float(n))
    c = u * scale
    c_rev = torch.cat([torch.zeros_like(c[..., :1]), c[..., 1:].flip(-1)], dim=-1)
    w = torch.complex(c, -c_rev)
    k = torch.arange(n, dtype=u.dtype, device=u.device)
    spec = w * torch.polar(torch.ones_like(k), math.pi * k / (2 * n))
    v = torch.fft.ifft(spec, dim=-1).real
    half = (n + 1) // 2
    out = torch.empty_like(v)
    out[..., ::2] = v[..., :half]
    out[..., 1::2] = v[..., half:].flip(-1)
    return out


def _dct2_fft(x: Tensor, inverse: bool) -> Tensor:
    dtype = _compute_dtype(x)
    one_d = _idct1_fft_last if inverse else _dct1_fft_last
    y = one_d(x.to(dtype))
    return one_d(y.transpose(-1, -2)).transpose(-1, -2)


def _pick(x: Tensor, method: DctMethod) -> Tensor:
    if x.dim() < 2:
        raise ValueError(f"DCT acts on the last two dims; got a tensor of shape {tuple(x.shape)}")
    if method == "auto":
        return "matrix" if max(x.shape[-2:]) <= MATRIX_FORM_MAX_SIDE else "fft"
    if method not in ("matrix", "fft"):
        raise ValueError(f"unknown DCT method {method!r}; use 'auto', 'matrix' or 'fft'")
    return method


def dct2(x: Tensor, method: DctMethod = "auto") -> Tensor:
    """Orthonormal 2-D DCT-II over the last two dims (u = Vᵀx). Keeps the input dtype."""
    out = _dct2_matrix(x, False) if _pick(x, method) == "matrix" else _dct2_fft(x, False)
    return out.to(x.dtype)


def idct2(u: Tensor, method: DctMethod = "auto") -> Tensor:
    """Inverse of ``dct2`` (orthonormal DCT-III, x = V u). Keeps the input dtype."""
    out = _dct2_matrix(u, True) if _pick(u, method) == "matrix" else _dct2_fft(u, True)
    return out.to(u.dtype)


BandKind = Literal["full", "null", "high_pass", "low_pass", "custom"]


def band_bound(r: float, d: int) -> int:
    """The paper's frequency bound B = int(r·D); the epsilon keeps e.g. 0.29·100 from flooring to 28."""
    return min(d, math.floor(r * d + 1e-9))


@dataclass(frozen=True, eq=False)
class BandMask:
    """A diagonal 0/1 filter Λ over DCT coefficients, resolved to any H×W on demand.

    ``high_pass(r)`` zeroes the low-frequency block ``[:B_h, :B_w]`` with B = int(r·D) per axis
    and keeps the L-shaped rest (the paper's 2D-prior filter, r = 0.6); ``low_pass(r)`` is its
    complement. ``custom`` holds a fixed boolean H×W mask.
    """

    kind: BandKind
    r: float | None = None
    custom_mask: Tensor | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.kind in ("high_pass", "low_pass"):
            if self.r is None or not math.isfinite(self.r) or not 0.0 <= self.r <= 1.0:
                raise ValueError(f"{self.kind} needs a ratio r in [0, 1], got {self.r!r}")
        elif self.r is not None:
            raise ValueError(f"a {self.kind!r} band takes no ratio r")
        if self.kind == "custom":
            m = self.custom_mask
            if m is None or m.dtype != torch.bool or m.dim() != 2:
                raise ValueError("a custom band needs a 2-D boolean mask tensor")
        elif self.custom_mask is not None:
            raise ValueError(f"a {self.kind!r} band takes no custom mask")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, BandMask):
            return NotImplemented
        if (self.kind, self.r) != (other.kind, other.r):
            return False
        return self.kind != "custom" or torch.equal(self.custom_mask, other.custom_mask)

    def __hash__(self) -> int:
        extra = hash(self.custom_mask.numpy().tobytes()) if self.kind == "custom" else 0
        return hash((self.kind, self.r, extra))

    @staticmethod
    def full() -> BandMask:
        return BandMask("full")

    @staticmethod
    def null() -> BandMask:
        return BandMask("null")

    @staticmethod
    def high_pass(r: float) -> BandMask:
        return BandMask("high_pass", float(r))

    @staticmethod
    def low_pass(r: float) -> BandMask:
        return BandMask("low_pass", float(r))

    @staticmethod
    def custom(mask: Tensor) -> BandMask:
        return BandMask("custom", custom_mask=mask.detach().to("cpu", torch.bool))

    def complement(self) -> BandMask:
        if self.kind == "full":
            return BandMask.null()
        if self.kind == "null":
            return BandMask.full()
        if self.kind == "high_pass":
            return BandMask.low_pass(self.r)
        if self.kind == "low_pass":
            return BandMask.high_pass(self.r)
        return BandMask.custom(~self.custom_mask)

    def mask(self, h: int, w: int, device: torch.device | str = "cpu") -> Tensor:
        """The H×W boolean mask (True = coefficient kept)."""
        if self.kind == "custom":
            if tuple(self.custom_mask.shape) != (h, w):
                raise ValueError(
                    f"custom band mask is {tuple(self.custom_mask.shape)} but the tensor is {h}×{w}"
                )
            return self.custom_mask.to(device)
        keep = torch.ones(h, w, dtype=torch.bool, device=device)
        if self.kind == "full":
            return keep
        if self.kind == "null":
            return ~keep
        low = torch.zeros(h, w, dtype=torch.bool, device=device)
        low[: band_bound(self.r, h), : band_bound(self.r, w)] = True
        return ~low if self.kind == "high_pass" else low

    def describe(self) -> str:
        return f"{self.kind}({self.r})" if self.r is not None else self.kind


def apply_band(u: Tensor, band: BandMask) -> Tensor:
    """Λu for DCT coefficients u (any leading dims)."""
    return u * band.mask(u.shape[-2], u.shape[-1], u.device).to(u.dtype)


def filter_residual(r: Tensor, band: BandMask, method: DctMethod = "auto") -> Tensor:
    """V Λ Vᵀ r: keep only the band's frequencies of a spatial tensor (per channel, over H×W).

    ``full`` returns r unchanged and ``null`` returns zeros: V I Vᵀ = I by orthonormality, which the
    tests check on the transform itself, so the common full-pass prior pays no transform cost.
    """
    if band.kind == "full":
        return r
    if band.kind == "null":
        return torch.zeros_like(r)
    return idct2(apply_band(dct2(r, method), band), method)


def frequency_reference_loss(
    x: Tensor,
    y: Tensor,
    band: BandMask,
    reduction: Literal["sum", "mean", "none"] = "sum",
    method: DctMethod = "auto",
) -> Tensor:
    """‖Λ(Vᵀx − Vᵀy)‖², the DCT taken over H×W of every channel.

    ``none`` returns the per-channel sums (shape = leading dims of x); ``sum`` adds everything (the
    paper's squared norm); ``mean`` divides that by the number of elements.
    """
    if x.shape != y.shape:
        raise ValueError(f"render {tuple(x.shape)} and reference {tuple(y.shape)} differ in shape")
    diff = x - y
    diff = diff.to(_compute_dtype(diff))
    if band.kind == "full":
        per = diff.pow(2).sum(dim=(-2, -1))  # Parseval: ‖Vᵀd‖ = ‖d‖
    elif band.kind == "null":
        per = diff.sum(dim=(-2, -1)) * 0.0
    else:
        per = apply_band(dct2(diff, method), band).pow(2).sum(dim=(-2, -1))
    if reduction == "none":
        return per
    if reduction == "sum":
        return per.sum()
    if reduction == "mean":
        return per.sum() / diff.numel()
    raise ValueError(f"unknown reduction {reduction!r}")


def _power_and_radius(images: Tensor) -> tuple[Tensor, Tensor]:
    """|FFT|²/(H·W) of the mean-removed images and each coefficient's radius (1 = Nyquist)."""
    if images.dim() < 2:
        raise ValueError("spectra need at least a 2-D image")
    x = torch.nan_to_num(images.float())
    h, w = x.shape[-2:]
    x = x - x.mean(dim=(-2, -1), keepdim=True)
    power = torch.fft.fft2(x).abs().pow(2) / (h * w)
    fy = torch.fft.fftfreq(h, device=x.device).abs()[:, None] * 2.0
    fx = torch.fft.fftfreq(w, device=x.device).abs()[None, :] * 2.0
    return power, torch.sqrt(fy**2 + fx**2)


def radial_psd(images: Tensor, bins: int | None = None) -> tuple[Tensor, Tensor]:
    """Radially averaged power spectral density of images (…×H×W), averaged over leading dims.

    Returns (radius, psd): radius in [0, 1] of the Nyquist frequency (bin centres), psd the mean
    power in each radial bin (corners beyond Nyquist fall in the last bin). Empty bins hold 0.
    """
    power, radius = _power_and_radius(images)
    h, w = power.shape[-2:]
    power = power.reshape(-1, h, w).mean(dim=0)
    nbins = bins or max(2, min(h, w) // 2)
    idx = torch.clamp((radius * nbins).long(), max=nbins - 1).flatten()
    total = torch.zeros(nbins, device=power.device).index_add_(0, idx, power.flatten())
    count = torch.zeros(nbins, device=power.device).index_add_(0, idx, torch.ones_like(power).flatten())
    psd = torch.where(count > 0, total / count.clamp(min=1), torch.zeros_like(total))
    centres = (torch.arange(nbins, device=power.device, dtype=torch.float32) + 0.5) / nbins
    return centres, psd


def high_frequency_ratio(images: Tensor, cutoff: float = 0.5) -> float:
    """Share of the (mean-removed) spectral energy at radius ≥ cutoff·Nyquist; 0 for a flat image."""
    if not 0.0 < cutoff < 1.0:
        raise ValueError(f"cutoff must lie in (0, 1), got {cutoff}")
    power, radius = _power_and_radius(images)
    total = power.sum()
    if total <= 0:
        return 0.0
    return float((power * (radius >= cutoff)).sum() / total)
