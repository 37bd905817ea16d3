"""A few teacher steps and a few concealment steps, run by test_parallel in a subprocess whose XLA host device
count is set before JAX starts: `python -m tests.parallel_job OUT SCENE START VIEWS_PER_STEP`.

The teacher job starts from the scene START (a .ply) and takes VIEWS_PER_STEP views per step; the concealment job
conceals in START with its two views per step. Both stop after STEPS steps
(max_steps), leaving their whole state (parameters, optimiser moments, densification statistics) in the
checkpoint under OUT/teacher and OUT/conceal. OUT/devices.json records the devices each job's mesh had.
"""
from __future__ import annotations

import json
import os
import sys

STEPS = 3


def main(out: str, scene: str, start: str, views_per_step: int) -> None:
  import jax  # after the parent set XLA_FLAGS

  from conceal_jax.conceal import train as conceal_train
  from conceal_jax.core import parallel
  from conceal_jax.gs import train
  from tests import test_conceal, test_train

  config = test_train.tiny_config(scene, iterations=100)
  config.train.views_per_step = views_per_step
  config.init.kind, config.init.ply = "ply", start
  config.train.densify.start = 100  # none within the steps run: the statistics are compared instead
  config.train.eval_every = 0
  assert train.train_and_evaluate(config, os.path.join(out, "teacher"), max_steps=STEPS) == dict(stopped_at=STEPS)
  conceal_config = test_conceal.tiny_config((scene, start), iterations=100)
  assert conceal_train.train_and_evaluate(conceal_config, os.path.join(out, "conceal"),
                                          max_steps=STEPS) == dict(stopped_at=STEPS)
  mesh_size = lambda batch: getattr(parallel.batch_mesh(batch), "size", 1)
  with open(os.path.join(out, "devices.json"), "w") as f:
    json.dump(dict(devices=jax.device_count(), teacher=mesh_size(views_per_step), conceal=mesh_size(2)), f)


if __name__ == "__main__":
  main(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]))
