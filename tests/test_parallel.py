"""Data parallelism over views (core.parallel): a teacher step's batch split over devices, the same steps on 1 and
on 4 host devices, and one teacher trained by two processes joined through jax.distributed on loopback."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.configs import default
from conceal_jax.core import checkpoint, loop, parallel
from conceal_jax.data import demo_scene, ply
from conceal_jax.gs import init, optimizer, train
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.render import RenderOptions
from tests.helpers import make_camera, random_gaussians
from tests.parallel_job import STEPS

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
needs_two = pytest.mark.skipif(jax.local_device_count() < 2, reason="needs two host devices (tests/conftest.py)")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  """A 32x32 demo scene of 6 training views and a start of random anisotropic Gaussians. (Isotropic ones, as
  init.gaussians_from_points makes, have a rotation gradient that is zero but for roundoff, which Adam's first
  steps turn into steps of the learning rate of either sign: no two summation orders agree there.)"""
  folder = tmp_path_factory.mktemp("parallel")
  scene_path = demo_scene.generate_demo_scene(folder / "scene", num_train=6, num_test=2, size=32)
  ply.save_ply(folder / "start.ply", jax.device_get(random_gaussians(0, 1200, degree=1)))
  return str(scene_path), str(folder / "start.ply")


def test_step_views_continue_the_epochs_shuffled_orders():
  """One view per step is 3D-GS's order (view_order per epoch); several take the next ones, across epochs."""
  one = [int(v) for i in range(1, 13) for v in train.step_views(7, i, 1, 6)]
  epochs = [int(v) for e in range(2) for v in train.view_order(7, e, 6)]
  assert one == epochs
  four = [train.step_views(7, i, 4, 6) for i in (1, 2, 3)]
  assert all(v.dtype == np.int32 and v.shape == (4,) for v in four)
  assert [int(v) for views in four for v in views] == epochs


@needs_two
def test_batch_mesh_takes_the_largest_device_count_dividing_the_batch():
  assert parallel.batch_mesh(1) is None and parallel.batch_mesh(3) is None
  assert parallel.batch_mesh(2).size == parallel.batch_mesh(4).size == 2
  with pytest.raises(ValueError, match="views per step"):
    parallel.check_batch(0)


@pytest.mark.parametrize("flags,env,message", [
    (dict(num_processes=2), {}, "coordinator"),
    (dict(num_processes=2, coordinator_address="127.0.0.1:1"), {}, "coordinator"),
    (dict(num_processes=2, coordinator_address="127.0.0.1:1", process_id=2), {}, r"0\.\.1"),
    (dict(process_id=1), {}, "one process"),
    ({}, dict(JAX_NUM_PROCESSES="two"), "integers"),
    (dict(num_processes=0), {}, ">= 1")])
def test_an_incomplete_process_setting_is_refused(monkeypatch, flags, env, message):
  """Every refusal comes before jax.distributed is started (which would block waiting for a coordinator)."""
  for name in parallel.PROCESS_ENV:
    monkeypatch.delenv(name, raising=False)
  for name, value in env.items():
    monkeypatch.setenv(name, value)
  with pytest.raises(ValueError, match=message):
    parallel.start_processes(**flags)


def test_one_process_starts_nothing(monkeypatch):
  for name in parallel.PROCESS_ENV:
    monkeypatch.delenv(name, raising=False)
  assert parallel.start_processes() == 1 and parallel.start_processes(num_processes=1, process_id=0) == 1
  monkeypatch.setenv("JAX_NUM_PROCESSES", "1")
  assert parallel.start_processes() == 1 and parallel.process_workdir("w") == "w"


@needs_two
def test_a_teacher_step_of_two_views_is_the_mean_of_its_views():
  """A step of views [a, b] split over two devices: its Adam first moment, linear in the gradient, is the mean
  of a step of view a's and of view b's from the same state, and its densification statistics are their sum
  (each view counts once). (One device against four: test_four_devices_train_and_conceal_as_one_does.)"""
  rng = np.random.default_rng(0)
  gaussians = random_gaussians(1, 400, degree=0)
  cameras = camera_lib.stack([make_camera(24, 24, eye=eye) for eye in ((0.0, -4.0, 1.0), (3.0, -3.0, 0.5))])
  images = jnp.asarray(rng.uniform(0.2, 0.8, (2, 24, 24, 3)), jnp.float32)
  options = RenderOptions(sh_degree=0, tile_size=8, pair_capacity=1 << 14)
  tx = optimizer.gaussian_optimizer(default.get_config().train.lr, 1.0, 100)
  fresh = lambda: train.create_train_state(gaussians, tx)
  mesh = parallel.batch_mesh(2)
  step = train.make_train_step(tx, options, 0.2, mesh=mesh)
  placed = parallel.replicate((images, cameras, np.array([0, 1], np.int32)), mesh)
  state, stats = jax.device_get(step(parallel.replicate(fresh(), mesh), *placed))
  single = train.make_train_step(tx, options, 0.2)
  (a, stats_a), (b, stats_b) = (jax.device_get(single(fresh(), images, cameras, view)) for view in (0, 1))
  assert stats_a["num_pairs"] > 0 and stats_b["num_pairs"] > 0 and not np.allclose(a.grad_accum, b.grad_accum)
  mu = lambda s: optimizer.adam_moments(s.opt_state).mu
  jax.tree.map(lambda got, x, y: assert_close_to_float_order(got, (x + y) / 2, "first moment"),
               mu(state), mu(a), mu(b))
  assert_close_to_float_order(state.grad_accum, a.grad_accum + b.grad_accum, "2D-mean gradient norms")
  np.testing.assert_array_equal(state.grad_count, a.grad_count + b.grad_count)
  np.testing.assert_array_equal(state.max_radii, np.maximum(a.max_radii, b.max_radii))
  np.testing.assert_allclose(stats["loss"], (stats_a["loss"] + stats_b["loss"]) / 2, rtol=1e-6)
  assert int(stats["num_pairs"]) == max(int(stats_a["num_pairs"]), int(stats_b["num_pairs"]))


def with_host_devices(count: int) -> dict:
  """The environment of a subprocess whose JAX starts with `count` host devices (other XLA flags kept)."""
  flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(parallel.HOST_DEVICES_FLAG)]
  return dict(os.environ, XLA_FLAGS=" ".join(flags + [f"{parallel.HOST_DEVICES_FLAG}={count}"]))


def checkpoint_leaves(job_dir) -> list[np.ndarray]:
  """The leaves of the job's checkpoint, which must be the one after parallel_job's steps."""
  _, meta, leaves = checkpoint.load_latest(os.path.join(job_dir, loop.CHECKPOINT_DIR))
  assert meta["step"] == STEPS
  return leaves


def assert_close_to_float_order(got, want, what: str) -> None:
  """Equal as sums over pixels and views in another order leave it: within 1e-4 of each value, or 1e-6 of the
  array's largest. An entry whose sum nearly cancels keeps a relative error well above float precision, and Adam,
  dividing a gradient by its root mean square, carries that error into the update."""
  scale = float(np.max(np.abs(want))) if np.size(want) else 0.0
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * scale, err_msg=what)


@pytest.mark.slow
def test_four_devices_train_and_conceal_as_one_does(tiny, tmp_path):
  """tests/parallel_job.py in two processes, one with one host device and one with four: a teacher taking four
  views per step (split four ways) and the concealment step's two views (split two ways) end with the same
  parameters, optimiser moments and densification statistics to float summation order."""
  for count in (1, 4):
    done = subprocess.run([sys.executable, "-m", "tests.parallel_job", str(tmp_path / str(count)), *tiny, "4"],
                          cwd=REPO, env=with_host_devices(count), capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
  devices = [json.loads((tmp_path / str(count) / "devices.json").read_text()) for count in (1, 4)]
  assert devices == [dict(devices=1, teacher=1, conceal=1), dict(devices=4, teacher=4, conceal=2)]
  for job in ("teacher", "conceal"):
    one, four = (checkpoint_leaves(tmp_path / str(count) / job) for count in (1, 4))
    assert len(one) == len(four) > 0
    for i, (a, b) in enumerate(zip(one, four)):
      assert_close_to_float_order(b, a, f"{job}: leaf {i}")


def free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


# Two processes joined through jax.distributed on loopback, summing one value over both: whether this platform
# (its jax, gloo, loopback sockets) can run several processes at all, before the test asks it to train.
PROBE = textwrap.dedent("""
    import sys
    import jax, numpy as np
    from jax.experimental import multihost_utils
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(sys.argv[1], 2, int(sys.argv[2]), initialization_timeout=60)
    print(int(np.sum(multihost_utils.process_allgather(np.array([jax.process_index() + 1])))))
    """)


def two_processes_unavailable() -> str | None:
  """None where two local processes can sum over each other, else why not (the probe's last error line)."""
  address = f"127.0.0.1:{free_port()}"
  env = with_host_devices(1)
  probes = [subprocess.Popen([sys.executable, "-c", PROBE, address, str(i)], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for i in range(2)]
  try:
    outs = [p.communicate(timeout=120) for p in probes]
  except subprocess.TimeoutExpired:
    for p in probes:
      p.kill()
    return "two jax.distributed processes on loopback did not finish a sum within 120 s"
  if all(p.returncode == 0 and out.split()[-1:] == ["3"] for p, (out, _) in zip(probes, outs)):
    return None
  errors = [line for _, err in outs for line in err.strip().splitlines()[-1:]]
  return f"two jax.distributed processes on loopback cannot sum over each other here: {errors}"


@pytest.mark.slow
def test_two_processes_train_the_teacher_one_process_trains(tiny, tmp_path):
  """`python -m conceal_jax.main` as two processes on this machine (one host device each; process 0 told by flags,
  process 1 by the environment) trains a teacher taking two views per step, one view on each process: both
  write the scene one process on two host devices trains, process 1 in its workdir/process_1."""
  reason = two_processes_unavailable()
  if reason:
    pytest.skip(reason)
  scene, start = tiny
  command = [sys.executable, "-m", "conceal_jax.main", "--config=conceal_jax/configs/demo.py", "--config.mode=train",
             f"--config.data.path={scene}", "--config.init.kind=ply", f"--config.init.ply={start}",
             "--config.train.iterations=3", "--config.train.views_per_step=2", "--config.train.densify.start=100",
             "--config.train.progress_bar=False", "--config.eval.max_views=1"]
  address = f"127.0.0.1:{free_port()}"
  env = with_host_devices(1)
  launched = [
      subprocess.Popen(command + [f"--workdir={tmp_path / 'two'}", f"--coordinator_address={address}",
                                  "--num_processes=2", "--process_id=0"], cwd=REPO, env=env,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True),
      subprocess.Popen(command + [f"--workdir={tmp_path / 'two'}"], cwd=REPO, stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True,
                       env=dict(env, JAX_COORDINATOR_ADDRESS=address, JAX_NUM_PROCESSES="2", JAX_PROCESS_ID="1"))]
  try:
    outs = [p.communicate(timeout=900)[0] for p in launched]
  finally:
    for p in launched:
      p.kill()
  for i, (p, out) in enumerate(zip(launched, outs)):
    assert p.returncode == 0, f"process {i}:\n{out[-3000:]}"
  one = subprocess.run(command + [f"--workdir={tmp_path / 'one'}"], cwd=REPO, env=with_host_devices(2),
                       capture_output=True, text=True, timeout=900)
  assert one.returncode == 0, one.stderr[-3000:]
  scenes = [ply.load_ply(tmp_path / folder / "point_cloud.ply") for folder in ("one", "two", "two/process_1")]
  start_scene = ply.load_ply(start)
  assert not np.allclose(scenes[0].means, start_scene.means), "the steps must have moved the scene"
  for other in scenes[1:]:
    jax.tree.map(lambda a, b: assert_close_to_float_order(b, a, "two processes' scene"), scenes[0], other)
  summaries = [json.loads((tmp_path / folder / "train.json").read_text()) for folder in ("two", "two/process_1")]
  assert [s["iterations"] for s in summaries] == [3, 3]
