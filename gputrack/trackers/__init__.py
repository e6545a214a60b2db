"""Trackers, one module per paper; ``body_template`` builds paper 000's 3D sparse template."""

from .body_template import TemplatePixels, select_pixels, sparse_template

__all__ = ["TemplatePixels", "select_pixels", "sparse_template"]
