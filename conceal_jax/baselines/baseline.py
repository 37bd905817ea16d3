"""The baseline job, `--config.mode=baseline`: LSB, DeepStega or StegaNeRF, the ways to hide an image that
ConcealGS (Yang et al. 2025, arXiv:2501.03605, Tables 1-2) compares with, trained and scored like a
concealment run.

LSB and DeepStega hide the image in the views, then 3D-GS is trained on them:
1. The hidden image (mark.hidden) goes into every training view, so also the check view's: the views
   become containers (lsb.py; deepstega.py, whose networks are first trained on natural-image crops in
   <workdir>/deepstega, or read from baseline.deepstega.networks).
2. A 3D-GS scene is trained on the containers from the teacher (mark.teacher) with the concealment
   run's recipe (gs.train in <workdir>/train, checkpointed and resumable): its learning rates
   (conceal.lr), its length (baseline.iterations, 0: conceal.iterations), the teacher's SH degree, and no
   densification or opacity reset, since the concealment run refines the teacher's Gaussians as they are.
StegaNeRF hides it in the scene itself (steganerf.py, steganerf_train.py): the teacher's SH colour, a
decoder and a classifier are trained jointly for the same length, the geometry frozen, checkpointed in
<workdir>/checkpoints; baseline.steganerf.protocol says whether every view or only the check view carries I.

3. The trained scene is scored by conceal.scoring.evaluate_concealment at the mark section's key (key_kind,
   key_index, key_seed) with the method's reveal function in the decoder's place, so every row of the
   paper's table is measured with the same views, key and metrics. Each baseline's own protocol hides I
   in every view, so baseline.json also has the hidden image's PSNR / SSIM over the test views.

Writes metrics.json, revealed.png, teacher_revealed.png, normal_revealed.png, hidden.png and baseline.json:
method, settings, the training's wall time, the hidden scores over the test views and, for LSB and
DeepStega, container_revealed.png (what the method reveals from the check view's own container, before
any 3D-GS training) and the containers' quality; for DeepStega the networks' own quality on held-out
images; for StegaNeRF its run's summary (steganerf.json; student.ply and the networks beside it).
"""
from __future__ import annotations

import copy
import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.baselines import containers as containers_lib
from conceal_jax.baselines import deepstega, deepstega_train, lsb, steganerf, steganerf_train
from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, scoring
from conceal_jax.core import fileio, loop, settings as settings_lib
from conceal_jax.data import datasets, ply
from conceal_jax.gs import evaluate, metrics, train

METHODS = ("lsb", "deepstega", "steganerf")
METHOD_NAMES = dict(lsb="LSB", deepstega="DeepStega", steganerf="StegaNeRF")  # as the paper's tables name them
BASELINE_FILE = "baseline.json"
TRAIN_DIR = "train"
NETWORKS_DIR = "deepstega"
NETWORKS_FILE = "networks.msgpack"
NETWORKS_REPORT = "deepstega.json"


@dataclasses.dataclass(frozen=True)
class BaselineSettings:
  """The baseline section's choice of method and run length (the rest is the conceal section's)."""
  method: str = "lsb"
  iterations: int = 0
  lsb_bits: int = 1

  def __post_init__(self):
    if self.method not in METHODS:
      raise ValueError(f"baseline.method must be one of {METHODS}, got {self.method!r}")
    settings_lib.check_count("baseline.iterations (0: conceal.iterations)", self.iterations, minimum=0)
    lsb.check_bits(self.lsb_bits)


def settings_from_config(config: ml_collections.ConfigDict) -> BaselineSettings:
  return settings_lib.from_section(BaselineSettings, config.baseline)


def deepstega_settings(config: ml_collections.ConfigDict):
  """(architecture, training settings, loop settings) of the DeepStega networks, from baseline.deepstega."""
  d = config.baseline.deepstega
  return (settings_lib.from_section(deepstega.Architecture, d),
          settings_lib.from_section(deepstega_train.StegaTrainSettings, d),
          settings_lib.from_section(loop.LoopSettings, d))


def run_length(config: ml_collections.ConfigDict) -> int:
  """Steps of the baseline's training: baseline.iterations, or conceal.iterations where it is 0 (the same
  length as the concealment run)."""
  return settings_from_config(config).iterations or config.conceal.iterations


def training_config(config: ml_collections.ConfigDict, sh_degree: int) -> ml_collections.ConfigDict:
  """A copy of `config` whose train and init sections are the concealment run's recipe: start from the
  teacher, conceal.lr, conceal.iterations unless baseline.iterations, SH degree `sh_degree` (the
  teacher's) from the first step, no densification or opacity reset (densify.until = 0), no snapshots."""
  t = copy.deepcopy(config)
  t.mode = "train"
  t.init.kind, t.init.ply = "ply", config.mark.teacher
  t.train.iterations = run_length(config)
  t.train.lr = ml_collections.ConfigDict(config.conceal.lr.to_dict())
  t.train.sh_degree = t.train.sh_degree_start = sh_degree
  t.train.densify.until = 0
  t.train.snapshots = ()
  return t


def validate(config: ml_collections.ConfigDict) -> None:
  """Every value the baseline job reads, checked before anything runs (ValueError naming the key)."""
  s = settings_from_config(config)
  m = config.mark
  if s.method == "deepstega":
    deepstega_settings(config)
    networks = config.baseline.deepstega.networks
    if networks and not os.path.isfile(networks):
      raise ValueError(f"baseline.deepstega.networks: no such file {networks}")
  if s.method == "steganerf":
    steganerf.settings_from_config(config)
    steganerf_train.loop_settings(config, run_length(config))
  if m.key_kind not in key_lib.KEY_KINDS:
    raise ValueError(f"mark.key_kind must be one of {key_lib.KEY_KINDS}, got {m.key_kind!r}")
  settings_lib.check_count("mark.hidden_size", m.hidden_size)
  if m.extra_hidden:
    raise ValueError("mark.extra_hidden: the baselines hide one image (mark.hidden); leave it empty")
  if not m.teacher:
    raise ValueError("mark.teacher (the teacher's .ply) is required")
  if not os.path.isfile(m.teacher):
    raise ValueError(f"mark.teacher: no such file {m.teacher}")
  train.validate(training_config(config, config.train.sh_degree))


def view_size(scene: datasets.SceneData) -> tuple[int, int]:
  """(H, W) of the training views; ValueError if they differ (one hidden image fits them all)."""
  sizes = sorted({np.shape(image)[:2] for image in scene.train_images})
  if len(sizes) != 1:
    raise ValueError(f"the baselines need training views of one size, got sizes {sizes}")
  return sizes[0]


def lsb_containers(config: ml_collections.ConfigDict, scene: datasets.SceneData, secret: np.ndarray,
                   workdir: str):
  """(containers [V, H, W, 3], reveal function, report) of LSB with baseline.lsb_bits bits."""
  del workdir  # LSB has nothing to train or save
  bits = settings_from_config(config).lsb_bits
  containers = lsb.embed(np.stack(scene.train_images), secret, bits)
  return containers, lsb.lsb_reveal(bits, config.mark.hidden_size), dict(lsb_bits=bits)


def deepstega_networks(config: ml_collections.ConfigDict, scene: datasets.SceneData, workdir: str):
  """(params, architecture, report): the networks of baseline.deepstega.networks, else of
  <workdir>/deepstega, trained there first (resumable) if that folder holds none yet. The report has the
  training's (when run here) and the networks' own quality on held-out images, measured here."""
  arch, train_settings, loop_settings = deepstega_settings(config)
  path = config.baseline.deepstega.networks or os.path.join(workdir, NETWORKS_DIR, NETWORKS_FILE)
  training_path = os.path.join(os.path.dirname(path), NETWORKS_REPORT)
  if os.path.isfile(path):
    params, arch = deepstega.load_networks(path)
    report = dict(reused=True)
    if os.path.isfile(training_path):  # written where the networks were trained
      with open(training_path) as f:
        report["training"] = json.load(f)
  else:
    params, training = deepstega_train.train_networks(arch, train_settings, loop_settings, os.path.dirname(path),
                                                      scene.train_images, config.mark.hidden, config.seed)
    deepstega.save_networks(path, params, arch)
    fileio.write_json(training_path, training)
    report = dict(reused=False, training=training)
  if "training" in report:
    report["training"] = {k: v for k, v in report["training"].items() if k != "history"}  # kept in its own file
  report.update(networks=path, architecture=dataclasses.asdict(arch),
                held_out=deepstega_train.held_out_quality(params, arch, train_settings, scene.train_images,
                                                          scene.test_images, config.mark.hidden, config.seed))
  return params, arch, report


def deepstega_containers(config: ml_collections.ConfigDict, scene: datasets.SceneData, secret: np.ndarray,
                         workdir: str):
  """(containers [V, H, W, 3], reveal function, report) of DeepStega: every training view hides `secret`."""
  params, arch, report = deepstega_networks(config, scene, workdir)
  containers = deepstega.hide_in_views(params, arch, np.stack(scene.train_images), secret)
  return containers, deepstega.stega_reveal(params, arch, config.mark.hidden_size), dict(deepstega=report)


CONTAINERS = dict(lsb=lsb_containers, deepstega=deepstega_containers)


def container_quality(scene: datasets.SceneData, containers, reveal_fn, hidden: np.ndarray, key_info: dict,
                      workdir: str) -> dict:
  """How far the containers are from the training views (mean PSNR / SSIM), and what `reveal_fn` reveals
  from the check view's own container (PSNR / SSIM to `hidden`, written as container_revealed.png): the
  method's quality before any 3D-GS training. An orbit key has no container: that part is None."""
  views = jnp.asarray(np.stack(scene.train_images))
  result = dict(psnr_to_views=float(np.mean(jax.vmap(metrics.psnr)(containers, views))),
                ssim_to_views=float(np.mean(metrics.batched_ssim(containers, views))), check_view_hidden=None)
  if key_info["kind"] == "train_index":
    revealed = np.asarray(reveal_fn(containers[key_info["index"]][None]))
    scores = scoring.scores_to_hidden(revealed, hidden)
    result["check_view_hidden"] = dict(psnr=float(scores["psnr"][0]), ssim=float(scores["ssim"][0]))
    fileio.write_image(os.path.join(workdir, "container_revealed.png"), revealed[0])
  return result


def train_on_containers(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None, teacher,
                        hidden: np.ndarray, scene: datasets.SceneData, key_info: dict) -> dict:
  """LSB / DeepStega: the containers, then 3D-GS trained on them in <workdir>/train. dict(stopped_at) when
  max_steps stopped the training; else the trained `gaussians`, their `reveal_fn`, the training's numbers
  (train.json's), the `student` path, the containers' quality and the method's report."""
  s = settings_from_config(config)
  secret = containers_lib.hidden_at_view(config.mark.hidden, *view_size(scene))
  containers, reveal_fn, method_report = CONTAINERS[s.method](config, scene, secret, workdir)
  train_dir = os.path.join(workdir, TRAIN_DIR)
  trained = train.train_and_evaluate(training_config(config, teacher.sh_degree), train_dir, max_steps,
                                     scene=containers_lib.container_scene(scene, containers), score=False)
  if "stopped_at" in trained:
    return trained
  student = os.path.join(train_dir, evaluate.SCENE_FILE)
  return dict(gaussians=ply.load_ply(student), reveal_fn=reveal_fn, student=student,
              containers=container_quality(scene, containers, reveal_fn, hidden, key_info, workdir),
              **{k: trained[k] for k in ("iterations", "num_gaussians", "wall_time_s", "median_step_s",
                                         "resumed_from")}, **method_report)


def hidden_over_test_views(config: ml_collections.ConfigDict, scene: datasets.SceneData, gaussians, reveal_fn,
                           hidden: np.ndarray) -> dict:
  """What `reveal_fn` reveals from the scene's renders of the test views (eval.max_views of them, rendered
  as evaluate_concealment renders them): mean and lowest PSNR / SSIM to `hidden`, the number a baseline's
  own protocol (I in every view) reports."""
  cameras, _, _ = evaluate.held_out_views(scene, config.eval.max_views)
  renders = evaluate.render_images(gaussians, cameras, evaluate.eval_options(config, scene.background))
  scores = scoring.scores_to_hidden(reveal_fn(renders), hidden)
  return dict(mean_psnr=float(scores["psnr"].mean()), mean_ssim=float(scores["ssim"].mean()),
              min_psnr=float(scores["psnr"].min()), min_ssim=float(scores["ssim"].min()), num_views=len(cameras))


def baseline_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None) -> dict:
  """Trains the baseline (max_steps: stop that training there, as if killed, leaving its checkpoint to resume
  from), scores the result; writes the files the module docstring lists and returns baseline.json's
  contents with the metrics."""
  validate(config)
  s = settings_from_config(config)
  c = config.mark
  teacher = ply.load_ply(c.teacher)
  hidden = hidden_lib.load_hidden_image(c.hidden, c.hidden_size)
  scene = evaluate.load_scene_data(config)
  check_camera, key_info = key_lib.check_camera(scene.train_cameras, c.key_kind, c.key_index, c.key_seed,
                                                c.key_offset)
  options = evaluate.render_options(config, scene.background)
  if s.method == "steganerf":
    run = steganerf_train.train_steganerf(config, workdir, run_length(config), teacher, hidden, scene, check_camera,
                                          options, max_steps)
  else:
    run = train_on_containers(config, workdir, max_steps, teacher, hidden, scene, key_info)
  if "stopped_at" in run:
    return run

  gaussians, reveal_fn = run.pop("gaussians"), run.pop("reveal_fn")
  fileio.write_image(os.path.join(workdir, "hidden.png"), hidden)
  scored = scoring.evaluate_concealment(config, workdir, scene, teacher, gaussians, reveal_fn, [check_camera],
                                        [hidden], options)
  summary = dict(method=METHOD_NAMES[s.method], seed=config.seed, key=key_info, hidden=c.hidden,
                 hidden_size=c.hidden_size,
                 test_views_hidden=hidden_over_test_views(config, scene, gaussians, reveal_fn, hidden), **run)
  fileio.write_json(os.path.join(workdir, BASELINE_FILE), summary)
  return dict(summary, metrics=scored)
