"""Default config: every option of every mode, with the Inria 3D-GS training defaults.

The default mode renders a generated Gaussian scene from an orbit of cameras and writes PNGs:

  python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=workdirs/render
  python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=workdirs/ply \
      --config.scene.ply=path/to/point_cloud.ply --config.render.sh_degree=3

What most users set:
  mode          render | train | eval | conceal | baseline | reveal | verify
  data.path     'demo' or a scene folder (Blender, COLMAP, transforms.json, LLFF)
  mark.teacher  the trained scene to mark; mark.hidden, the image to hide (a path or a scikit-image sample)
  reveal.ply, reveal.key, reveal.decoder   what to reveal from (reveal and verify modes)
The concealment recipes are configs/conceal.py's; the dataset configs (demo.py, nerf_synthetic.py, colmap.py)
start from this one.
"""
import ml_collections

# Settings removed from the code, at the value every run now has: a workdir whose config.json holds one at this
# value resumes (core/workdir.py); at any other value it is a different run.
RETIRED_SETTINGS = {"conceal.decoder.pattern": 0, "conceal.decoder.modulation": 0.0}


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.mode = "render"  # the job to run; see conceal_jax.main.MODES
  config.seed = 0
  config.scene = scene_section()
  config.render = render_section()
  config.data = data_section()
  config.init = init_section()
  config.train = train_section()
  config.eval = eval_section()
  config.mark = mark_section()
  config.conceal = conceal_section(config.train.lr)
  config.baseline = baseline_section()
  config.reveal = reveal_section()
  config.verify = verify_section()
  return config


def scene_section() -> ml_collections.ConfigDict:
  """Render mode: the scene to show and the orbit of cameras it is shown from."""
  c = ml_collections.ConfigDict()
  c.ply = ""          # a standard 3D-GS .ply; empty: the generated scene below
  c.num_points = 3000  # size of the generated scene
  c.sh_degree = 3
  c.width = 128
  c.height = 128
  c.fov_deg = 45.0
  c.distance = 4.0       # orbit radius around the origin
  c.elevation_deg = 25.0
  c.num_views = 4
  return c


def render_section() -> ml_collections.ConfigDict:
  """The rasteriser, for every mode (fields of conceal_jax.splat.render.RenderOptions)."""
  c = ml_collections.ConfigDict()
  c.sh_degree = ml_collections.config_dict.placeholder(int)  # None: every band the scene stores
  c.background = (1.0, 1.0, 1.0)  # train / eval / conceal use the dataset's background
  c.tile_size = 8
  c.segment_size = 32   # pairs per compositing segment
  # None (default) composites every splat (exact); an int K keeps each tile's K nearest (an approximation)
  c.max_per_tile = ml_collections.config_dict.placeholder(int)
  c.antialiased = False
  return c


def data_section() -> ml_collections.ConfigDict:
  """Train, eval, conceal and baseline modes: the dataset."""
  c = ml_collections.ConfigDict()
  # 'demo' (generated, cached) or a Blender / COLMAP / transforms.json / LLFF folder
  c.path = "demo"
  # 'auto' (the first complete one of blender, colmap, transforms, llff; the choice is logged) or one of those
  c.format = "auto"
  # COLMAP and LLFF: the images folder in data.path, e.g. 'images_4' (downscaled copies; cameras follow them);
  # 'images' where a capture has none reads its least downscaled images_<factor>/ (logged)
  c.images = "images"
  c.downscale = 1.0        # image resolution divisor
  c.background = "default"  # 'white', 'black' or 'default' (white for Blender, black otherwise)
  return c


def init_section() -> ml_collections.ConfigDict:
  """Train mode: where the Gaussians start."""
  c = ml_collections.ConfigDict()
  # 'points' (SfM / point file; a capture without any starts as 'random', with a logged note), 'auto' (the
  # same, without the note), 'random' (box) or 'ply'
  c.kind = "auto"
  c.ply = ""               # init.kind='ply': a trained 3D-GS .ply to train further (fine-tuning)
  c.num_random_points = 100_000
  c.box_half_extent = 1.3
  return c


def train_section() -> ml_collections.ConfigDict:
  """Train mode: the Inria 3D-GS recipe (learning rates, densification, SH schedule) and the loop's cadence."""
  c = ml_collections.ConfigDict()
  c.iterations = 30_000
  c.sh_degree = 3
  c.sh_degree_start = 0     # fine-tuning a trained scene: its degree (no schedule from 0)
  c.sh_increase_every = 1000
  c.ssim_weight = 0.2
  c.lr = ml_collections.ConfigDict()
  c.lr.means_init = 1.6e-4   # times the scene extent
  c.lr.means_final = 1.6e-6  # times the scene extent
  c.lr.means_steps = 0        # decay length; 0: the run's length (3D-GS: 30k of 30k)
  c.lr.sh_dc = 2.5e-3
  c.lr.sh_rest = 2.5e-3 / 20
  c.lr.opacity = 0.05
  c.lr.scales = 5e-3
  c.lr.quats = 1e-3
  c.lr.warmup_steps = 0       # linear ramp of every update (not in 3D-GS; see gs/optimizer.py)
  c.lr.warmup_fraction = 0.0  # ... over this fraction of the run instead, where that is longer
  c.densify = ml_collections.ConfigDict()
  c.densify.start = 500
  c.densify.until = 15_000
  c.densify.every = 100
  c.densify.opacity_reset_every = 3000
  c.densify.grad_threshold = 2e-4
  c.densify.percent_dense = 0.01
  c.densify.split_factor = 1.6
  c.densify.min_opacity = 0.005
  c.densify.max_screen_radius = 20.0
  c.densify.max_world_scale = 0.1
  # 0: no limit (3D-GS). A cap keeps a CPU step affordable: candidates beyond it are dropped, smallest
  # gradients first (the bench configs measure what it costs in PSNR).
  c.densify.max_gaussians = 0
  c.log_every = 10
  c.eval_every = 0        # quick test PSNR every this many steps; 0: only at the end
  c.eval_views = 4
  # views rendered per step, the update their gradients' mean; a mesh of devices (--host_devices, GPUs,
  # processes) splits them. 1: 3D-GS's one view per step
  c.views_per_step = 1
  c.checkpoint_every = 1000  # 0: no checkpoints
  # > 0: stop at the first checkpoint after this many minutes and score the scene there (a machine lent for
  # a fixed time); train.json records the step reached, and the same command resumes the run
  c.time_limit_min = 0.0
  c.snapshots = ()        # steps after which point_cloud_<step>.ply is also written
  c.progress_bar = True
  return c


def eval_section() -> ml_collections.ConfigDict:
  """Eval mode, and the scoring at the end of train, conceal and baseline runs."""
  c = ml_collections.ConfigDict()
  c.ply = ""               # scene to score; empty: <workdir>/point_cloud.ply
  c.exact = True           # score exactly even when render.max_per_tile truncates
  c.max_views = 0          # 0: the whole test split
  c.lpips_net = "vgg"
  return c


def mark_section() -> ml_collections.ConfigDict:
  """What is hidden where: the teacher scene, the hidden image(s) and the secret key (conceal and baseline modes)."""
  c = ml_collections.ConfigDict()
  c.teacher = ""          # the teacher's .ply (required)
  c.hidden = "astronaut"  # an image path or a scikit-image sample name
  c.hidden_size = 64      # the hidden image and decoder resolution S (S x S)
  # message mode (conceal/message.py): > 0 hides a message of this many bits, BCH-coded and laid out as the hidden
  # image, instead of mark.hidden; mark.message its bits in hex ("": drawn from seed). key.json records it
  c.message_bits = 0
  c.message = ""
  # 'train_index', 'orbit' (a secret pose on the training orbit, from key_seed) or 'unseen' (a pose looking where
  # no camera of the scene looks, key_offset camera distances from their orbit target, turned about its axis by
  # key_seed; conceal.carrier)
  c.key_kind = "train_index"
  c.key_index = -2        # second to last training camera, as released
  c.key_seed = 1
  c.key_offset = 1.0
  # several images (beyond the paper): up to 3 more, each at its own key of key_kind's kind (training cameras
  # key_index - 1, key_index - 2, ... or orbit seeds key_seed + 1, ...), one decoder reading every key
  c.extra_hidden = ()
  return c


def conceal_section(train_lr: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """Conceal mode: ConcealGS on a trained teacher. The defaults are the paper as written; the recipes a user
  chooses between are configs/conceal.py's (recipes.RECIPES)."""
  c = ml_collections.ConfigDict()
  c.iterations = 10_000
  c.variant = "paper"     # 'paper' or 'released' (the authors' code; see conceal/settings.py)
  c.use_decoder = True    # the paper's ablations (Table 3)
  c.consistency = True
  c.guidance = True
  c.granularity = "layer"  # what the guidance calls a layer: 'layer' (paper) or 'tensor' (released)
  c.weight_kd = 1.0       # the loss weights: L_kd, lambda+ (L_d^+), lambda- (L_d^-),
  c.weight_plus = 1.0
  c.weight_minus = 1.0
  c.weight_check = 1.0    # and the released variant's check-view L1
  # student learning rates: the 3D-GS schedule continued from step 10k of 30k, as the released run does
  c.lr = ml_collections.ConfigDict(train_lr.to_dict())
  c.lr.means_init = 3.45e-5
  c.lr.means_steps = 20_000
  c.log_every = 10
  c.eval_every = 0        # steps between hidden PSNR/SSIM + student test PSNR records (0: none)
  c.eval_views = 4        # test views of that student PSNR
  c.checkpoint_every = 1000
  c.progress_bar = True

  c.decoder = conceal_decoder_section()
  c.decoder_opt = conceal_decoder_opt_section()
  c.leakage = conceal_leakage_section()
  c.attacks = conceal_attacks_section()
  c.carrier = conceal_carrier_section()
  return c


def conceal_decoder_section() -> ml_collections.ConfigDict:
  """The decoder F: a U-Net (conceal/unet.py) and how it reads a render (saved in key.json)."""
  c = ml_collections.ConfigDict()
  c.width = 64      # base channels (64 = the released decoder)
  c.vgg_init = True  # ImageNet VGG16 conv1_2..conv4_3 (width 64 only)
  # beyond the paper: 'center' (F reads each image less its mean and adds it back) or 'standardize' (also over
  # its std); 'none': the paper's decoder
  c.input_norm = "none"
  # beyond the paper: F reads every render clipped to [0, 1], as an image file holds it, so no hidden signal can
  # live in values an attacked or saved image loses
  c.clip_input = False
  # beyond the paper: F reads a learned image of its own beside every render (unet.UNet.reference_size), started
  # from the clean teacher's render at the first key, so that it can tell the key's exact framing from a key
  # zoomed or rolled a little (a mark in the scene's own Gaussians looks the same there)
  c.reference = False
  return c


def conceal_decoder_opt_section() -> ml_collections.ConfigDict:
  """The decoder's optimiser: Adam at lr; beyond the paper, a log-linear decay to lr * lr_final_ratio over the run
  and each tensor's step clipped to RMS update_clip (0: off), against the bursts that kill an unnormalised
  conv+ReLU U-Net late in a run; rollback_factor (0: off) a guard that returns the decoder to its snapshot of
  rollback_every to twice that many steps back at a step whose L_d^+ exceeds rollback_factor times its running mean
  (conceal/rollback.py); then polish_steps more steps that train the decoder alone on the finished student (the
  same losses and guided update), fitting it to the scene that is shared; polish_merge_fraction, where set, is the
  share of those steps whose check render is merged as a decimation merges it (conceal.attacks.merge_fraction's
  draw, the joint steps keeping theirs), so that the decoder learns to read the decimated copies of the finished
  film."""
  c = ml_collections.ConfigDict()
  c.lr = 1e-4
  c.adam_eps = 1e-15  # the released code's (torch's default: 1e-8)
  c.lr_final_ratio = 1.0
  c.update_clip = 0.0
  c.rollback_factor = 0.0
  c.rollback_every = 100
  c.polish_steps = 0
  c.polish_merge_fraction = ml_collections.config_dict.placeholder(float)  # None: conceal.attacks.merge_fraction
  return c


def conceal_leakage_section() -> ml_collections.ConfigDict:
  """Leakage control (beyond the paper; off = the method as written): the decoder must reveal I at the key only.
  L_d^- also on the student's render of the normal view (what a viewer of the shared scene sees) and on the clean
  teacher's check render (the key reveals the student's change, not the pose); decoy_views cameras near every key
  (moved by a fraction of the key's depth, turned by degrees, within the ranges) trained as normal views with
  probability decoy_fraction, holding the student to the teacher and F to the identity there. The key's depth
  (near.near_length) is the opacity- weighted median depth of the teacher's Gaussians in its image (the camera
  distance for a key that sees almost none): the unit of the near-key leakage figure's translations too, so that a
  fraction means about the same pixel motion on an object-centred orbit and on a forward-facing capture, where the
  3D-GS extent (the spread of the camera centres) is small against the depth. decoy_key_axes: the decoys that are
  only moved go along, and those only turned turn about, the key's own axes in turn (a zoom and a roll among them)
  rather than random ones; decoy_orbit_turns: those both moved and turned are orbit turns instead, the key turned
  about the point its depth ahead (a pose whose image of the scene barely moves at its centre). decoys_hold_student
  False: a decoy holds the decoder to the identity (on the student's and the teacher's renders there) but not the
  student to the teacher's render (no L_kd at decoys), so that a mark in the scene's own Gaussians may stay a
  texture every nearby view shows faintly, which the decoder alone learns to read at the key only, rather than one
  only the exact key shows. A key tolerance radius (issue 39's trade of the leakage
  radius for robustness): tolerance_views poses within tolerance_deg of every key (the key turned about the point it
  looks at, as a camera on its orbit sees the scene) reveal the key's image too, one of them the check view with
  probability tolerance_fraction, and the training views within the radius are not held to F's identity on the
  student's render; the decoys belong beyond it (decoy_rotation_deg, decoy_translation), so that a copy trained on
  views that come near the key, not onto it, can carry the mark (0: off, the key alone)."""
  c = ml_collections.ConfigDict()
  c.identity_on_student = False
  c.identity_on_teacher_check = False
  c.decoy_views = 0
  c.decoy_fraction = 0.0
  c.decoy_translation = (0.01, 0.1)
  c.decoy_rotation_deg = (1.0, 10.0)
  c.decoy_key_axes = False
  c.decoy_orbit_turns = False
  c.decoys_hold_student = True
  c.tolerance_deg = 0.0
  c.tolerance_views = 0
  c.tolerance_fraction = 0.0
  return c


def conceal_attacks_section() -> ml_collections.ConfigDict:
  """Training through attacks (beyond the paper, conceal/augment.py): per step the check render is read through a
  distortion drawn up to these maxima (blur sigma and noise sigma ~ U[0, max]; brightness ~ U[-max, max] and
  contrast ~ 1 + U[-max, max], applied first) and rendered from a perturbed student (each Gaussian dropped with a
  probability ~ U[0, dropout_max], every parameter noised by ~ U[0, param_noise_max] times its spread; on a
  quantize_fraction share of the steps, its base colours and opacities on 8-bit grids as the formats store them; on a
  reset_fraction share, every opacity at most 0.01 as 3D-GS's opacity reset leaves it; on a merge_fraction share, the
  carrier film's neighbouring pairs merged as a converter's decimation does, ~ U[0, merge_depth] rounds deep: 1 is
  every pair once, 1.5 half the pairs of what that leaves again, as deep as a converter's 50% goes, and at most 2;
  with merge_groups 'converter' instead the groups splat-transform's decimation merges, to one of the fractions
  merge_keep, reproduced from the student's geometry and colours every regroup_every steps (conceal/grouping.py), on
  copies of it scaled by each of merge_scales (the converter groups a resized scene differently);
  with prune_small_max, the share ~ U[0, prune_small_max] of smallest Gaussians dropped, as a size pruning does), so
  that the hidden image
  survives them; identity_distorted: L_d^- reads the student's normal render through the
  same image distortion, so that F stays the identity on distorted views near the key."""
  c = ml_collections.ConfigDict()
  c.blur_max = 0.0
  c.noise_max = 0.0
  c.brightness_max = 0.0
  c.contrast_max = 0.0
  c.dropout_max = 0.0
  c.param_noise_max = 0.0
  c.quantize_fraction = 0.0
  c.reset_fraction = 0.0
  c.merge_fraction = 0.0
  c.merge_depth = 1.0
  c.merge_groups = "nearest"
  c.merge_keep = (0.5, 0.8)
  c.regroup_every = 500
  c.merge_scales = (1.0,)
  c.prune_small_max = 0.0
  c.identity_distorted = False
  return c


def conceal_carrier_section() -> ml_collections.ConfigDict:
  """Where the mark lives (beyond the paper, conceal/carrier.py). film off: in the teacher's Gaussians, refined
  (the paper). film on (needs mark.key_kind='unseen'): in a film of flat Gaussians `distance` camera distances
  before the key (mark.key_offset's unit), `layers` grids of one splat every `spacing` pixels of the key's image
  (0: two pixels of the decoder's input, whatever the key's resolution; carrier.key_spacing), of `opacity`, in the
  space only the key sees; only the film's base colours train, so the normal views are the teacher's and
  fine-tuning on them leaves the mark as it is. Splats at opacity 0.01 or less, as many layers as
  make the film opaque enough, outlive 3D-GS's opacity reset (it lowers every opacity to at most 0.01). dc_bound > 0
  clips the film's base colours (SH DC) to [-dc_bound, dc_bound] after each update (a format's range; 0: none).
  stack > 1 puts that many splats at each position of the grids, their colours trained as one: a converter's
  decimation down to 1/stack of the film merges stacks, provided the splats are small against the distance between
  neighbouring positions (spread: in-plane sigma in grid spacings; splat-transform's merge cost can favour an
  overlapping neighbour over an identical stack partner). A merged stack renders a little larger than its splats
  (the renderer's 1/255 alpha cut): attacks.merge_fraction trains through it. thickness: each splat's sigma along
  the key's axis as a fraction of its in-plane sigma (a thin film's variance there can fall below the converter's
  covariance regulariser, which makes the converter group a resized copy of the scene differently).
  at_decoder_size: the keys, and the decoys around them, are cameras of the decoder's input size
  (mark.hidden_size square, their field of view kept), so that what the decoder reads there is rendered, not
  resized; the training views, which the film leaves as the teacher's, enter as the teacher's renders resized,
  as the decoder reads any view. Needs every training view left as the teacher's (no attacks.param_noise_max)."""
  c = ml_collections.ConfigDict()
  c.film = False
  c.distance = 0.1
  c.spacing = 2.0
  c.opacity = 0.5
  c.layers = 1
  c.dc_bound = 0.0
  c.stack = 1
  c.spread = 0.6
  c.thickness = 0.01
  c.at_decoder_size = False
  # the most memory (MB) the normal views' renders of the film may take held as linear maps of its colours
  # (conceal/linear_check.py: the same images, read in a fraction of a render's time); 0: they render
  c.linear_maps_mb = 4096.0
  return c


def baseline_section() -> ml_collections.ConfigDict:
  """Baseline mode: a way to hide an image that the paper compares with (see conceal_jax/baselines/baseline.py), of
  mark's hidden image in mark's teacher at mark's key; the containers' 3D-GS training uses the ConcealGS student's
  rates and length (conceal.lr, conceal.iterations), the comparison's common ground."""
  c = ml_collections.ConfigDict()
  c.method = "lsb"       # 'lsb', 'deepstega' or 'steganerf'
  c.iterations = 0       # training steps (3D-GS on the containers, or StegaNeRF's); 0: conceal.iterations
  c.lsb_bits = 1         # low bits of each 8-bit channel that carry the image (1-4)
  c.deepstega = ml_collections.ConfigDict()
  c.deepstega.networks = ""  # saved networks to reuse; empty: <workdir>/deepstega, trained if absent
  c.deepstega.width = 8      # filters per kernel size (3, 4, 5) in every layer (Baluja: 50)
  c.deepstega.prep_depth = 2
  c.deepstega.hide_depth = 4
  c.deepstega.reveal_depth = 4
  c.deepstega.cover_skip = False  # hide the change to the cover, C' = C + net (not Baluja's)
  c.deepstega.beta = 1.0     # weight of the secret term of the loss
  c.deepstega.noise_std = 0.01  # noise on the container during training
  c.deepstega.crop_size = 64    # training crops, at the decoder size
  c.deepstega.batch_size = 8
  c.deepstega.learning_rate = 1e-3
  c.deepstega.held_out_pairs = 16  # held-out (cover, secret) crops of the networks' own report
  c.deepstega.iterations = 3000    # training steps of the networks
  c.deepstega.log_every = 50
  c.deepstega.checkpoint_every = 500
  c.deepstega.progress_bar = True
  # StegaNeRF (Li et al. 2023): the teacher's SH colour, a U-Net decoder and a classifier trained jointly, geometry
  # frozen; the SH learning rates are conceal.lr's (see conceal_jax/baselines/steganerf.py)
  c.steganerf = ml_collections.ConfigDict()
  c.steganerf.protocol = "all_views"  # 'all_views' (StegaNeRF's: I from every view) or 'check_view'
  c.steganerf.weight_render = 1.0     # MSE(render, initial render)
  c.steganerf.weight_hidden = 0.5     # MSE(U(render), I)
  c.steganerf.weight_clean = 0.5      # MSE(U(initial render), 0)
  c.steganerf.weight_classifier = 0.01  # BCE of the watermarked-vs-initial classifier
  c.steganerf.decoder_width = 16      # U-Net base channels (4 input channels: render + score)
  c.steganerf.classifier_width = 16   # channels of the classifier's first conv (then x2, x4)
  c.steganerf.decoder_lr = 1e-3     # fresh networks (no VGG16 start): 1e-4 learns I ~3x slower
  c.steganerf.classifier_lr = 1e-3
  c.steganerf.networks_lr_final_ratio = 1.0  # log-linear decay of both rates to this fraction
  c.steganerf.sh_adam_eps = 1e-8  # Adam eps of the SH colour (torch's default; 3D-GS uses 1e-15)
  c.steganerf.mask_at = "gradient"    # adaptive SH mask on the 'gradient' (StegaNeRF) or Adam's 'update'
  c.steganerf.log_every = 10
  c.steganerf.checkpoint_every = 1000
  c.steganerf.progress_bar = True
  return c


def reveal_section() -> ml_collections.ConfigDict:
  """Reveal mode (verify reads it too): the scene, key and decoder to reveal with."""
  c = ml_collections.ConfigDict()
  c.ply = ""      # any standard 3D-GS .ply
  c.decoder = ""  # decoder.msgpack written by conceal
  c.key = ""      # key.json written by conceal
  c.hidden = ""   # optional reference hidden image (path or sample name) to score against
  c.key_number = 0  # which key of the key file: 0 its check view, k its k-th extra_keys entry
  # the owner's own copy of the marked scene (e.g. the student.ply conceal wrote); set: the suspect scene is
  # registered onto it and the key moved with the similarity found (a turned, moved, resized or reordered
  # scene), reveal.json reporting the transform; empty: the key is used as saved
  c.owner = ""
  return c


def verify_section() -> ml_collections.ConfigDict:
  """Verify mode: the reveal section's ply, decoder, key and hidden image (required here); the scene is owned when
  the p-value of the phase correlation of what it reveals with the hidden image is at most alpha
  (robust.ownership); a calibration file of measured clean and marked SSIM scores adds its threshold's decision."""
  c = ml_collections.ConfigDict()
  c.alpha = 1e-6  # the false-positive rate the decision is made at
  # renders of the scene turned away from the key, among the decoder outputs the null is drawn from (at least: more
  # where a small hidden image would leave too few draws for a p-value at most alpha, robust.ownership)
  c.null_views = 32
  c.calibration = ""  # optional: e.g. experiments/results/ownership_calibration.json (make bench-robust)
  # optional: the folders of conceal runs that hid further marks in the same scene (comma-separated; each a run
  # made on the student of the one before, its mark.teacher), each read with its key.json, decoder.msgpack and
  # hidden.png beside reveal's mark: owned on the best of all their readings (robust.ownership.verify)
  c.marks = ""
  return c
