"""The CC0 images embedded in the package (attribution in jaxpso/data/ATTRIBUTION.md)."""

from jaxpso._src.data import IMAGES
from jaxpso._src.data import load_image

__all__ = ("IMAGES", "load_image")
