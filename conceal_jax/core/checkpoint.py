"""Checkpoints of plain pytrees as .npz files, written atomically, so a killed run resumes exactly.

A checkpoint holds the flattened leaves and a JSON `meta` dict (step, buffer capacity, ...); the
caller rebuilds a template pytree from `meta` and `restore` fills it, checking every shape.
"""
from __future__ import annotations

import io
import json
import os
import re

import jax
import numpy as np

from conceal_jax.core import fileio

_NAME = re.compile(r"^ckpt_(\d+)\.npz$")


def checkpoint_path(directory: str, step: int) -> str:
  return os.path.join(directory, f"ckpt_{step:08d}.npz")


def save(directory: str, step: int, tree, meta: dict, keep: int = 2) -> str:
  """Writes `tree` (and meta, which gets `step`) as ckpt_<step>.npz; keeps the newest `keep` files."""
  os.makedirs(directory, exist_ok=True)
  leaves = [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]
  buffer = io.BytesIO()
  np.savez(buffer, meta=np.array(json.dumps(dict(meta, step=int(step)))),
           **{f"leaf_{i:05d}": leaf for i, leaf in enumerate(leaves)})
  path = checkpoint_path(directory, step)
  fileio.write_bytes(path, buffer.getvalue())
  for old in list_steps(directory)[:-keep]:
    os.remove(checkpoint_path(directory, old))
  return path


def list_steps(directory: str) -> list[int]:
  """Steps of the complete checkpoints in `directory`, ascending (temp files are never matched)."""
  if not os.path.isdir(directory):
    return []
  return sorted(int(m.group(1)) for m in map(_NAME.match, os.listdir(directory)) if m)


def load(path: str) -> tuple[dict, list[np.ndarray]]:
  """(meta, leaves) of a checkpoint file; ValueError naming the file if it cannot be read."""
  try:
    with np.load(path) as data:
      meta = json.loads(str(data["meta"]))
      leaves = [data[k] for k in sorted(k for k in data.files if k.startswith("leaf_"))]
  except (OSError, ValueError, KeyError) as error:
    raise ValueError(f"cannot read checkpoint {path}: {error}") from error
  return meta, leaves


def load_latest(directory: str) -> tuple[str, dict, list[np.ndarray]] | None:
  """(path, meta, leaves) of the newest checkpoint in `directory`, or None if there is none."""
  steps = list_steps(directory)
  if not steps:
    return None
  path = checkpoint_path(directory, steps[-1])
  return (path,) + load(path)


def restore(template, leaves: list[np.ndarray], source: str = "checkpoint"):
  """Fills `template`'s structure with `leaves`, checking their number, shapes and dtypes."""
  expected, treedef = jax.tree.flatten(template)
  if len(expected) != len(leaves):
    raise ValueError(f"{source} has {len(leaves)} arrays, expected {len(expected)}")
  for i, (want, got) in enumerate(zip(expected, leaves)):
    if np.shape(want) != got.shape or np.asarray(want).dtype != got.dtype:
      raise ValueError(f"{source}: array {i} is {got.dtype}{list(got.shape)}, expected "
                       f"{np.asarray(want).dtype}{list(np.shape(want))}")
  return jax.tree.unflatten(treedef, leaves)
