"""Scoring a marked scene: hidden-image recovery at its keys, render quality, and leakage.

Shared by ConcealGS, the baselines and the attacks, none of which imports another's job. A scorer is given
a `reveal_fn`, renders [V, H, W, 3] -> revealed images [V, S, S, 3] (reveal.decoder_reveal for a ConcealGS
decoder; a baseline has its own way of reading the image out of a render), so every method is scored alike.

Leakage is what the decoder reveals where it should not: on the student's own test views (what a viewer
of the shared scene sees), at the clean teacher's check view (the key without the mark), and at poses near
the key (what someone guessing the key would try). Its floor is the same decoder on the clean teacher's
test renders: the SSIM an unmarked scene scores (a bright image shares some structure with any hidden one).
"""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import near
from conceal_jax.core import fileio
from conceal_jax.gs import evaluate, metrics
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions, render

# Leakage near the key: the student at the check pose moved by these fractions of the key's near-key length
# (near.near_length: the depth of the scene as the key sees it), or turned by these degrees, each along / about the
# key's own axes both ways (near.KEY_AXES) and in NEAR_DIRECTIONS random directions.
NEAR_TRANSLATIONS = (0.02, 0.05)
NEAR_ROTATIONS_DEG = (2.0, 5.0)
NEAR_DIRECTIONS = 4


def scores_to_hidden(revealed, hidden) -> dict[str, np.ndarray]:
  """PSNR and SSIM [V] of revealed images [V, S, S, 3] to the hidden image I [S, S, 3]; given several hidden
  images [J, S, S, 3], each view's best over them (each score on its own): leakage of any of them."""
  if np.ndim(hidden) == 4:
    each = [scores_to_hidden(revealed, image) for image in hidden]
    return {name: np.max([scores[name] for scores in each], axis=0) for name in ("psnr", "ssim")}
  revealed = jnp.asarray(revealed)
  hidden = jnp.broadcast_to(jnp.asarray(hidden), revealed.shape)
  return dict(psnr=np.asarray(jax.vmap(metrics.psnr)(revealed, hidden), np.float64),
              ssim=np.asarray(metrics.batched_ssim(revealed, hidden), np.float64))


def near_key_rows(gaussians, check_camera: Camera, options: RenderOptions, reveal_fn, hidden, length: float,
                  translations=NEAR_TRANSLATIONS, rotations_deg=NEAR_ROTATIONS_DEG,
                  directions: int = NEAR_DIRECTIONS) -> list[dict]:
  """What `reveal_fn` reveals at poses near the key (near.nearby_cameras): per (kind, value), the mean and max
  SSIM and the mean PSNR to I over the directions (to the best of several hidden images); translations
  are fractions of `length`, the key's near.near_length."""
  poses = near.nearby_cameras(check_camera, length, translations, rotations_deg, directions)
  renders = evaluate.render_images(gaussians, [camera for _, _, camera in poses], options)
  scores = scores_to_hidden(reveal_fn(renders), hidden)
  rows = []
  for kind, value in dict.fromkeys((kind, value) for kind, value, _ in poses):
    mine = np.array([(k, v) == (kind, value) for k, v, _ in poses])
    rows.append(dict(kind=kind, value=value, unit="fraction of key depth" if kind == "translation" else "degrees",
                     mean_ssim=float(scores["ssim"][mine].mean()), max_ssim=float(scores["ssim"][mine].max()),
                     mean_psnr=float(scores["psnr"][mine].mean())))
  return rows


def pooled_near_rows(rows_per_key: list[list[dict]]) -> list[dict]:
  """near_key_rows of K keys (the same poses relative to each key) as one list: per (kind, value), the mean
  over keys of mean_ssim and mean_psnr and the max of max_ssim."""
  return [dict(rows[0], mean_ssim=float(np.mean([r["mean_ssim"] for r in rows])),
               max_ssim=max(r["max_ssim"] for r in rows), mean_psnr=float(np.mean([r["mean_psnr"] for r in rows])))
          for rows in zip(*rows_per_key)]


def key_scores(revealed, hiddens: np.ndarray, near_rows: list[list[dict]], teacher_ssim) -> dict:
  """metrics.json's `keys` for K keys, from the images revealed at them [K][S, S, 3], the hidden images
  [K, S, S, 3], each key's near-key rows and the SSIM [K][K] of the clean teacher's reveal at key i to image
  j: `hidden` (per key: PSNR / SSIM of its own image, its leakage near the key and at the clean teacher),
  `cross_talk_ssim` [K][K] (row i revealed at key i, column j: SSIM to image j), `max_cross_talk` (the
  largest off-diagonal entry) and `images_ssim` [K][K] (the hidden images' SSIM to each other: the
  cross-talk of a perfect reveal)."""
  cross = [[float(metrics.ssim(image, h)) for h in hiddens] for image in revealed]
  num = len(hiddens)
  return dict(hidden=[dict(psnr=float(metrics.psnr(image, hiddens[i])), ssim=cross[i][i],
                           max_ssim_near_key=max(row["max_ssim"] for row in near_rows[i]),
                           ssim_teacher_at_key=max(teacher_ssim[i])) for i, image in enumerate(revealed)],
              cross_talk_ssim=cross, max_cross_talk=max(cross[i][j] for i in range(num) for j in range(num) if i != j),
              images_ssim=[[float(metrics.ssim(a, b)) for b in hiddens] for a in hiddens])


def reveal_at_keys(scene_gaussians, keys, options: RenderOptions, reveal_fn) -> list[np.ndarray]:
  """[K][S, S, 3] what `reveal_fn` reveals at each key camera, each rendered alone as the reveal job does."""
  return [np.asarray(reveal_fn(render(scene_gaussians, camera, options).rgb[None])[0]) for camera in keys]


def leakage_scores(config, workdir: str, scene, teacher, student, reveal_fn, key_cameras: list[Camera],
                   hiddens: np.ndarray, options: RenderOptions) -> dict:
  """Render quality of student and teacher on the test split and the leakage figures (module doc) over
  every hidden image [K, S, S, 3]; writes the student's test renders and normal_revealed.png (the test
  view whose decoder output looks most like a hidden image). `near_key_length` per key: the length its
  near-key translations are fractions of (near.near_length of the clean `teacher`), what it is, and the
  scene extent beside it; `near_poses`: the directions each near-key move and turn is scored in (the key's
  own axes, random ones), which figures scored before the axes were added lack."""
  eval_opts = evaluate.eval_options(config, scene.background)
  cameras, targets, names = evaluate.held_out_views(scene, config.eval.max_views)
  student_renders = evaluate.render_images(student, cameras, eval_opts)
  teacher_renders = evaluate.render_images(teacher, cameras, eval_opts)
  evaluate.write_images(os.path.join(workdir, "test_renders"), names, student_renders)
  normal_revealed = reveal_fn(student_renders)
  ssim_to_hidden = scores_to_hidden(normal_revealed, hiddens)["ssim"]
  worst = int(np.argmax(ssim_to_hidden))
  fileio.write_image(os.path.join(workdir, "normal_revealed.png"), np.asarray(normal_revealed[worst]))
  floor_ssim = scores_to_hidden(reveal_fn(teacher_renders), hiddens)["ssim"]
  lengths = [near.near_length(teacher, camera, scene.train_cameras) for camera in key_cameras]
  near_rows = [near_key_rows(student, camera, options, reveal_fn, hiddens, length)
               for camera, (length, _) in zip(key_cameras, lengths)]
  net = config.eval.lpips_net
  return dict(
      student_vs_ground_truth=evaluate.image_metrics(student_renders, targets, names, net)["mean"],
      teacher_vs_ground_truth=evaluate.image_metrics(teacher_renders, targets, names, net)["mean"],
      student_vs_teacher=evaluate.image_metrics(student_renders, teacher_renders, names, net)["mean"],
      leakage_worst_test_view=names[worst], max_ssim_student_test_views=float(ssim_to_hidden.max()),
      leakage_floor=dict(max_ssim_teacher_test_views=float(floor_ssim.max()),
                         ssim_teacher_at_worst_test_view=float(floor_ssim[worst])),
      near_rows=near_rows, num_test_views=len(names), lpips_net=metrics.LPIPS_NET_NAME[net],
      near_key_length=[dict(length=length, source=source, scene_extent=scene.scene_extent())
                       for length, source in lengths],
      near_poses=dict(key_axes=len(near.KEY_AXES), random_directions=NEAR_DIRECTIONS),
      eval_render_options=repr(eval_opts))


def evaluate_concealment(config, workdir: str, scene, teacher, student, reveal_fn, key_cameras: list[Camera],
                         hiddens, options: RenderOptions) -> dict:
  """metrics.json: render quality (student and teacher against ground truth, the student against the
  teacher), hidden-image recovery at the first key, leakage and its floor (module doc), and with several
  keys `keys` (see `key_scores`). Images: revealed.png (student, first key), teacher_revealed.png (clean
  teacher, first key), revealed_key<k>.png (the k-th extra key) and normal_revealed.png. `key_cameras` [K]
  and `hiddens` [K, S, S, 3]: each key and its image, the first the check view."""
  hiddens = np.stack([np.asarray(h) for h in hiddens])
  revealed = reveal_at_keys(student, key_cameras, options, reveal_fn)
  teacher_revealed = reveal_at_keys(teacher, key_cameras, options, reveal_fn)
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed[0])
  fileio.write_image(os.path.join(workdir, "teacher_revealed.png"), teacher_revealed[0])
  for k, image in enumerate(revealed[1:], 1):
    fileio.write_image(os.path.join(workdir, f"revealed_key{k}.png"), image)
  scored = leakage_scores(config, workdir, scene, teacher, student, reveal_fn, key_cameras, hiddens, options)
  near_rows, student_views = scored.pop("near_rows"), scored.pop("max_ssim_student_test_views")
  near_check = pooled_near_rows(near_rows)
  teacher_ssim = [[float(metrics.ssim(image, h)) for h in hiddens] for image in teacher_revealed]
  result = dict(scored, hidden=dict(psnr=float(metrics.psnr(revealed[0], hiddens[0])),
                                    ssim=float(metrics.ssim(revealed[0], hiddens[0]))),
                leakage=dict(max_ssim_student_test_views=student_views,
                             ssim_teacher_check_view=max(max(row) for row in teacher_ssim),
                             max_ssim_near_check=max(row["max_ssim"] for row in near_check)),
                near_check=near_check)
  if len(hiddens) > 1:
    result["keys"] = key_scores(revealed, hiddens, near_rows, teacher_ssim)
  fileio.write_json(os.path.join(workdir, evaluate.METRICS_FILE), result)
  return result
