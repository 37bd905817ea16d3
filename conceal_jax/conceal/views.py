"""What a concealment step reads: the run's device-resident data, and the two `View`s of one step.

`build_data` renders the teacher once per run at every normal view (the V training cameras, then the D
decoys near the keys) and at every key; `step_views` picks one step's normal view and key from it and
lays out the weights of each term (objective.View).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from conceal_jax.conceal import augment, key as key_lib, linear_check, reveal, subsets
from conceal_jax.conceal.key import Key
from conceal_jax.conceal.objective import View
from conceal_jax.conceal.settings import ConcealSettings, RunPlan
from conceal_jax.core import parallel
from conceal_jax.gs import evaluate
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions, render_batch

# augment.distort and perturb.perturb_gaussians with these levels are the identity (a point kernel, zero noise, no
# dropout, brightness 0, contrast 1): the distortion of a view that is not distorted
NO_DISTORTION = dict(blur=np.float32(0.0), noise=np.float32(0.0), seed=np.uint32(0), dropout=np.float32(0.0),
                     param_noise=np.float32(0.0), model_seed=np.uint32(0), brightness=np.float32(0.0),
                     contrast=np.float32(1.0), quantize=np.float32(0.0), reset=np.float32(0.0),
                     rounding=np.float32(0.5), merge=np.float32(0.0), prune_small=np.float32(0.0))


@struct.dataclass
class ConcealData:
  """images [V, H, W, 3]: ground truth of the training views; teacher [V + D, H, W, 3] and teacher_small
  [V + D, S, S, 3]: the teacher's renders of the normal views (training views, then decoys) at the render's
  and the decoder's size; cameras: Camera [V + D]; keys: Key [K]; colour_rows: None (the whole student trains)
  or int32 [F] the rows whose base colours alone train (carrier.colour_rows); merges: None or the rounds of the carrier
  film's pairs a decimation merges (decimate.film_merges, for conceal.attacks.merge_fraction); ties: None or the
  int32 [S, stack] rows of colour_rows in each of the film's stacks, each training as one (carrier.tied_rows); rows:
  None (every render reads the whole student) or int32 [V + D + K, M] the student rows the normal views' then the
  keys' renders read (subsets.view_rows), with fixed [V + D] bool: the normal views rendered by no row that trains,
  whose render is the teacher's; check_weights: None or the keys' renders as linear maps of the colours
  (linear_check.check_weights: linear.ColourWeights [K * L]), which the check views that draw no 8-bit grid are
  read through; normal_weights: None or the renders of the normal views that are not fixed as linear maps
  (linear_check.normal_weights: linear.ColourWeights [R]), with normal_maps int32 [V + D]: each normal view's index
  among them (-1: fixed), which those views are read through. The two stacks hold maps of one length, so that a
  step's two views stack whichever they read. held: None (every normal view) or bool [V + D]: the normal views whose
  student render L_d^- holds to F's identity (beyond the key tolerance radius; tolerance.held_to_identity). keys: the
  run's keys, then the poses within the key tolerance radius of each (tolerance.check_views), key by key."""
  images: jax.Array
  teacher: jax.Array
  teacher_small: jax.Array
  cameras: Camera
  keys: Key
  colour_rows: Any = None
  merges: Any = None
  ties: Any = None
  rows: Any = None
  fixed: Any = None
  check_weights: Any = None
  normal_weights: Any = None
  normal_maps: Any = None
  held: Any = None


def build_data(train_images, teacher, options: RenderOptions, normal_cameras: list[Camera], key_cameras, hiddens,
               size: int, clip: bool = False, key_images=None, colour_rows=None, merges=None,
               ties=None, at_decoder_size: bool = False, held_to_identity=None, student=None,
               check_states: int = 0, linear_maps_mb: float = 0.0) -> ConcealData:
  """The device-resident inputs of the concealment step. `normal_cameras`: the training cameras then the
  decoys; `key_cameras` and `hiddens` [S, S, 3]: one of each per key; `key_images` [H, W, 3]: the released
  variant's check-view targets of the first len(key_images) keys (None: of none; the teacher's renders at the
  others); `colour_rows`, `merges`, `ties`, `held_to_identity` (held): ConcealData's. The teacher renders at the
  decoder size are clipped to [0, 1] first with `clip` (reveal.Reading).
  With `at_decoder_size` (conceal.carrier.at_decoder_size: the decoys and keys are S x S cameras), the training
  views' renders are the teacher's resized as the decoder reads them, their cameras the same views at S x S.
  With `student` (where only colour_rows train), ConcealData's rows and fixed: every render reads colour_rows; and
  with `check_states` (linear_check.states, where linear_check.applies) its check_weights, and within
  `linear_maps_mb` MB (conceal.carrier.linear_maps_mb) its normal_weights."""
  if at_decoder_size:
    views, decoys = normal_cameras[:len(train_images)], normal_cameras[len(train_images):]
    teacher_renders = jnp.concatenate(
        [reveal.resize_for_decoder(evaluate.render_images(teacher, views, options), size, clip)]
        + ([evaluate.render_images(teacher, decoys, options)] if decoys else []))
    normal_cameras = [camera.resized(size, size) for camera in views] + decoys
  else:
    teacher_renders = evaluate.render_images(teacher, normal_cameras, options)
  key_stack = camera_lib.stack(list(key_cameras))
  teacher_keys = render_batch(teacher, key_stack, options).rgb
  check_images = list(key_images or []) + list(teacher_keys[len(key_images or []):])
  keys = key_lib.stack_keys(key_cameras, hiddens, check_images, reveal.resize_for_decoder(teacher_keys, size, clip))
  rows = fixed = normal_weights = normal_maps = None
  if student is not None:
    fixed = np.arange(len(normal_cameras)) < len(train_images)
    always = np.isin(np.arange(student.num), np.asarray(colour_rows))  # what trains is read by every render
    rows = jnp.asarray(subsets.view_rows(student, list(normal_cameras) + list(key_cameras), options, always,
                                         np.concatenate([fixed, np.zeros(len(key_cameras), bool)])))
    if linear_maps_mb > 0:
      normal_weights, normal_maps = linear_check.normal_weights(student, normal_cameras, np.asarray(rows), fixed,
                                                                options, linear_maps_mb)
  data = ConcealData(images=jnp.asarray(np.stack(train_images)), teacher=teacher_renders,
                   teacher_small=reveal.resize_for_decoder(teacher_renders, size, clip),
                   cameras=camera_lib.stack(list(normal_cameras)), keys=keys, colour_rows=colour_rows, merges=merges,
                   ties=ties, rows=rows, fixed=None if fixed is None else jnp.asarray(fixed),
                   normal_weights=normal_weights, normal_maps=normal_maps,
                   held=None if held_to_identity is None else jnp.asarray(held_to_identity))
  return regrouped(data, student, merges, options, check_states) if student is not None and check_states else data


def regrouped(data: ConcealData, student, merges, options: RenderOptions, check_states: int,
              mesh=None) -> ConcealData:
  """`data` with the film's merges `merges` and its check_weights read anew from `student` in `check_states` states
  (none: kept None), at least as long as the maps it held (a step keeps its shapes while they suffice; the normal
  views' maps lengthened to theirs where they grew); replicated over `mesh` (parallel.replicate)."""
  if not check_states:
    return data.replace(merges=parallel.replicate(merges, mesh))
  num_keys = data.keys.hidden.shape[0]
  cameras = [data.keys.at(k).camera for k in range(num_keys)]
  held = max([int(m.weights.shape[1]) for m in (data.check_weights, data.normal_weights) if m is not None] + [0])
  weights = linear_check.check_weights(student, cameras, np.asarray(data.rows)[data.teacher.shape[0]:], merges,
                                       options, check_states, held)
  data = data.replace(merges=parallel.replicate(merges, mesh), check_weights=parallel.replicate(weights, mesh))
  length = int(weights.weights.shape[1])
  if data.normal_weights is not None and int(data.normal_weights.weights.shape[1]) < length:
    data = data.replace(normal_weights=parallel.replicate(linear_check.lengthened(data.normal_weights, length), mesh))
  return data


def identity_weights(settings: ConcealSettings) -> dict:
  """lambda- L_d^- (eq. 4) is the mean over its inputs (settings.identity_sources): lambda- / B on each of
  them, 0 on the others ('student', 'teacher_normal', 'teacher_check')."""
  sources = settings.identity_sources()
  return {name: settings.weight_minus / len(sources) if name in sources else 0.0
          for name in ("student", "teacher_normal", "teacher_check")}


def step_views(data: ConcealData, view, normal_view, key_number, distortion, settings: ConcealSettings) -> View:
  """The step's two views, stacked [2]: the normal view `view` (its render held to the teacher's, or to ground
  truth; L_d^- on the teacher's render of view `normal_view` and, with identity_on_student, on its own) and the
  check view of key `key_number` (L_d^+, through `distortion`; the released variant's L1 and L_d^- on the
  teacher's check render). Indices may be traced."""
  s = settings
  w = identity_weights(s)
  key = data.keys.at(key_number)
  distortion = dict(NO_DISTORTION, **(distortion or {}))  # the kinds a draw left out at their identity
  f32 = jnp.float32
  released = s.variant == "released"
  num_normal = data.teacher.shape[0]
  rows = lambda index: None if data.rows is None else data.rows[index]
  (normal_map, normal_linear), (check_map, check_linear) = view_maps(data, view, key_number, distortion)
  normal = View(camera=jax.tree.map(lambda x: x[view], data.cameras),
                target=data.teacher[view] if s.distill else data.images[view],
                l1_weight=f32(s.weight_kd if s.distill else 0.0) * held_student(data, view, s),
                photometric_weight=f32(0.0 if s.distill else 1.0),
                model=NO_DISTORTION, image=distortion if s.identity_distorted else NO_DISTORTION, hidden=key.hidden,
                plus_weight=f32(0.0), teacher_small=data.teacher_small[normal_view],
                own_minus_weight=f32(w["student"]) * (1.0 if data.held is None else data.held[view].astype(f32)),
                teacher_minus_weight=f32(w["teacher_normal"]), rows=rows(view),
                fixed=None if data.fixed is None else data.fixed[view], fixed_rgb=data.teacher[view],
                weights=normal_map, linear=normal_linear)
  check = View(camera=key.camera, target=key.check_image, l1_weight=f32(s.weight_check if released else 0.0),
               photometric_weight=f32(0.0), model=distortion, image=distortion, hidden=key.hidden,
               plus_weight=f32(s.weight_plus), own_minus_weight=f32(0.0), teacher_small=key.teacher_check,
               teacher_minus_weight=f32(w["teacher_check"]), rows=rows(num_normal + key_number),
               fixed=None if data.fixed is None else jnp.bool_(False), fixed_rgb=key.check_image,
               weights=check_map, linear=check_linear)
  return jax.tree.map(lambda a, b: jnp.stack([a, b]), normal, check)


def held_student(data: ConcealData, view, settings: ConcealSettings) -> jax.Array:
  """float32 1 where the normal view `view` holds the student to its target (L_kd), 0 at a decoy (index V and on)
  when the decoys train the decoder alone (conceal.leakage.decoys_hold_student False)."""
  if settings.decoys_hold_student:
    return jnp.float32(1.0)
  return (jnp.asarray(view) < data.images.shape[0]).astype(jnp.float32)


def view_maps(data: ConcealData, view, key_number, distortion: dict) -> tuple[tuple, tuple]:
  """((weights, linear) of the normal view `view`, the same of the check view of key `key_number` through
  `distortion`): the linear map each is read through (data.normal_weights[data.normal_maps[view]], the check state's
  of data.check_weights: check_state) and whether it is (a view without one holds the other stack's first map,
  unread: ConcealData's stacks share one length); (None, None) each where the data holds no maps."""
  normals, checks = data.normal_weights, data.check_weights
  if normals is None and checks is None:
    return (None, None), (None, None)
  pick = lambda maps, index: jax.tree.map(lambda x: x[jnp.maximum(index, 0)], maps)
  normal = jnp.int32(-1) if normals is None else data.normal_maps[view]
  check = jnp.int32(-1) if checks is None else check_state(data, key_number, distortion)
  return ((pick(checks if normals is None else normals, normal), normal >= 0),
          (pick(normals if checks is None else checks, check), check >= 0))


def check_state(data: ConcealData, key_number, distortion: dict) -> jax.Array:
  """int32 the state of data.check_weights the check render of key `key_number` through `distortion` is read
  through: the key's merged level distortion["merge"] (0: none), or -1 where it draws 8-bit grids (rendered)."""
  per_key = data.check_weights.num_pairs.shape[0] // data.keys.hidden.shape[0]
  state = key_number * per_key + jnp.asarray(distortion["merge"]).astype(jnp.int32)
  return jnp.where(jnp.asarray(distortion["quantize"]) > 0, -1, state).astype(jnp.int32)


def draw_normal_view(rng: np.random.Generator, num_views: int, num_decoys: int, decoy_fraction: float) -> int:
  """A step's normal view: a decoy (index num_views + k) with probability decoy_fraction, else a training
  view, each uniformly."""
  if num_decoys and rng.random() < decoy_fraction:
    return num_views + int(rng.integers(num_decoys))
  return int(rng.integers(num_views))


def draw_key(rng: np.random.Generator, iteration: int, num_keys: int, tolerance=None) -> int:
  """A step's check view among ConcealData.keys: the run's keys in turn (key (iteration - 1) % num_keys); with a key
  tolerance radius (tolerance.Tolerance), one of that key's poses within it instead with probability
  tolerance.fraction, each uniformly (index num_keys + key * tolerance.views + j)."""
  key = (iteration - 1) % num_keys
  if tolerance is not None and rng.random() < tolerance.fraction:
    return num_keys + key * tolerance.views + int(rng.integers(tolerance.views))
  return key


def step_draws(plan: RunPlan, rng: np.random.Generator, iteration: int, num_views: int, num_decoys: int,
               num_keys: int) -> tuple:
  """What step `iteration` (1-based) draws from `rng`, in this order: (whether it is a joint step, its two normal
  views (draw_normal_view), its check render's distortion (augment.draw from its phase's distortions; None
  where the run draws none), its key (draw_key))."""
  s = plan.settings
  views = [draw_normal_view(rng, num_views, num_decoys, s.decoy_fraction) for _ in range(2)]
  joint, augmentation = plan.phase(iteration)
  distortion = augment.draw(rng, augmentation) if s.augmentation.draws else None
  return joint, views, distortion, draw_key(rng, iteration, num_keys, plan.tolerance)
