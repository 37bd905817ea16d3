"""demo.py trained through the attacks of the robustness issue, the decoder reading clipped renders
(recipes.through_attacks): the demo run of bench-robust and of the ownership calibration.

  python -m conceal_jax.main --config=conceal_jax/configs/demo_robust.py --workdir=workdirs/demo_robust/teacher
  python -m conceal_jax.main --config=conceal_jax/configs/demo_robust.py --workdir=workdirs/demo_robust/conceal \
      --config.mode=conceal --config.mark.teacher=workdirs/demo_robust/teacher/point_cloud.ply

The teacher is demo.py's (the conceal settings do not touch it).
"""
from conceal_jax.configs import demo, recipes


def get_config():
  return recipes.through_attacks(demo.get_config(), clip_input=True)
