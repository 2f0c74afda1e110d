"""The images embedded in the package (CC0; see jaxpso/data/ATTRIBUTION.md)."""

from __future__ import annotations

import importlib.resources

import numpy as np

IMAGES = ("camera", "brick")
"""Names accepted by `load_image`."""


def load_image(name: str = "camera") -> np.ndarray:
  """Loads an embedded 512×512 grey image as float32 in [0, 1].

  Args:
    name: one of `IMAGES`.

  Returns:
    (512, 512) float32 array.
  """
  if name not in IMAGES:
    raise ValueError(f"name must be one of {IMAGES}, got {name!r}")
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  raw = importlib.resources.files("jaxpso").joinpath("data", name + ".png").read_bytes()
  image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)
  return image.astype(np.float32) / 255.0
