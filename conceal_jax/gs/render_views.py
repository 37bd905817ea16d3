"""The `render` job: render a scene (a .ply, or a generated one) from an orbit of cameras and write the
images to the workdir."""
from __future__ import annotations

import math
import os

import jax
import ml_collections
import numpy as np
from absl import logging

from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, scene_gen
from conceal_jax.splat.camera import Camera, look_at, orbit_eye
from conceal_jax.splat.render import render


def validate(config: ml_collections.ConfigDict) -> None:
  c = config.scene
  if c.num_views < 1 or c.width < 1 or c.height < 1 or not 0 < c.fov_deg < 180 or not c.distance > 0:
    raise ValueError("scene.num_views, width, height and distance must be positive and fov_deg in (0, 180)")
  if not c.ply and c.num_points < 2:
    raise ValueError(f"scene.num_points must be at least 2, got {c.num_points}")
  evaluate.render_options(config)


def orbit_cameras(config: ml_collections.ConfigDict) -> list[Camera]:
  """scene.num_views cameras evenly spaced in azimuth, looking at the origin from scene.distance."""
  c = config.scene
  azimuths = 2 * math.pi * np.arange(c.num_views) / c.num_views
  eyes = orbit_eye((0.0, 0.0, 0.0), c.distance, azimuths, math.radians(c.elevation_deg))
  return [Camera.from_fov(look_at(eye, (0.0, 0.0, 0.0)), math.radians(c.fov_deg), c.width, c.height)
          for eye in eyes]


def load_scene(config: ml_collections.ConfigDict):
  if config.scene.ply:
    return ply.load_ply(config.scene.ply)
  return scene_gen.sphere_and_ground(config.scene.num_points, config.scene.sh_degree, config.seed)


def render_and_save(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """Renders every orbit view; writes view_000.png, view_001.png, ... and render.json (overflow per view) to workdir."""
  validate(config)
  options = evaluate.render_options(config)
  gaussians = load_scene(config)
  summary = dict(num_gaussians=gaussians.num, options=repr(options), views=[])
  for k, camera in enumerate(orbit_cameras(config)):
    out = render(gaussians, camera, options)
    path = os.path.join(workdir, f"view_{k:03d}.png")
    fileio.write_image(path, np.asarray(jax.device_get(out.rgb)))
    summary["views"].append(dict(file=os.path.basename(path), overflow_tiles=int(out.num_overflow_tiles),
                                 mean_alpha=float(np.mean(out.alpha))))
    logging.info("wrote %s (overflowing tiles: %d)", path, int(out.num_overflow_tiles))
  fileio.write_json(os.path.join(workdir, "render.json"), summary)
  return summary
