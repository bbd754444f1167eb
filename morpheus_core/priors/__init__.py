"""Diffusion priors behind one protocol (see ``base.Prior``)."""

from morpheus_core.priors.base import PixelSpacePrior, Prior

__all__ = ["PixelSpacePrior", "Prior"]
