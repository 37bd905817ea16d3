"""Test-split evaluation: PSNR, SSIM (3D-GS window) and LPIPS per view and on average.

`--config.mode=eval` scores a trained scene (`<workdir>/point_cloud.ply` or `config.eval.ply`) on the
test split of `config.data`, writing `metrics.json` and the renders as PNGs into the workdir.
"""
from __future__ import annotations

import dataclasses
import os

import jax
import ml_collections
import numpy as np
from absl import logging

from conceal_jax.core import fileio
from conceal_jax.data import datasets, ply
from conceal_jax.gs import metrics, render_views
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render

BACKGROUNDS = {"white": datasets.WHITE, "black": datasets.BLACK, "default": None}
SCENE_FILE = "point_cloud.ply"
METRICS_FILE = "metrics.json"


def load_scene_data(config: ml_collections.ConfigDict) -> datasets.SceneData:
  """The dataset of `config.data`: path ('demo' or a folder), downscale, background name."""
  if config.data.background not in BACKGROUNDS:
    raise ValueError(f"data.background must be one of {sorted(BACKGROUNDS)}, got {config.data.background!r}")
  return datasets.load_scene(config.data.path, config.data.downscale, BACKGROUNDS[config.data.background])


def eval_options(config: ml_collections.ConfigDict, background) -> RenderOptions:
  """Render options for evaluation: the config's, on the scene's background, exact if `eval.exact`."""
  options = render_views.render_options(config)
  max_per_tile = None if config.eval.exact else options.max_per_tile
  return dataclasses.replace(options, background=tuple(background), max_per_tile=max_per_tile)


def render_images(gaussians: Gaussians, cameras: list[Camera], options: RenderOptions) -> list[np.ndarray]:
  """[H, W, 3] float32 numpy renders, one per camera."""
  return [np.asarray(jax.device_get(render(gaussians, camera, options).rgb)) for camera in cameras]


def image_metrics(rendered: list[np.ndarray], targets: list[np.ndarray], names: list[str],
                  lpips_net: str = "vgg") -> dict:
  """Per-view and mean PSNR / SSIM / LPIPS of `rendered` against `targets` ([H, W, 3] in [0, 1])."""
  if len(rendered) != len(targets):
    raise ValueError(f"{len(rendered)} renders for {len(targets)} targets")
  psnr, ssim, lpips = jax.jit(metrics.psnr), jax.jit(metrics.ssim), jax.jit(metrics.lpips_fn(lpips_net))
  views = []
  for name, image, target in zip(names, rendered, targets):
    if image.shape != target.shape:
      raise ValueError(f"render of {name} is {image.shape}, its target {target.shape}")
    image = np.clip(image, 0.0, 1.0)  # scored as the 8-bit PNG a viewer would show, minus quantisation
    views.append(dict(name=name, psnr=float(psnr(image, target)), ssim=float(ssim(image, target)),
                      lpips=float(lpips(image, target))))
  mean = {key: float(np.mean([v[key] for v in views])) for key in ("psnr", "ssim", "lpips")}
  return dict(mean=mean, views=views, num_views=len(views), lpips_net=metrics.LPIPS_NET_NAME[lpips_net])


def write_images(folder: str, names: list[str], images: list[np.ndarray]) -> None:
  os.makedirs(folder, exist_ok=True)
  for name, image in zip(names, images):
    fileio.write_image(os.path.join(folder, f"{os.path.splitext(os.path.basename(name))[0]}.png"), image)


def evaluate_scene(gaussians: Gaussians, scene: datasets.SceneData, options: RenderOptions, workdir: str,
                   lpips_net: str = "vgg", max_views: int = 0) -> dict:
  """Renders the test split (the first `max_views`, 0 = all), writes test_renders/*.png and
  metrics.json into workdir, and returns the metrics."""
  cameras, targets, names = held_out_views(scene, max_views)
  rendered = render_images(gaussians, cameras, options)
  result = image_metrics(rendered, targets, names, lpips_net)
  result.update(num_gaussians=int(gaussians.num), render_options=repr(options))
  write_images(os.path.join(workdir, "test_renders"), names, rendered)
  fileio.write_json(os.path.join(workdir, METRICS_FILE), result)
  logging.info("test PSNR %.2f SSIM %.4f LPIPS %.4f on %d views", result["mean"]["psnr"],
               result["mean"]["ssim"], result["mean"]["lpips"], len(names))
  return result


def evaluate(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """The eval job: scores config.eval.ply (default <workdir>/point_cloud.ply) on the test split."""
  path = config.eval.ply or os.path.join(workdir, SCENE_FILE)
  gaussians = ply.load_ply(path)
  scene = load_scene_data(config)
  return evaluate_scene(gaussians, scene, eval_options(config, scene.background), workdir,
                        config.eval.lpips_net, config.eval.max_views)


def held_out_views(scene: datasets.SceneData,
                   max_views: int = 0) -> tuple[list[Camera], list[np.ndarray], list[str]]:
  """The first `max_views` (0 = all) test cameras, images and names (view_000, ... if unnamed)."""
  count = len(scene.test_cameras) if max_views <= 0 else min(max_views, len(scene.test_cameras))
  names = list(scene.test_names[:count]) if len(scene.test_names) >= count else [
      f"view_{i:03d}" for i in range(count)]
  return scene.test_cameras[:count], scene.test_images[:count], names
