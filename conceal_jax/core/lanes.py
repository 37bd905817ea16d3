"""Lanes: the same computation on different inputs, side by side, one per XLA device.

Why: XLA's CPU backend runs a computation's loops on one thread, so the ConcealGS step's two renders (a
normal view and the check view) use one core after the other. On lego 200x200 (2 cores), the two renders
with their backward passes take 350 ms in one computation and 213 ms on two lanes. The host CPU is
therefore split into two XLA devices (`split_host_cpu`, before the backend starts), and `map_lanes` runs
fn(shared, x_i) for lane i on device i (shard_map over LANE_AXIS). Every lane runs the same program: what
differs per lane must be data, not code, because a branch chosen per device (lax.switch) puts its ops in
a conditional, where XLA's CPU backend runs the decoder's convolutions 7x slower (measured: 552 vs 80 ms).
On one device (a GPU) the lanes run in turn; the values are the same, so the choice is one of speed.
"""
from __future__ import annotations

import math
import os
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.sharding import Mesh, NamedSharding, PartitionSpec

LANE_AXIS = "lane"
HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
# conceal.lanes = AUTO: two lanes where the default backend is the CPU split into two devices, else one.
AUTO = 0


def split_host_cpu(count: int = 2) -> None:
  """Asks XLA for `count` host CPU devices (XLA_FLAGS), unless the flag is already set or there are fewer
  cores. It takes effect only if the backend has not started yet, so it runs on importing the package."""
  flags = os.environ.get("XLA_FLAGS", "")
  if HOST_DEVICES_FLAG not in flags and (os.cpu_count() or 1) >= count:
    os.environ["XLA_FLAGS"] = f"{flags} {HOST_DEVICES_FLAG}={count}".strip()


def resolve(lanes: int) -> int:
  """The number of lanes a run uses: 1 or 2 as asked, AUTO (0) -> 2 on a split CPU host, else 1.
  ValueError for any other value, or 2 where fewer than 2 devices exist."""
  if lanes not in (AUTO, 1, 2):
    raise ValueError(f"conceal.lanes must be 0 (automatic), 1 or 2, got {lanes!r}")
  devices = jax.local_device_count()
  if lanes == AUTO:
    return 2 if jax.default_backend() == "cpu" and devices >= 2 else 1
  if lanes > devices:
    raise ValueError(f"conceal.lanes={lanes} needs {lanes} devices, this host has {devices} "
                     f"(on a CPU, set XLA_FLAGS={HOST_DEVICES_FLAG}={lanes} before JAX starts)")
  return lanes


def lane_mesh(lanes: int) -> Mesh | None:
  """A mesh of the first `lanes` devices along LANE_AXIS; None for one lane."""
  return Mesh(jax.local_devices()[:lanes], (LANE_AXIS,)) if lanes > 1 else None


def replicate(tree, mesh: Mesh | None):
  """`tree` with every array on every device of `mesh` (a no-op for arrays already there, or without a mesh)."""
  return tree if mesh is None else jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def on_one_device(tree, mesh: Mesh | None):
  """`tree` on the first device only, so that work outside the step (evaluation) is not run once per lane."""
  return tree if mesh is None else jax.device_put(tree, jax.local_devices()[0])


def map_lanes(fn: Callable, shared, per_lane: Sequence, mesh: Mesh | None) -> list:
  """[fn(shared, x) for x in per_lane], differentiable in `shared` and `per_lane`.

  With a mesh of len(per_lane) devices and inputs of one structure and shape, lane i computes
  fn(shared, per_lane[i]) on device i, all at once (`shared` replicated); otherwise, in turn.

  The lanes meet once: every collective is a rendezvous in which the faster lane waits, and left to the
  partitioner the lego conceal step had 103 of them (the stacked inputs resharded by all-to-all, one
  all-gather per output leaf). Here each device picks its lane's input from the replicated stack, and the
  outputs travel as one flat vector per dtype (`_gather_flat`).
  """
  trees = [jax.tree.structure(x) for x in per_lane]
  shapes = [[jnp.shape(leaf) for leaf in jax.tree.leaves(x)] for x in per_lane]
  if mesh is None or len(per_lane) != mesh.size or any(t != trees[0] for t in trees) or any(
      s != shapes[0] for s in shapes):
    return [fn(shared, x) for x in per_lane]
  stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *per_lane)
  structure = []  # the output's treedef, leaf shapes and dtypes, set while tracing `lane`

  def lane(shared, stacked):
    index = jax.lax.axis_index(LANE_AXIS)
    out = fn(shared, jax.tree.map(lambda leaf: leaf[index], stacked))
    leaves, treedef = jax.tree.flatten(out)
    leaves = [jnp.asarray(leaf) for leaf in leaves]
    structure[:] = [treedef, [(leaf.shape, leaf.dtype) for leaf in leaves]]
    return _gather_flat(leaves)

  # check_vma off: the renderer's loops start from zeros that are the same on every lane and are updated
  # with lane data; after the all-gather every output is the same on every device (out_specs replicated),
  # and what follows runs as one replicated program (left to the partitioner, the code after the lanes was
  # split across the devices and ran slower than on one).
  gathered = jax.shard_map(lane, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec()), out_specs=PartitionSpec(),
                           check_vma=False)(shared, stacked)
  treedef, specs = structure
  return [jax.tree.unflatten(treedef, _split_flat(gathered, specs, i)) for i in range(len(per_lane))]


def _gather_flat(leaves: list) -> dict:
  """Inside a lane: {dtype name: [lanes, size]}, the lane's leaves of each dtype raveled into one vector and
  all-gathered over LANE_AXIS (one collective per dtype)."""
  groups = {}
  for leaf in leaves:
    groups.setdefault(leaf.dtype.name, []).append(leaf.ravel())
  return {name: jax.lax.all_gather(jnp.concatenate(parts), LANE_AXIS) for name, parts in groups.items()}


def _split_flat(gathered: dict, specs: list, lane: int) -> list:
  """Lane `lane`'s leaves (shapes and dtypes in `specs`) back from `_gather_flat`'s vectors."""
  offsets = {name: 0 for name in gathered}
  leaves = []
  for shape, dtype in specs:
    size, name = math.prod(shape), jnp.dtype(dtype).name
    leaves.append(gathered[name][lane, offsets[name]:offsets[name] + size].reshape(shape))
    offsets[name] += size
  return leaves
