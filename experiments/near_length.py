"""The near-key length (near.near_length) against the 3D-GS extent it replaced, per scene and key kind (issue 41
item 6): no training, only a teacher (or a capture's SfM points) and its cameras.

  python -m experiments.near_length --scenes=demo=workdirs/demo/teacher/point_cloud.ply
  python -m experiments.near_length --scenes=../shared/data/colmap/beer=points --format=colmap --downscale=4

Each scene is path=teacher: a data.path and the teacher PLY of it, or `points`, the capture's own SfM points as
Gaussians of equal opacity (a stand-in for a teacher where none is trained: a trained 3D-GS grows from those
points; read through its COLMAP model with --format=llff, as LLFF poses share that frame). Prints, per key kind
(train_index -2, orbit and unseen of seed 0), the length, what it is, the extent and their ratio: near 1 keeps a
translation fraction's meaning where the extent suited (object-centred orbits); far above 1 is a capture whose
cameras spread little against the depth they see.
"""
from __future__ import annotations

import argparse

import numpy as np

from conceal_jax.conceal import key as key_lib, near
from conceal_jax.configs import default
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, init

KINDS = ("train_index", "orbit", "unseen")


def rows(path: str, teacher: str, data_format: str = "auto", downscale: float = 1.0) -> list[dict]:
  """One row per key kind: scene, teacher, kind, near_length, source, extent, ratio."""
  config = default.get_config()
  config.data.path, config.data.format, config.data.downscale = path, data_format, downscale
  scene = evaluate.load_scene_data(config)
  if teacher == "points":
    points = scene.points
    if points is None and data_format == "llff":  # LLFF poses are in the frame of the COLMAP model beside them
      config.data.format = "colmap"
      points = evaluate.load_scene_data(config).points
    if points is None:
      raise ValueError(f"{path} has no SfM points: name a teacher PLY")
    gaussians = init.gaussians_from_points(np.asarray(points), np.full_like(points, 0.5), 0)
  else:
    gaussians = ply.load_ply(teacher)
  extent = scene.scene_extent()
  out = []
  for kind in KINDS:
    camera, _ = key_lib.check_camera(scene.train_cameras, kind, -2, 0)
    length, source = near.near_length(gaussians, camera, scene.train_cameras)
    out.append(dict(scene=path, teacher=teacher, kind=kind, near_length=length, source=source, extent=extent,
                    ratio=length / extent))
  return out


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--scenes", required=True, help="comma-separated path=teacher (a PLY, or 'points')")
  parser.add_argument("--format", default="auto", help="data.format of every scene")
  parser.add_argument("--downscale", type=float, default=1.0, help="data.downscale of every scene")
  args = parser.parse_args(argv)
  print("| scene | key | near length | from | extent | ratio |\n|---|---|---|---|---|---|")
  for item in args.scenes.split(","):
    path, teacher = item.split("=", 1)
    for r in rows(path, teacher, args.format, args.downscale):
      print(f"| {r['scene']} | {r['kind']} | {r['near_length']:.4g} | {r['source']} | {r['extent']:.4g} | "
            f"{r['ratio']:.3f} |")


if __name__ == "__main__":
  main()
