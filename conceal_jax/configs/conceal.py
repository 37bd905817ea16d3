"""Conceal an image in any scene: a scene folder the loaders read and its trained teacher .ply, with one of the
recipes of recipes.py (default: recommended).

  python -m conceal_jax.main --config=conceal_jax/configs/conceal.py --workdir=workdirs/my_scene/conceal \
      --config.data.path=SCENE --config.mark.teacher=TEACHER.ply
  python -m conceal_jax.main --config=conceal_jax/configs/conceal.py:paper ...     # the paper as written
  python -m conceal_jax.main --config=conceal_jax/configs/conceal.py:released ...  # the authors' code

The scene's background is the dataset's default (white for Blender, black otherwise; data.background).
"""
from conceal_jax.configs import default, recipes


def get_config(recipe: str = "recommended"):
  config = default.get_config()
  config.mode = "conceal"
  config.data.path = ""  # required: the scene folder
  return recipes.apply(config, recipe or "recommended")
