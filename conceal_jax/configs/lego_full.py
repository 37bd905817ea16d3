"""NeRF-Synthetic lego at the full resolution the shared copy holds (400x400: the original 800x800 halved)
with the unmodified 3D-GS recipe: 30k steps, 100k random start points, densification over the first 15k
steps without a cap, 8-pixel tiles. It is meant for an accelerator (`make bench-full`); a test PSNR every
1000 steps on 10 test views draws its curve.

  python -m conceal_jax.main --config=conceal_jax/configs/lego_full.py --workdir=workdirs/full/lego/teacher
  python -m conceal_jax.main --config=conceal_jax/configs/lego_full.py:in_scene \
      --workdir=workdirs/full/lego/conceal --config.mark.teacher=workdirs/full/lego/teacher/point_cloud.ply

With a recipe of recipes.py after the colon it conceals in such a teacher at the same resolution.
"""
from conceal_jax.configs import nerf_synthetic, recipes

EVAL_EVERY, EVAL_VIEWS = 1000, 10


def get_config(recipe: str = ""):
  config = nerf_synthetic.get_config()
  config.data.downscale = 1.0
  config.train.iterations = 30_000
  config.train.eval_every, config.train.eval_views = EVAL_EVERY, EVAL_VIEWS
  if not recipe:
    return config
  config.mode = "conceal"
  config.conceal.eval_every, config.conceal.eval_views = EVAL_EVERY, EVAL_VIEWS
  return recipes.apply(config, recipe)
