"""The concealment recipes, as edits of a config: the paper as written, the authors' released code, our refinement
of the paper (the mark in the teacher's Gaussians) and our recommended recipe (the mark in a carrier film only the
key sees), built from the named parts below. configs/conceal.py applies one by name:

  python -m conceal_jax.main --config=conceal_jax/configs/conceal.py:recommended --workdir=W \\
      --config.data.path=SCENE --config.mark.teacher=TEACHER.ply

The figures behind each choice: experiments/results/REPRODUCTION.md (a row per recipe) and conceal_options.md.
"""
import math

RECIPES = ("paper", "released", "in_scene", "standardized", "recommended", "recommended_at_decoder_size",
           "in_scene_watched", "in_scene_close", "in_scene_close_decoder", "in_scene_tolerant", "in_scene_axial",
           "in_scene_axes", "in_scene_layer")

# The decoder a CPU trains: width 16 from scratch (the paper's width 64 costs ~10x more per step), at a rate
# a from-scratch decoder learns at (1e-3 stalled the demo's first steps).
NARROW_DECODER_WIDTH, NARROW_DECODER_LR = 16, 5e-4
# The gentle student's warmup: a tenth of the run, at least this many steps.
MIN_WARMUP_STEPS, WARMUP_FRACTION = 200, 0.1
# Training through attacks: blur and noise maxima of the check render.
ATTACK_BLUR, ATTACK_NOISE = 1.5, 0.02
# Decoys around the key in the in_scene recipe, and the share of the steps one is the normal view.
DECOY_VIEWS, DECOY_FRACTION = 64, 0.25
# Training through drift: the largest relative parameter noise of the perturbed student, about what the first
# hundred steps of 3D-GS fine-tuning move a student's opacities (experiments/results/survive_bench.md).
DRIFT_NOISE = 0.15
# Training through size pruning: the largest share of a student's smallest Gaussians a check render drops (the
# robustness harness's medium prune_small level).
PRUNE_SHARE = 0.3
# Training through quantization and opacity resets: the share of steps whose check render is of 8-bit colours
# and opacities, and of opacities reset.
QUANTIZE_FRACTION = RESET_FRACTION = 0.25
# Training through decimation: the share of steps whose check render has film pairs merged, and how many rounds
# deep at most (pairs only: deeper merges cost the film more at the key than they gain after a converter's 50%).
MERGE_FRACTION, MERGE_DEPTH = 0.25, 1.0
# Training through the converter's own decimation: the share of check renders merged in the groups splat-transform's
# decimation forms (a thick film, whose groups are alike at every size, reads its plain render best with a fifth of
# them merged), the sizes of the student's copies those groups are computed on (the converter groups a resized scene
# differently), and how often they are recomputed as the film's colours train.
CONVERTER_MERGE_FRACTION, CONVERTER_MERGE_SCALES, CONVERTER_REGROUP_EVERY = 0.2, (0.1, 0.25, 0.6, 1.0, 2.5), 1000
# The thick film: each splat's sigma along the key's axis equal to its in-plane sigma (conceal.carrier.thickness),
# its variance there far above the converter's covariance regulariser at any size a scene is saved at.
THICK_FILM = 1.0
# The closely watched key: decoys turned at most a few degrees, L_d^- weighted well above L_d^+.
CLOSE_DECOY_ROTATION_DEG, CLOSE_WEIGHT_MINUS = (1.0, 5.0), 2.5
# Training twice as deep (demo.py:film_deep), as a converter's decimation to 50% merges some groups of 3 and 4.
DEEP_MERGE_DEPTH = 1.5
# The faint film: each splat at the opacity 3D-GS's reset lowers every opacity to (so the reset leaves it as it is),
# a grid every FAINT_SPACING pixels of the key's image, FAINT_LAYERS grids: about half the background let through.
FAINT_OPACITY, FAINT_SPACING, FAINT_LAYERS = 0.01, 4.0, 22
# The publishable film: an opacity every format's 8-bit opacity stores unchanged, rounded or floored (2/255 and a
# little more, below the reset's ceiling), and base colours within .spz's range (it stores 0.15 * dc + 0.5 in
# 8 bits, so |dc| beyond 0.5 / 0.15 is cut off).
GRID_OPACITY, SPZ_DC_BOUND = 2.001 / 255, 0.5 / 0.15
# The stacked film: splats per grid position, their colours trained as one (a converter's decimation to 50% merges
# each stack, which renders as its splats did).
FILM_STACK = 2
# The watched key: decoys near the key on most steps, many of them, and L_d^- weighted above L_d^+.
WATCH_DECOY_VIEWS, WATCH_DECOY_FRACTION, WATCH_WEIGHT_MINUS = 768, 0.9, 1.5
# The decoder polished alone on the finished student: this many decoder-only steps after the joint ones, on this
# share of them reading the film merged as the converter's decimation merges it (the joint steps read a fifth so).
POLISH_STEPS, POLISH_MERGE_FRACTION = 2000, 0.5
# The rate of the film's base colours in the vivid film (the gentle student's is 6.25e-4).
VIVID_DC_LR = 1e-2
# The key tolerance radius: poses within TOLERANCE_DEG of the key (turned about what it looks at, as an orbit camera)
# reveal its image on TOLERANCE_FRACTION of the steps; its decoys beyond the radius, between TOLERANT_DECOYS_BEYOND
# times it: turned that many degrees, or moved as far as such an orbit turn moves the key (2 sin(t / 2) of its depth).
TOLERANCE_DEG, TOLERANCE_VIEWS, TOLERANCE_FRACTION = 10.0, 64, 0.5
TOLERANT_DECOYS_BEYOND = (1.5, 3.0)
# The axial layer's decoys: how many, moved by these fractions of the key's depth, turned by these degrees.
AXIAL_DECOY_VIEWS, AXIAL_DECOY_TRANSLATION, AXIAL_DECOY_ROTATION_DEG = 192, (0.01, 0.06), (1.0, 6.0)
# The watched axes: the axial decoys on this share of the steps, L_d^- and L_kd weighted so.
AXES_DECOY_FRACTION, AXES_WEIGHT_MINUS, AXES_WEIGHT_KD = 0.5, 2.5, 4.0
# The layer a film-marked scene carries: L_kd weighted so; a guarded decoder returns to its snapshot when L_d^+ exceeds
# ROLLBACK_FACTOR times its running mean (a constant output's L_d^+ is some 40 times a trained decoder's).
LAYER_WEIGHT_KD, ROLLBACK_FACTOR = 32.0, 8.0
# The key at the decoder's size: its decoys (twice the watched key's), moved by these fractions of the key's depth
# (the default's are 0.01-0.1), and the memory their linear maps may take.
DECODER_SIZE_DECOYS, DECODER_SIZE_DECOY_TRANSLATION, DECODER_SIZE_MAPS_MB = 1536, (0.005, 0.06), 8192


def paper(config):
  """ConcealGS as written (Sec. 2.2-2.3): the default config's conceal section, stated."""
  c = config.conceal
  c.variant, c.granularity, c.use_decoder, c.consistency, c.guidance = "paper", "layer", True, True, True
  return config


def released(config):
  """The authors' released code: the normal view against ground truth, L_d^- on the teacher's check render
  only, an L1 of the check render to its image, tensor-wise guidance."""
  config.conceal.variant, config.conceal.granularity = "released", "tensor"
  return config


def in_scene(config):
  """The paper refined, the mark kept in the teacher's Gaussians as the paper keeps it: leakage control, a gentle
  student, training through attacks, a decoder reading clipped renders, and a narrow decoder on a decaying, clipped
  rate. Fine-tuning on the training views reaches those Gaussians and erases the mark; `recommended` moves it into a
  carrier film no training view sees."""
  config = paper(config)
  config = leakage_control(config, DECOY_VIEWS, DECOY_FRACTION)
  config = gentle_student(config)
  config = through_attacks(config)
  config = narrow_decoder(config)
  d = config.conceal.decoder_opt
  d.lr_final_ratio, d.update_clip = 0.3, 1.0
  return config


def standardized(config):
  """in_scene with the decoder reading each render less its mean over its standard deviation
  (conceal.decoder.input_norm): a decoder that no global change of brightness or contrast can move, and that
  reads through size pruning, at some cost to the render (experiments/results/ownership_notes.md)."""
  config = in_scene(config)
  config.conceal.decoder.input_norm = "standardize"
  return config


def recommended(config):
  """Our recommended recipe: in_scene with the mark in a carrier film that only an unseen key sees (unseen_carrier),
  made of faint layers that 3D-GS's opacity reset leaves as they are (faint_film) of colours free to move
  (vivid_film) that the publishing formats store as they are (publishable_film), trained through 8-bit colours and
  the converter's own decimation at several sizes (through_quantization, through_converter_decimation) of splats as
  thick along the key's axis as across it (thick_film), read by the decoder from standardized renders only at the
  key (closely_watched_key) along and about its own axes too (key_axes_watched), with the decoder polished alone on
  the finished student and its decimated copies (polished_decoder), and not through image distortions
  (owner_rendered). The film's grid
  follows the decoder's input (conceal.carrier.spacing 0: a position every other pixel of it, so the film's size does
  not grow with the key's resolution)."""
  config = owner_rendered(in_scene(config))
  config = thick_film(publishable_film(vivid_film(faint_film(unseen_carrier(config), spacing=0.0))))
  config = closely_watched_key(through_converter_decimation(through_quantization(config)))
  config = polished_decoder(key_axes_watched(config))
  config.conceal.decoder.input_norm = "standardize"
  return config


def recommended_at_decoder_size(config):
  """`recommended` with the key at the decoder's size (decoder_size_key): the same film and training, the key's
  render and its decoys' read at 64x64 instead of resized from the training size, about 4 times faster a step on a
  CPU (experiments/results/cpu_speed.md)."""
  return decoder_size_key(recommended(config))


def in_scene_watched(config):
  """in_scene with the recommended recipe's closely watched key (closely_watched_key): a second mark, concealed in
  the Gaussians of a recommended student (mark.teacher: its student.ply) beside the film's, that a model extraction
  carries over where the film (no training view sees it) is lost; verify reads both (verify.marks). In the scene's
  own Gaussians every view sees the mark's texture, so the decoder is watched near its key as the film's is."""
  return closely_watched_key(in_scene(config))


def in_scene_close(config):
  """in_scene_watched with a decoy the normal view on in_scene's share of the steps (DECOY_FRACTION), not the
  watched key's: a layer in the scene's own Gaussians needs the training views on most steps, or those Gaussians
  drift in every view while L_d^- and the check render move them (conceal.leakage.decoy_fraction)."""
  return closely_watched_key(in_scene(config), decoy_fraction=DECOY_FRACTION)


def in_scene_close_decoder(config):
  """in_scene_close with decoys that watch the decoder alone (conceal.leakage.decoys_hold_student False): the
  student is not held to the teacher's render at them, so the mark may stay a texture nearby views show faintly
  (within the render bound, as in_scene's) while the decoder learns to read it at the key only, as the film's does;
  holding the student there asks for a texture only the exact key shows, which costs every view."""
  config = in_scene_close(config)
  config.conceal.leakage.decoys_hold_student = False
  return config


def in_scene_tolerant(config):
  """in_scene with a key tolerance radius (tolerant_key): a mark in the scene's own Gaussians that views near the
  key, not only the key, reveal, so that a copy trained on an attacker's views, which come near the key but not onto
  it, can carry it; the leakage radius grows to TOLERANCE_DEG (the trade issue 39 names)."""
  return tolerant_key(in_scene(config))


def in_scene_axial(config):
  """in_scene with decoys along and about the key's own axes that watch the decoder alone (axial_decoys): an in-scene
  layer leaks where its texture barely moves in the image, a key moved along its optical axis (a zoom) or rolled
  about it, and only there; random directions seldom come near those poses, and holding the student to the teacher
  at them asks for a texture a 2% zoom hides, which costs every view."""
  return axial_decoys(in_scene(config))


def referenced_decoder(config):
  """The decoder reads a learned image of its own beside every render, started from the clean teacher's render at
  the key (conceal.decoder.reference): an in-scene mark looks the same from the key zoomed 2% or rolled 2 degrees,
  what changes there is the framing of the whole scene, which the decoder can compare with its reference pixel by
  pixel (demo.py:referenced; a U-Net watched often enough learned the framing without one:
  experiments/results/layer_designs.md)."""
  config.conceal.decoder.reference = True
  return config


def in_scene_axes(config):
  """in_scene with its key's axes watched (watched_axes): a second mark in the scene's own Gaussians that a model
  extraction carries over (as in_scene's does) and that the key zoomed or rolled a little does not reveal."""
  return watched_axes(in_scene(config))


def in_scene_layer(config):
  """in_scene_axes as the second mark of a scene already marked in a carrier film (the Makefile's LAYER): read from
  the owner's renders (owner_rendered), L_kd weighted LAYER_WEIGHT_KD (the film student's render is the bound this
  layer must keep), and a guarded decoder (guarded_decoder): the decoys that zoom the key by 1-2% collapse it now
  and then, and a decoder that relearned from the identity cost the render more than the mark."""
  config = guarded_decoder(owner_rendered(in_scene_axes(config)))
  config.conceal.weight_kd = LAYER_WEIGHT_KD
  return config


def guarded_decoder(config, factor: float = ROLLBACK_FACTOR):
  """The decoder returned to its snapshot of 100 to 200 steps back at a step whose L_d^+ exceeds `factor` times its
  running mean (conceal.decoder_opt.rollback_factor; conceal/rollback.py): a collapsed decoder does not relearn."""
  config.conceal.decoder_opt.rollback_factor = factor
  return config


def watched_axes(config):
  """axial_decoys as the normal view on AXES_DECOY_FRACTION of the steps, L_d^- weighted AXES_WEIGHT_MINUS: the
  decoder sees a zoom or roll of the key often enough, and hard enough, to learn the key's exact framing (at a
  quarter of the steps and weight 1 it still reveals from its own zoomed decoys); and L_kd weighted AXES_WEIGHT_KD:
  decoys that watch the decoder alone leave the student without L_kd on those steps, and a decoder that refuses
  the zoom asks L_d^+ for more, which drifts the render in every view unless the normal views hold it harder."""
  config = axial_decoys(config)
  config.conceal.leakage.decoy_fraction = AXES_DECOY_FRACTION
  config.conceal.weight_minus, config.conceal.weight_kd = AXES_WEIGHT_MINUS, AXES_WEIGHT_KD
  return config


def axial_decoys(config, decoy_views: int = AXIAL_DECOY_VIEWS):
  """`decoy_views` decoys (AXIAL_DECOY_TRANSLATION, AXIAL_DECOY_ROTATION_DEG) whose moved-only and turned-only
  ones go along and about the key's axes in turn (conceal.leakage.decoy_key_axes) and hold the decoder alone to
  the identity (decoys_hold_student False), on in_scene's share of the steps."""
  lk = key_axes_watched(config).conceal.leakage
  lk.decoy_views, lk.decoys_hold_student = decoy_views, False
  lk.decoy_translation, lk.decoy_rotation_deg = AXIAL_DECOY_TRANSLATION, AXIAL_DECOY_ROTATION_DEG
  return config


def tolerant_key(config, radius_deg: float = TOLERANCE_DEG):
  """TOLERANCE_VIEWS poses within `radius_deg` of the key reveal its image on TOLERANCE_FRACTION of the steps, the
  training views within it are not held to F's identity, and the decoys lie beyond it, TOLERANT_DECOYS_BEYOND times
  it (conceal.leakage.tolerance_*, decoy_rotation_deg, decoy_translation)."""
  lk = config.conceal.leakage
  lk.tolerance_deg, lk.tolerance_views, lk.tolerance_fraction = radius_deg, TOLERANCE_VIEWS, TOLERANCE_FRACTION
  turns = tuple(radius_deg * factor for factor in TOLERANT_DECOYS_BEYOND)
  lk.decoy_rotation_deg = turns
  lk.decoy_translation = tuple(round(2.0 * math.sin(math.radians(t) / 2.0), 4) for t in turns)
  return config


def decoder_size_key(config, decoy_views: int = DECODER_SIZE_DECOYS):
  """The key and its decoys cameras of the decoder's input size (conceal.carrier.at_decoder_size), with `decoy_views`
  decoys moved DECODER_SIZE_DECOY_TRANSLATION of the key's depth (conceal.leakage.decoy_views, decoy_translation)
  and room for their linear maps (conceal.carrier.linear_maps_mb): read at the decoder's size, the decoder reveals
  its image where the watched key's decoys lie thinly, at small moves and turns that shift the image vertically."""
  config.conceal.carrier.at_decoder_size = True
  config.conceal.carrier.linear_maps_mb = DECODER_SIZE_MAPS_MB
  lk = config.conceal.leakage
  lk.decoy_views, lk.decoy_translation = decoy_views, DECODER_SIZE_DECOY_TRANSLATION
  return config


def owner_rendered(config):
  """No training through blur or noise of the check render (conceal.attacks.blur_max, noise_max): the owner
  renders the key from the suspect's scene, so no image reaches the decoder distorted, and a decoder taught to
  read through them reads a coarser texture, which a key turned a degree or two still shows."""
  a = config.conceal.attacks
  a.blur_max = a.noise_max = 0.0
  a.identity_distorted = False
  return config


def unseen_carrier(config):
  """The key looks where no camera of the scene looks and the mark lives in a film of Gaussians there
  (mark.key_kind 'unseen', conceal.carrier): fine-tuning on the training views cannot reach it, and the normal
  views render the teacher's images."""
  config.mark.key_kind = "unseen"
  config.conceal.carrier.film = True
  return config


def faint_film(config, spacing: float = FAINT_SPACING):
  """The carrier film made of FAINT_LAYERS grids of splats at FAINT_OPACITY, one every `spacing` pixels of the key's
  image (0: every other pixel of the decoder's input; its opacity comes from many faint layers): 3D-GS's opacity
  reset, which lowers every opacity to at most FAINT_OPACITY, leaves it as it is, so no training through resets is
  needed."""
  c = config.conceal.carrier
  c.opacity, c.spacing, c.layers = FAINT_OPACITY, spacing, FAINT_LAYERS
  return config


def vivid_film(config, lr: float = VIVID_DC_LR):
  """The film's base colours trained at `lr` (conceal.lr.sh_dc; only the film trains, so the teacher's colours keep
  theirs): a faint film's contrast is its opacity times how far its colours move from the background's, and at a
  gentle student's rate they hardly move in a run."""
  config.conceal.lr.sh_dc = lr
  return config


def publishable_film(config):
  """The film at GRID_OPACITY with its base colours held within SPZ_DC_BOUND (conceal.carrier.opacity and
  dc_bound): the publishing formats store both as they are, so a round trip leaves the film's image unchanged but
  for 8-bit rounding of its colours."""
  c = config.conceal.carrier
  c.opacity, c.dc_bound = GRID_OPACITY, SPZ_DC_BOUND
  return config


def thick_film(config, thickness: float = THICK_FILM):
  """The film's splats `thickness` times as thick along the key's axis as across it (conceal.carrier.thickness):
  a thin film's variance along that axis falls below splat-transform's covariance regulariser, so the converter
  groups a resized copy of the scene otherwise than the scene itself, and its decimation of a small copy costs the
  film more."""
  config.conceal.carrier.thickness = thickness
  return config


def stacked_film(config, stack: int = FILM_STACK):
  """The film's grids with `stack` splats at each position, their colours trained as one (conceal.carrier.stack),
  and 1/stack as many grids, so the film keeps its splat count and its opacity; the film's colour rate divided by
  `stack`, as a stack's colour step moves its image `stack` times as far as one splat's. splat-transform merges
  each stack with itself only with splats small against their neighbours' distance (conceal.carrier.spread), and a
  merged stack renders larger than its pair (experiments/results/film_designs.md)."""
  c = config.conceal.carrier
  c.stack, c.layers = stack, max(1, c.layers // stack)
  config.conceal.lr.sh_dc /= stack
  return config


def watched_key(config, decoy_views: int = WATCH_DECOY_VIEWS, decoy_fraction: float = WATCH_DECOY_FRACTION):
  """Decoys near the key (`decoy_views` of them) as the normal view on `decoy_fraction` of the steps, and
  L_d^- weighted WATCH_WEIGHT_MINUS: a decoder that reads a texture it is not watched closely on learns to read it
  wherever it lies, and reveals the image shifted when the key is turned a degree or two. A film's normal views
  teach little else (no training view sees the film)."""
  config = leakage_control(config, decoy_views, decoy_fraction)
  config.conceal.weight_minus = WATCH_WEIGHT_MINUS
  return config


def closely_watched_key(config, decoy_fraction: float = WATCH_DECOY_FRACTION):
  """watched_key with its decoys turned at most CLOSE_DECOY_ROTATION_DEG and L_d^- weighted CLOSE_WEIGHT_MINUS
  (conceal.leakage.decoy_rotation_deg, conceal.weight_minus): a decoder trained through the converter's merges
  learns a film read in many groupings, and without a closer watch it reads that film from a key turned two
  degrees too."""
  config = watched_key(config, decoy_fraction=decoy_fraction)
  config.conceal.leakage.decoy_rotation_deg = CLOSE_DECOY_ROTATION_DEG
  config.conceal.weight_minus = CLOSE_WEIGHT_MINUS
  return config


def key_axes_watched(config):
  """The watched key's moved-only and turned-only decoys along and about the key's own axes in turn
  (conceal.leakage.decoy_key_axes): a film's image moves least when the key is rolled about its optical axis or
  moved along it, poses random decoy directions seldom come near, so a decoder watched only at random directions
  still reads its image from the key rolled a degree."""
  config.conceal.leakage.decoy_key_axes = True
  return config


def polished_decoder(config, steps: int = POLISH_STEPS, merge_share: float = POLISH_MERGE_FRACTION):
  """`steps` more steps that train the decoder alone on the finished student (conceal.decoder_opt.polish_steps):
  the decoys about the key's axes hold the decoder to the identity at poses close to the key, which the joint steps
  pay for in hidden SSIM; a decoder fitted to the student as it is shared wins it back and leaves the student as
  it was. On `merge_share` of those steps it reads the finished film as the converter's decimation merges it
  (conceal.decoder_opt.polish_merge_fraction): a decoder that refuses the key rolled a degree also refuses a
  decimated copy, which moves the image about as little, unless it sees such copies often."""
  config.conceal.decoder_opt.polish_steps = steps
  config.conceal.decoder_opt.polish_merge_fraction = merge_share
  return config


def through_pruning(config, share: float = PRUNE_SHARE):
  """The check render drawn from the student with up to `share` of its smallest Gaussians dropped
  (conceal.attacks.prune_small_max): without it a decoder may read the mark from small Gaussians that a size
  pruning removes first."""
  config.conceal.attacks.prune_small_max = share
  return config


def through_drift(config, param_noise: float = DRIFT_NOISE):
  """The check render drawn from a student whose every parameter is noised by up to `param_noise` times its
  spread (conceal.attacks.param_noise_max): a decoder and a mark taught to survive the drift of re-training."""
  config.conceal.attacks.param_noise_max = param_noise
  return config


def through_quantization(config, fraction: float = QUANTIZE_FRACTION):
  """A `fraction` of the check renders drawn from the student's colours and opacities rounded to 8 bits as .spz
  stores them (conceal.attacks.quantize_fraction), so that the mark survives publishing formats."""
  config.conceal.attacks.quantize_fraction = fraction
  return config


def through_decimation(config, fraction: float = MERGE_FRACTION, depth: float = MERGE_DEPTH):
  """A `fraction` of the check renders drawn with the carrier film's neighbouring splats merged pairwise as a
  converter's decimation merges them, up to `depth` rounds deep (conceal.attacks.merge_fraction, merge_depth), so
  that the mark survives a scene shrunk for the web."""
  config.conceal.attacks.merge_fraction, config.conceal.attacks.merge_depth = fraction, depth
  return config


def through_converter_decimation(config, fraction: float = CONVERTER_MERGE_FRACTION,
                                 scales: tuple = CONVERTER_MERGE_SCALES):
  """A `fraction` of the check renders drawn with the carrier film merged in the groups splat-transform's
  decimation to each of conceal.attacks.merge_keep forms (conceal.attacks.merge_groups 'converter',
  conceal/grouping.py), computed on copies of the student scaled by each of `scales` and recomputed every
  CONVERTER_REGROUP_EVERY steps: the converter's groups, not neighbouring pairs, are what a scene shrunk for the
  web meets, at whatever size it was saved."""
  a = config.conceal.attacks
  a.merge_groups, a.merge_fraction, a.merge_scales = "converter", fraction, tuple(scales)
  a.regroup_every = CONVERTER_REGROUP_EVERY
  return config


def through_reset(config, fraction: float = RESET_FRACTION):
  """A `fraction` of the check renders drawn from the student with its opacities reset as 3D-GS's densifying
  training does (conceal.attacks.reset_fraction): a reset leaves what no training view sees dimmed for good."""
  config.conceal.attacks.reset_fraction = fraction
  return config


def leakage_control(config, decoy_views: int, decoy_fraction: float = 0.25):
  """L_d^- on the student's normal renders and the clean teacher's check render, and `decoy_views` poses near
  the key trained as normal views a `decoy_fraction` of the steps (default.py, conceal.leakage)."""
  lk = config.conceal.leakage
  lk.identity_on_student = lk.identity_on_teacher_check = True
  lk.decoy_views, lk.decoy_fraction = decoy_views, decoy_fraction
  return config


def gentle_student(config):
  """Gentler student rates than a scene in training needs: a warmup (a tenth of the run, at least
  MIN_WARMUP_STEPS) and a quarter of the 3D-GS rates for everything but the positions. A fresh Adam on a
  converged teacher otherwise moves every parameter by its rate at once."""
  lr = config.conceal.lr
  lr.warmup_steps, lr.warmup_fraction = MIN_WARMUP_STEPS, WARMUP_FRACTION
  lr.opacity, lr.scales, lr.quats = 0.0125, 1.25e-3, 2.5e-4
  lr.sh_dc, lr.sh_rest = 6.25e-4, 3.125e-5
  return config


def through_attacks(config, clip_input: bool = True):
  """The check render read through blur and noise (conceal.attacks), L_d^- reading the student's normal renders
  alike, and with `clip_input` the decoder reading renders clipped to [0, 1] (conceal.decoder.clip_input)."""
  a = config.conceal.attacks
  a.blur_max, a.noise_max, a.identity_distorted = ATTACK_BLUR, ATTACK_NOISE, True
  config.conceal.decoder.clip_input = clip_input
  return config


def narrow_decoder(config):
  """The width-16 decoder from scratch at NARROW_DECODER_LR."""
  d = config.conceal.decoder
  d.width, d.vgg_init = NARROW_DECODER_WIDTH, False
  config.conceal.decoder_opt.lr = NARROW_DECODER_LR
  return config


def apply(config, recipe: str):
  """`config` with the recipe named `recipe` (one of RECIPES); ValueError otherwise."""
  if recipe not in RECIPES:
    raise ValueError(f"unknown concealment recipe {recipe!r}; choose one of {RECIPES}")
  return globals()[recipe](config)
