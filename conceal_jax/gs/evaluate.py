"""Test-split evaluation: PSNR, SSIM (3D-GS window) and LPIPS per view and on average.

`--config.mode=eval` scores a trained scene (`<workdir>/point_cloud.ply` or `config.eval.ply`) on the
test split of `config.data`, writing `metrics.json` and the renders as PNGs into the workdir. Views are
rendered in batches that stay on the device, and every metric is one jitted, batched function.
"""
from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from absl import logging

from conceal_jax.core import fileio, settings
from conceal_jax.data import datasets, ply
from conceal_jax.gs import metrics
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render_batch

BACKGROUNDS = {"white": datasets.WHITE, "black": datasets.BLACK, "default": None}
SCENE_FILE = "point_cloud.ply"
METRICS_FILE = "metrics.json"
# Views rendered per batch: enough to amortise dispatch, few enough to bound the batch's memory.
RENDER_CHUNK = 4


def validate(config: ml_collections.ConfigDict) -> None:
  """The data, render and eval sections every job that loads a scene reads."""
  if config.data.background not in BACKGROUNDS:
    raise ValueError(f"data.background must be one of {sorted(BACKGROUNDS)}, got {config.data.background!r}")
  if not (isinstance(config.data.downscale, (int, float)) and config.data.downscale > 0):
    raise ValueError(f"data.downscale must be a positive number, got {config.data.downscale!r}")
  scene_format(config)
  render_options(config)
  if config.eval.max_views < 0:
    raise ValueError(f"eval.max_views must be >= 0, got {config.eval.max_views}")
  metrics.lpips_weights_path(config.eval.lpips_net)


def load_scene_data(config: ml_collections.ConfigDict) -> datasets.SceneData:
  """The dataset of `config.data`: path ('demo' or a folder), format, images folder, downscale, background
  name."""
  return datasets.load_scene(config.data.path, config.data.downscale, BACKGROUNDS[config.data.background],
                             **scene_format(config))


def scene_format(config: ml_collections.ConfigDict) -> dict:
  """load_scene's data_format and images from data.format and data.images; ValueError naming the key."""
  choices = (datasets.AUTO, *datasets.FORMATS)
  if config.data.format not in choices:
    raise ValueError(f"data.format must be one of {', '.join(choices)}, got {config.data.format!r}")
  problem = datasets.images_folder_problem(config.data.images)
  if problem:
    raise ValueError(f"data.images {problem}")
  return dict(data_format=config.data.format, images=config.data.images)


def render_options(config: ml_collections.ConfigDict, background=None) -> RenderOptions:
  """RenderOptions from the config's `render` section (ValueError naming a bad value), on `background`
  when given (a scene's own)."""
  overrides = {} if background is None else dict(background=tuple(background))
  return settings.from_section(RenderOptions, config.render, **overrides)


def eval_options(config: ml_collections.ConfigDict, background) -> RenderOptions:
  """Render options for evaluation: the config's, on the scene's background, exact if `eval.exact`."""
  options = render_options(config, background)
  return dataclasses.replace(options, max_per_tile=None) if config.eval.exact else options


def render_images(gaussians: Gaussians, cameras: list[Camera], options: RenderOptions) -> jax.Array:
  """[V, H, W, 3] device renders of cameras of one size, in batches of RENDER_CHUNK views."""
  chunks = [render_batch(gaussians, camera_lib.stack(cameras[i:i + RENDER_CHUNK]), options).rgb
            for i in range(0, len(cameras), RENDER_CHUNK)]
  return jnp.concatenate(chunks) if chunks else jnp.zeros((0,), jnp.float32)


def image_metrics(rendered: jax.Array, targets, names: list[str], lpips_net: str = "vgg") -> dict:
  """Per-view and mean PSNR / SSIM / LPIPS of `rendered` against `targets` ([V, H, W, 3] in [0, 1])."""
  rendered, targets = jnp.asarray(rendered), jnp.asarray(np.stack(targets) if isinstance(targets, list) else targets)
  if rendered.shape != targets.shape:
    raise ValueError(f"renders {rendered.shape} and targets {targets.shape} differ in shape")
  # Scored as the 8-bit PNG a viewer would show, minus quantisation.
  scores = metrics.batched_scores(lpips_net)(jnp.clip(rendered, 0.0, 1.0), targets)
  scores = {k: np.asarray(v, np.float64) for k, v in jax.device_get(scores).items()}
  views = [dict(name=name, **{k: float(v[i]) for k, v in scores.items()}) for i, name in enumerate(names)]
  mean = {key: float(np.mean(scores[key])) for key in ("psnr", "ssim", "lpips")}
  return dict(mean=mean, views=views, num_views=len(views), lpips_net=metrics.LPIPS_NET_NAME[lpips_net])


def views_psnr(gaussians: Gaussians, cameras: list[Camera], targets, options: RenderOptions) -> float:
  """Mean PSNR of the clipped renders at `cameras` against `targets` ([H, W, 3] each)."""
  rendered = jnp.clip(render_images(gaussians, cameras, options), 0, 1)
  return float(jnp.mean(jax.vmap(metrics.psnr)(rendered, jnp.asarray(np.stack(targets)))))


def mean_psnr(gaussians: Gaussians, scene: datasets.SceneData, options: RenderOptions, max_views: int) -> float:
  """Mean test PSNR over `max_views` evenly spaced test views (the periodic training check)."""
  cameras, targets, _ = held_out_views(scene, max_views)
  return views_psnr(gaussians, cameras, targets, options)


def write_images(folder: str, names: list[str], images) -> None:
  os.makedirs(folder, exist_ok=True)
  for name, image in zip(names, np.asarray(jax.device_get(images))):
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
  """`max_views` (0 = all) test cameras, images and names (view_000, ... if unnamed), evenly spaced over
  the test split so that a subset of an orbit covers the whole orbit."""
  total = len(scene.test_cameras)
  count = total if max_views <= 0 else min(max_views, total)
  rows = np.linspace(0, total - 1, count).round().astype(int) if count else np.zeros(0, int)
  names = [scene.test_names[i] if len(scene.test_names) == total else f"view_{i:03d}" for i in rows]
  return [scene.test_cameras[i] for i in rows], [scene.test_images[i] for i in rows], names
