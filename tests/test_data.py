"""Tests for jaxpso.data: the embedded CC0 images."""

from __future__ import annotations

import numpy as np
import pytest

import jaxpso


@pytest.mark.parametrize("name", jaxpso.data.IMAGES)
def test_every_embedded_image_loads_as_a_textured_512x512_float32_image_in_0_1(name):
  image = jaxpso.data.load_image(name)
  assert image.shape == (512, 512) and image.dtype == np.float32
  assert 0.0 <= image.min() and image.max() <= 1.0
  assert image.std() > 0.05  # a photograph, not a blank or constant image


def test_the_embedded_images_differ():
  first, second = (jaxpso.data.load_image(name) for name in jaxpso.data.IMAGES[:2])
  assert np.abs(first - second).mean() > 0.05


def test_an_unknown_image_name_is_a_value_error_naming_the_choices():
  with pytest.raises(ValueError, match="name must be one of .*camera"):
    jaxpso.data.load_image("lena")
