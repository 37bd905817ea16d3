"""ConcealGS in a lego teacher of lego.py with our best measured settings (conceal_ours.best, width-16 decoder),
the run of bench-conceal's row ours_robust_clip_dec03:

  python -m conceal_jax.main --config=conceal_jax/configs/lego.py --workdir=workdirs/lego/teacher
  python -m conceal_jax.main --config=conceal_jax/configs/lego_conceal.py --workdir=workdirs/lego/conceal \
      --config.conceal.teacher=workdirs/lego/teacher/point_cloud.ply

Lego 200x200, 10k steps, two seeds: student within 0.19 dB of its teacher, hidden 39.4-40.7 dB / SSIM
0.996-0.997, leakage at most 0.191, 48-61 min on 2 CPU cores. The hidden PSNR / SSIM and the student's test
PSNR are recorded every 500 steps on 10 test views (conceal.json).
"""
from conceal_jax.configs import conceal_ours, lego

# bench-conceal's curve: every 500 steps, 10 test views (about 1% of the run's time)
EVAL_EVERY, EVAL_VIEWS = 500, 10


def get_config():
  config = lego.get_config()
  config.mode = "conceal"
  config.conceal.hidden = "astronaut"
  config.conceal.eval_every, config.conceal.eval_views = EVAL_EVERY, EVAL_VIEWS
  return conceal_ours.best(conceal_ours.narrow_decoder(config), decoy_views=64)
