"""How a real diffusion prior errs, as a model the render-target (proxy) prior can carry.

A noise-free proxy predicts x̂0 = target exactly, so its SDS residual is a deterministic pull and VSD
equals SDS. A real denoiser's x̂0 is a different guess for every noise draw, worse at high t, and
(for an image-prompt 2D model) inconsistent in colour from call to call. ``DenoiserError`` models
those errors from first principles of denoising, with few parameters:

* **Noise-driven error.** Natural images have a power spectrum S(f) ≈ A/f² (f the radial frequency
  as a fraction of the image side; Field 1987, van der Schaaf & van Hateren 1996). At timestep t the
  noise in x_t/α_t has per-coefficient power N = σ_t²/α_t², so frequencies above f_c(t) = √A·α_t/σ_t
  are hidden by the noise ("diffusion is spectral autoregression": coarse structure is decided at
  high t, detail at low t). A model conditioned on the object (Zero123 on the photo, the 2D model on
  edges and the photo's embedding) is uncertain about a share κ of a generic image's variance; the
  Gaussian (Wiener) posterior then leaves an error of spectrum E_t(f) = κA/(f² + κ·f_c(t)²) — flat
  below √κ·f_c, falling like 1/f² above: spatially correlated blotches whose size grows with t, and
  whose variance grows with t. The error is drawn from the step's noise ε itself (its DCT shaped by
  √E_t), so, like a network, the prediction is a fixed function of x_t: a new ε gives a new error,
  views and calls are independent.
* **Colour drift (2D role).** An image-prompt model reproduces the photo's colours only roughly, and
  differently each call: a hue rotation and an RGB tint drawn per image (mean zero; the role's
  systematic deviation stays in its corruption), confined to the low band ``drift_r`` so the high
  band stays right.
* **Classifier-free guidance.** The unconditional model knows only what x_t shows: per frequency the
  generic Wiener share w_t(f) = 1/(1 + (f/f_c)²). The conditional one also knows (1 − κ) of the
  rest, so x̂0_c − x̂0_u = (1 − κ)(1 − w_t)·AC(target), the target's detail hidden by the noise, and
  guidance at scale s extrapolates it by (s − 1): CFG > 1 over-sharpens and over-saturates, as it
  does with real priors. Both branches share the noise-driven error (one network, one x_t).
* **VSD counterpart.** The LoRA copy starts as the frozen network and is trained on the renders, so it
  repeats a share ``counterpart_shared`` of the frozen model's noise-driven error (not its colour
  drift, which comes from the conditioning and which the LoRA, trained on the renders' own colours,
  does not make). That shared share is what VSD's control variate removes from the residual.

Parameters are set from this rationale, not fitted to any result (README, "The stochastic oracle").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.color import rotate_hue
from morpheus_core.guidance.frequency import BandMask, dct2, filter_residual, idct2

# The drift's random numbers are read from DCT coefficients of ε at the top corner of the band,
# where the noise-driven error's weight is smallest (E_t falls like 1/f²): independent standard
# normals per call that barely overlap the error drawn from the same ε.
_DRIFT_COEFFS = 4


@dataclass(frozen=True)
class DenoiserError:
    """One prior role's error model (see the module docstring)."""

    spectrum_amplitude: float = 0.004
    """A of the image power spectrum S(f) = A/f² (orthonormal-DCT power per coefficient, f = radial frequency /
    image side); sets where the noise hides the image at each t. 0.004: the benchmark scenes' renders measure
    A ≈ 0.0009 in [0, 1] (median of f²·power over 8 scenes × 4 views at 128 px), and the priors denoise images
    scaled to [−1, 1], four times that power."""
    uncertainty: float = 0.1
    """κ in (0, 1]: the share of a generic image's variance the conditioned model is still unsure of."""
    drift_hue_sd: float = 0.0
    """Per-call hue rotation's standard deviation (degrees); 0: no drift (the 3D role)."""
    drift_tint_sd: float = 0.0
    """Per-call RGB tint's standard deviation (per channel); 0: no tint drift."""
    drift_r: float = 0.15
    """The drift is confined to the low band [0, r) of the image."""
    counterpart_shared: float = 0.5
    """Share of the noise-driven error the VSD counterpart (the LoRA copy of the same network) repeats."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.spectrum_amplitude) and self.spectrum_amplitude > 0.0):
            raise ValueError(f"spectrum_amplitude must be > 0, got {self.spectrum_amplitude}")
        if not 0.0 < self.uncertainty <= 1.0:
            raise ValueError(f"uncertainty must lie in (0, 1], got {self.uncertainty}")
        if not (self.drift_hue_sd >= 0.0 and self.drift_tint_sd >= 0.0):
            raise ValueError("drift standard deviations must be ≥ 0")
        if not 0.0 < self.drift_r <= 1.0:
            raise ValueError(f"drift_r must lie in (0, 1], got {self.drift_r}")
        if not 0.0 <= self.counterpart_shared <= 1.0:
            raise ValueError(f"counterpart_shared must lie in [0, 1], got {self.counterpart_shared}")

    def describe(self) -> str:
        drift = (f", colour drift hue ±{self.drift_hue_sd:g}° tint ±{self.drift_tint_sd:g} below r = {self.drift_r:g}"
                 if self.drift_hue_sd or self.drift_tint_sd else "")
        return (f"x̂0 error of spectrum κA/(f² + κf_c²), A = {self.spectrum_amplitude:g}, κ = {self.uncertainty:g}"
                f"{drift}; VSD counterpart shares {self.counterpart_shared:g} of it")

    # -- the pieces -------------------------------------------------------------------------------

    def cutoff(self, alpha_bar: Tensor) -> Tensor:
        """f_c(t) = √A·α_t/σ_t: the generic model resolves frequencies below it (shaped like ``alpha_bar``)."""
        ab = alpha_bar.clamp(1e-8, 1.0 - 1e-8)
        return math.sqrt(self.spectrum_amplitude) * (ab / (1.0 - ab)).sqrt()

    def error_spectrum(self, alpha_bar: Tensor, height: int, width: int) -> Tensor:
        """E_t(f) per DCT coefficient, B×1×H×W for ``alpha_bar`` of shape B×1×1×1."""
        f2 = _radial_frequency(height, width, alpha_bar.device, alpha_bar.dtype).pow(2)
        k = self.uncertainty
        return k * self.spectrum_amplitude / (f2 + k * self.cutoff(alpha_bar).pow(2))

    def noise_error(self, noise: Tensor, alpha_bar: Tensor) -> Tensor:
        """The noise-driven x̂0 error for the step's noise ε (B×C×H×W): ε's DCT shaped by √E_t."""
        return self._noise_error(dct2(noise), alpha_bar)

    def _noise_error(self, noise_dct: Tensor, alpha_bar: Tensor) -> Tensor:
        spectrum = self.error_spectrum(alpha_bar, noise_dct.shape[-2], noise_dct.shape[-1])
        return idct2(noise_dct * spectrum.sqrt())

    def colour_drift(self, target: Tensor, noise: Tensor) -> Tensor:
        """The per-call colour drift of ``target`` (low band only), its hue and tint read from ε."""
        return self._colour_drift(target, dct2(noise))

    def _colour_drift(self, target: Tensor, noise_dct: Tensor) -> Tensor:
        if not (self.drift_hue_sd or self.drift_tint_sd):
            return torch.zeros_like(target)
        if target.shape[-3] != 3:
            raise ValueError("colour drift needs RGB images (3 channels at dim -3)")
        z = noise_dct[..., -1, -_DRIFT_COEFFS:].flatten(1)  # B × (3·4) standard normals
        hue = self.drift_hue_sd * z[:, 0]
        tint = self.drift_tint_sd * z[:, 1:4].reshape(-1, 3, 1, 1)
        return filter_residual(rotate_hue(target, hue) + tint - target, BandMask.low_pass(self.drift_r))

    def guidance_shift(self, target: Tensor, alpha_bar: Tensor) -> Tensor:
        """x̂0_c − x̂0_u: the target's detail (DC excluded) hidden by the noise that the condition explains."""
        h, w = target.shape[-2:]
        f2 = _radial_frequency(h, w, target.device, target.dtype).pow(2)
        hidden = f2 / (f2 + self.cutoff(alpha_bar).pow(2))  # 1 − w_t(f); 0 at DC
        return (1.0 - self.uncertainty) * idct2(dct2(target) * hidden)

    def predictions(self, target: Tensor, noise: Tensor, alpha_bar: Tensor, cfg_scale: float) -> Tensor:
        """The guided x̂0 = x̂0_u + s·(x̂0_c − x̂0_u) of the frozen prior (``target`` = the role's truth)."""
        noise_dct = dct2(noise)  # one transform serves the error and the drift
        conditional = target + self._noise_error(noise_dct, alpha_bar) + self._colour_drift(target, noise_dct)
        if cfg_scale == 1.0:
            return conditional
        return conditional + (cfg_scale - 1.0) * self.guidance_shift(target, alpha_bar)

    def counterpart_prediction(self, current: Tensor, noise: Tensor, alpha_bar: Tensor) -> Tensor:
        """The VSD counterpart's x̂0: the current render plus its shared share of the noise-driven error."""
        if self.counterpart_shared == 0.0:
            return current
        return current + self.counterpart_shared * self.noise_error(noise, alpha_bar)


def _radial_frequency(height: int, width: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """f = √((k_v/H)² + (k_u/W)²) per DCT coefficient (0 at DC, √2 at the top corner)."""
    fv = torch.arange(height, device=device, dtype=dtype) / height
    fu = torch.arange(width, device=device, dtype=dtype) / width
    return (fv[:, None].pow(2) + fu[None, :].pow(2)).sqrt()
