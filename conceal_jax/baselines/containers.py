"""Containers: training views that carry the hidden image, as the 8-bit images a photographer would share,
and the scene 3D-GS is then trained on. Shared by every baseline (lsb.py, deepstega.py)."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib
from conceal_jax.data import datasets

LEVELS = 255  # the largest 8-bit level


def to_levels(images) -> jnp.ndarray:
  """images [..., H, W, 3] in [0, 1] (clipped) -> int32 8-bit levels 0..255 of the same shape."""
  return jnp.round(jnp.clip(jnp.asarray(images, jnp.float32), 0.0, 1.0) * LEVELS).astype(jnp.int32)


def from_levels(levels) -> jnp.ndarray:
  """int 8-bit levels [..., H, W, 3] -> float32 images in [0, 1]."""
  return jnp.asarray(levels, jnp.float32) / LEVELS


def hidden_at_view(source: str, height: int, width: int) -> np.ndarray:
  """[height, width, 3] float32 in [0, 1]: the hidden image (a file or sample name, see conceal.hidden) at
  the size of a view, as the baselines hide it: loaded as a square of the view's larger side, then
  stretched to a non-square view (so every pixel of the view carries the image)."""
  square = hidden_lib.load_hidden_image(source, max(height, width))
  if height == width:
    return square
  import skimage.transform
  stretched = skimage.transform.resize(square, (height, width), order=1, anti_aliasing=True)
  return np.clip(stretched, 0.0, 1.0).astype(np.float32)


def container_scene(scene: datasets.SceneData, containers) -> datasets.SceneData:
  """`scene` with its training images replaced by `containers` [V, H, W, 3] (one per training view, of
  the views' size); cameras, test split and background are unchanged."""
  containers = np.asarray(containers, np.float32)
  expected = (len(scene.train_images),) + np.shape(scene.train_images[0])
  if containers.shape != expected:
    raise ValueError(f"containers {containers.shape} do not match the training views {expected}")
  return dataclasses.replace(scene, train_images=list(containers))
