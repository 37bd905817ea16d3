"""Data parallelism over a batch of views: a sum over the batch computed by several devices at once.

A step's gradient is a sum over views. `batch_mesh` makes a one-axis mesh of the devices that share a
batch, and `map_reduce_over_batch` computes sum_b fn(shared, batch_b) with each device taking its slice of the
batch and the partial sums added across devices; without a mesh, the examples in turn and their sum. The
values are the same either way, to float summation order.

XLA's CPU backend runs one computation's loops on one thread, so a 2-core host is worth splitting into two
XLA devices for a step that renders two views. That split is the process's choice, made before JAX starts
(`host_devices_flag`, set by `python -m conceal_jax.main --host_devices`), never by importing the library.

Several processes (several machines, or several on one) share a batch the same way: `start_processes` joins
them through `jax.distributed` before JAX starts, every process runs the same job on the same inputs, and the
mesh takes the same number of devices from each, so the sums run over all of them. Each process keeps the whole
state (replicated) and does the host-side work (densification, checkpoints, scoring) itself, on the same values.
"""
from __future__ import annotations

import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"
HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
# The environment variables start_processes reads where a flag is not given (the first is jax.distributed's own).
PROCESS_ENV = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")


def host_devices_flag(count: int) -> None:
  """Asks XLA for `count` host CPU devices (appended to XLA_FLAGS) unless the flag is already set. Only the
  process's entry point calls it, before JAX's backend starts; it has no effect afterwards."""
  flags = os.environ.get("XLA_FLAGS", "")
  if HOST_DEVICES_FLAG not in flags:
    os.environ["XLA_FLAGS"] = f"{flags} {HOST_DEVICES_FLAG}={count}".strip()


def start_processes(coordinator_address: str | None = None, num_processes: int | None = None,
                    process_id: int | None = None) -> int:
  """Joins this process to a run over `num_processes` processes (jax.distributed.initialize) and returns the
  count; each value not given is read from PROCESS_ENV, and without a count (or with 1) nothing is started and
  the run is this process alone. Called by the entry point before JAX's backend starts; on a CPU the processes'
  collectives go through gloo. ValueError for an incomplete or inconsistent setting."""
  env = dict(zip(("coordinator_address", "num_processes", "process_id"), (os.environ.get(k) for k in PROCESS_ENV)))
  coordinator_address = coordinator_address or env["coordinator_address"] or None
  try:
    num_processes = int(num_processes if num_processes is not None else env["num_processes"] or 1)
    process_id = None if process_id is None and not env["process_id"] else int(
        process_id if process_id is not None else env["process_id"])
  except ValueError as error:
    raise ValueError(f"{PROCESS_ENV[1]} and {PROCESS_ENV[2]} must be integers ({error})") from error
  if num_processes < 1:
    raise ValueError(f"the number of processes must be >= 1, got {num_processes}")
  if num_processes == 1:
    if process_id not in (None, 0):
      raise ValueError(f"process id {process_id} given for a run of one process (set the number of processes)")
    return 1
  if not coordinator_address or process_id is None:
    raise ValueError(f"a run over {num_processes} processes needs the coordinator's address (host:port of process "
                     f"0) and this process's id, as flags or as {PROCESS_ENV[0]} and {PROCESS_ENV[2]}")
  if not 0 <= process_id < num_processes:
    raise ValueError(f"process id must be in 0..{num_processes - 1}, got {process_id}")
  # gloo: the CPU backend's collectives across processes (without it a CPU psum stays within one process)
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(coordinator_address, num_processes, process_id)
  return num_processes


def process_workdir(workdir: str) -> str:
  """Where this process writes a job's files: `workdir` for process 0 (and a run of one process); the others,
  whose files are the same, write theirs to workdir/process_<id>, so processes sharing a file system never
  write the same file and each resumes from its own checkpoints."""
  index = jax.process_index()
  return workdir if index == 0 else os.path.join(workdir, f"process_{index}")


def check_batch(batch_size: int) -> None:
  """ValueError unless `batch_size` views can be shared by the processes of the run (a multiple of their count:
  each process takes the same number of views)."""
  processes = jax.process_count()
  if batch_size < 1 or batch_size % processes:
    raise ValueError(f"a step's {batch_size} views cannot be shared by {processes} processes: the views per step "
                     f"must be a multiple of the number of processes")


def batch_mesh(batch_size: int) -> Mesh | None:
  """A mesh over the largest number of devices that divides `batch_size`, the same number from every process
  (None where that is one device). One process: its local devices; several: the first devices of each, so that
  every process holds part of the mesh (check_batch's condition)."""
  check_batch(batch_size)
  processes = jax.process_count()
  per_process = max(n for n in range(1, min(jax.local_device_count(), batch_size // processes) + 1)
                    if batch_size % (n * processes) == 0)
  if per_process * processes == 1:
    return None
  devices = [device for p in range(processes)
             for device in sorted((d for d in jax.devices() if d.process_index == p), key=lambda d: d.id)[:per_process]]
  return Mesh(np.array(devices), (BATCH_AXIS,))


def replicate(tree, mesh: Mesh | None):
  """`tree` with every array on every device of `mesh` (as it is without a mesh). Across processes the values
  go through the host (device_put takes host values, the same on every process, or arrays already on the mesh)."""
  if mesh is None:
    return tree
  sharding = NamedSharding(mesh, PartitionSpec())
  if jax.process_count() > 1:
    tree = jax.tree.map(lambda x: x if getattr(x, "sharding", None) == sharding else np.asarray(x), tree)
  return jax.device_put(tree, sharding)


def on_one_device(tree, mesh: Mesh | None):
  """`tree` on this process's first device only, for work outside the step (evaluation runs once, not per
  device)."""
  if mesh is None:
    return tree
  if jax.process_count() > 1:  # a replicated array reads back on every process
    tree = jax.tree.map(np.asarray, tree)
  return jax.device_put(tree, jax.local_devices()[0])


def _by_dtype(tree):
  """(vectors {dtype name: the leaves of that dtype raveled into one vector}, a function that undoes it)."""
  leaves, treedef = jax.tree.flatten(tree)
  names = [jnp.asarray(leaf).dtype.name for leaf in leaves]
  packed = {name: ravel_pytree([leaf for leaf, n in zip(leaves, names) if n == name]) for name in dict.fromkeys(names)}

  def unpack(vectors):
    groups = {name: iter(packed[name][1](vector)) for name, vector in vectors.items()}
    return jax.tree.unflatten(treedef, [next(groups[name]) for name in names])

  return {name: vector for name, (vector, _) in packed.items()}, unpack


def map_reduce_over_batch(fn: Callable, shared, batch, mesh: Mesh | None):
  """(sum_b s_b, stacked e_b) where fn(shared, batch[b]) = (s_b, e_b), over the leading axis of every leaf of
  `batch` (static and small: the examples are unrolled): s_b are what adds up over the batch (losses,
  gradients), e_b what is kept per example (scalars, or arrays such as a view's screen radii). On a mesh each
  device maps its slice; the sums meet in one psum and the kept values in one all-gather per dtype (the leaves
  raveled into one vector each), and both come back replicated."""

  def local(shared, part):
    # the examples of a slice in turn (unrolled), not vmapped: batching the renderer's loops and scatters
    # costs a CPU more than running them one after the other
    outs = [fn(shared, jax.tree.map(lambda x, i=i: x[i], part)) for i in range(jax.tree.leaves(part)[0].shape[0])]
    sums = jax.tree.map(lambda *xs: sum(xs[1:], xs[0]), *[o[0] for o in outs])
    return sums, jax.tree.map(lambda *xs: jnp.stack(xs), *[o[1] for o in outs])

  if mesh is None:
    return local(shared, batch)
  unpackers = []
  size = jax.tree.leaves(batch)[0].shape[0] // mesh.size

  def on_device(shared, batch):
    # each device picks its slice of the batch, which reaches it whole (replicated, as the step builds it):
    # handing it in sharded made the partitioner move it with an all-to-all, one more rendezvous per step
    start = jax.lax.axis_index(BATCH_AXIS) * size
    sums, each = local(shared, jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, size), batch))
    (sum_vectors, unpack_sums), (each_vectors, unpack_each) = _by_dtype(sums), _by_dtype(each)
    unpackers[:] = [unpack_sums, unpack_each]
    return ({name: jax.lax.psum(v, BATCH_AXIS) for name, v in sum_vectors.items()},
            {name: jax.lax.all_gather(v, BATCH_AXIS) for name, v in each_vectors.items()})

  # check_vma off: both outputs are combined over the axis, the same on every device (out_specs replicated)
  sums, gathered = jax.shard_map(on_device, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec()),
                                 out_specs=PartitionSpec(), check_vma=False)(shared, batch)
  unpack_sums, unpack_each = unpackers
  # gathered: [devices, per-device slice size] per dtype; the kept leaves back to [batch, ...] in batch order
  per_device = [unpack_each({name: v[d] for name, v in gathered.items()}) for d in range(mesh.size)]
  return unpack_sums(sums), jax.tree.map(lambda *xs: jnp.concatenate(xs), *per_device)
