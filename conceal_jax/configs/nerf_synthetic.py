"""NeRF-Synthetic with the paper's settings: 1/4 resolution, white background, 10k pre-training steps.

  python -m conceal_jax.main --config=conceal_jax/configs/nerf_synthetic.py \
      --config.data.path=../shared/data/nerf_synthetic/lego --workdir=workdirs/lego/teacher
"""
from conceal_jax.configs import default


def get_config():
  config = default.get_config()
  config.mode = "train"
  config.data.path = "../shared/data/nerf_synthetic/lego"
  config.data.downscale = 4.0
  config.data.background = "white"
  config.init.kind = "random"        # 100k points in [-1.3, 1.3]^3, as 3D-GS does for synthetic scenes
  config.train.iterations = 10_000
  config.eval.max_views = 0
  return config
