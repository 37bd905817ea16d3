"""Default config: render a generated Gaussian scene from an orbit of cameras and write PNGs.

  python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=workdirs/demo
  python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=workdirs/ply \
      --config.scene.ply=path/to/point_cloud.ply --config.render.sh_degree=3
"""
import ml_collections


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.mode = "render"  # the job to run; see conceal_jax.main.MODES
  config.seed = 0

  config.scene = ml_collections.ConfigDict()
  config.scene.ply = ""          # a standard 3D-GS .ply; empty: the generated scene below
  config.scene.num_points = 3000  # size of the generated scene
  config.scene.sh_degree = 3

  config.render = ml_collections.ConfigDict()
  config.render.width = 128
  config.render.height = 128
  config.render.fov_deg = 45.0
  config.render.distance = 4.0       # orbit radius around the origin
  config.render.elevation_deg = 25.0
  config.render.num_views = 4
  config.render.sh_degree = -1       # -1: every band the scene stores
  config.render.background = (1.0, 1.0, 1.0)
  config.render.tile_size = 16
  config.render.max_per_tile = 256   # K nearest splats per tile
  config.render.exact = False        # True: never truncate (slower)
  config.render.antialiased = False
  return config
