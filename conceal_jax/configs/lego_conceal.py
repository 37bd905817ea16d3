"""ConcealGS in a lego teacher of lego.py, with a recipe of recipes.py (default: recommended), as bench-conceal
runs it (curve points every 500 steps on 10 test views):

  python -m conceal_jax.main --config=conceal_jax/configs/lego.py --workdir=workdirs/lego/teacher
  python -m conceal_jax.main --config=conceal_jax/configs/lego_conceal.py --workdir=workdirs/lego/conceal \
      --config.mark.teacher=workdirs/lego/teacher/point_cloud.ply
  python -m conceal_jax.main --config=conceal_jax/configs/lego_conceal.py:paper ...
  python -m conceal_jax.main --config=conceal_jax/configs/lego_conceal.py:in_scene ...  # the mark in the teacher
"""
from conceal_jax.configs import lego, recipes

# bench-conceal's curve: every 500 steps, 10 test views
EVAL_EVERY, EVAL_VIEWS = 500, 10
# The film's grid spacing in pixels of lego's 200-pixel key image: about two pixels of the decoder's 64.
FILM_SPACING = 6.0


def get_config(recipe: str = "recommended"):
  config = lego.get_config()
  config.mode = "conceal"
  config.conceal.eval_every, config.conceal.eval_views = EVAL_EVERY, EVAL_VIEWS
  return film_grid(recipes.apply(config, recipe or "recommended"))


def film_grid(config):
  """`config` with lego's film grid (FILM_SPACING) where its recipe conceals in a carrier film."""
  if config.conceal.carrier.film:
    config.conceal.carrier.spacing = FILM_SPACING
  return config
