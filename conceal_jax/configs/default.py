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


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.mode = "render"  # the job to run; see conceal_jax.main.MODES
  config.seed = 0

  # render mode: the scene to show and the orbit of cameras it is shown from
  config.scene = ml_collections.ConfigDict()
  config.scene.ply = ""          # a standard 3D-GS .ply; empty: the generated scene below
  config.scene.num_points = 3000  # size of the generated scene
  config.scene.sh_degree = 3
  config.scene.width = 128
  config.scene.height = 128
  config.scene.fov_deg = 45.0
  config.scene.distance = 4.0       # orbit radius around the origin
  config.scene.elevation_deg = 25.0
  config.scene.num_views = 4

  # the rasteriser, for every mode (fields of conceal_jax.splat.render.RenderOptions)
  config.render = ml_collections.ConfigDict()
  config.render.sh_degree = ml_collections.config_dict.placeholder(int)  # None: every band the scene stores
  config.render.background = (1.0, 1.0, 1.0)  # train / eval / conceal use the dataset's background
  config.render.tile_size = 8
  config.render.segment_size = 32   # pairs per compositing segment
  # None (default) composites every splat (exact); an int K keeps each tile's K nearest (an approximation)
  config.render.max_per_tile = ml_collections.config_dict.placeholder(int)
  config.render.antialiased = False

  # train / eval / conceal modes: the dataset
  config.data = ml_collections.ConfigDict()
  # 'demo' (generated, cached) or a Blender / COLMAP / transforms.json / LLFF folder
  config.data.path = "demo"
  config.data.downscale = 1.0        # image resolution divisor
  config.data.background = "default"  # 'white', 'black' or 'default' (white for Blender, black otherwise)

  config.init = ml_collections.ConfigDict()
  config.init.kind = "auto"          # 'auto', 'points' (SfM / point file), 'random' (box) or 'ply'
  config.init.ply = ""               # init.kind='ply': a trained 3D-GS .ply to train further (fine-tuning)
  config.init.num_random_points = 100_000
  config.init.box_half_extent = 1.3

  config.train = ml_collections.ConfigDict()
  config.train.iterations = 30_000
  config.train.sh_degree = 3
  config.train.sh_degree_start = 0     # fine-tuning a trained scene: its degree (no schedule from 0)
  config.train.sh_increase_every = 1000
  config.train.ssim_weight = 0.2
  config.train.lr = ml_collections.ConfigDict()
  config.train.lr.means_init = 1.6e-4   # times the scene extent
  config.train.lr.means_final = 1.6e-6  # times the scene extent
  config.train.lr.means_steps = 0        # decay length; 0: the run's length (3D-GS: 30k of 30k)
  config.train.lr.sh_dc = 2.5e-3
  config.train.lr.sh_rest = 2.5e-3 / 20
  config.train.lr.opacity = 0.05
  config.train.lr.scales = 5e-3
  config.train.lr.quats = 1e-3
  config.train.lr.warmup_steps = 0       # linear ramp of every update (not in 3D-GS; see gs/optimizer.py)
  config.train.lr.warmup_fraction = 0.0  # ... over this fraction of the run instead, where that is longer
  config.train.densify = ml_collections.ConfigDict()
  config.train.densify.start = 500
  config.train.densify.until = 15_000
  config.train.densify.every = 100
  config.train.densify.opacity_reset_every = 3000
  config.train.densify.grad_threshold = 2e-4
  config.train.densify.percent_dense = 0.01
  config.train.densify.split_factor = 1.6
  config.train.densify.min_opacity = 0.005
  config.train.densify.max_screen_radius = 20.0
  config.train.densify.max_world_scale = 0.1
  # 0: no limit (3D-GS). A cap keeps a CPU step affordable: candidates beyond it are dropped, smallest
  # gradients first (the bench configs measure what it costs in PSNR).
  config.train.densify.max_gaussians = 0
  config.train.log_every = 10
  config.train.eval_every = 0        # quick test PSNR every this many steps; 0: only at the end
  config.train.eval_views = 4
  config.train.checkpoint_every = 1000  # 0: no checkpoints
  config.train.snapshots = ()        # steps after which point_cloud_<step>.ply is also written
  config.train.progress_bar = True

  config.eval = ml_collections.ConfigDict()
  config.eval.ply = ""               # scene to score; empty: <workdir>/point_cloud.ply
  config.eval.exact = True           # score exactly even when render.max_per_tile truncates
  config.eval.max_views = 0          # 0: the whole test split
  config.eval.lpips_net = "vgg"

  # what is hidden where: the teacher scene, the hidden image(s) and the secret key (conceal and baseline modes)
  config.mark = ml_collections.ConfigDict()
  config.mark.teacher = ""          # the teacher's .ply (required)
  config.mark.hidden = "astronaut"  # an image path or a scikit-image sample name
  config.mark.hidden_size = 64      # the hidden image and decoder resolution S (S x S)
  config.mark.key_kind = "train_index"  # 'train_index' or 'orbit' (a secret pose on the training orbit, from key_seed)
  config.mark.key_index = -2        # second to last training camera, as released
  config.mark.key_seed = 1
  # several images (beyond the paper): up to 3 more, each at its own key of key_kind's kind (training cameras
  # key_index - 1, key_index - 2, ... or orbit seeds key_seed + 1, ...), one decoder reading every key
  config.mark.extra_hidden = ()

  # conceal mode: ConcealGS on a trained teacher. The defaults are the paper as written; the recipes a user
  # chooses between are configs/conceal.py's (paper, released, recommended).
  config.conceal = ml_collections.ConfigDict()
  config.conceal.iterations = 10_000
  config.conceal.variant = "paper"     # 'paper' or 'released' (the authors' code; see conceal/settings.py)
  config.conceal.use_decoder = True    # the paper's ablations (Table 3)
  config.conceal.consistency = True
  config.conceal.guidance = True
  config.conceal.granularity = "layer"  # what the guidance calls a layer: 'layer' (paper) or 'tensor' (released)
  config.conceal.weight_kd = 1.0       # the loss weights: L_kd, lambda+ (L_d^+), lambda- (L_d^-),
  config.conceal.weight_plus = 1.0
  config.conceal.weight_minus = 1.0
  config.conceal.weight_check = 1.0    # and the released variant's check-view L1
  # student learning rates: the 3D-GS schedule continued from step 10k of 30k, as the released run does
  config.conceal.lr = ml_collections.ConfigDict(config.train.lr.to_dict())
  config.conceal.lr.means_init = 3.45e-5
  config.conceal.lr.means_steps = 20_000
  config.conceal.log_every = 10
  config.conceal.eval_every = 0        # steps between hidden PSNR/SSIM + student test PSNR records (0: none)
  config.conceal.eval_views = 4        # test views of that student PSNR
  config.conceal.checkpoint_every = 1000
  config.conceal.progress_bar = True

  # the decoder F: a U-Net (conceal/unet.py) and how it reads a render (saved in key.json)
  config.conceal.decoder = ml_collections.ConfigDict()
  config.conceal.decoder.width = 64      # base channels (64 = the released decoder)
  config.conceal.decoder.vgg_init = True  # ImageNet VGG16 conv1_2..conv4_3 (width 64 only)
  # beyond the paper: 'center' (F reads each image less its mean and adds it back) or 'standardize' (also over
  # its std); 'none': the paper's decoder
  config.conceal.decoder.input_norm = "none"
  # beyond the paper: F reads every render clipped to [0, 1], as an image file holds it, so no hidden signal can
  # live in values an attacked or saved image loses
  config.conceal.decoder.clip_input = False

  # the decoder's optimiser: Adam at lr; beyond the paper, a log-linear decay to lr * lr_final_ratio over the run
  # and each tensor's step clipped to RMS update_clip (0: off), against the bursts that kill an unnormalised
  # conv+ReLU U-Net late in a run; then polish_steps more steps that train the decoder alone on the finished
  # student (the same losses and guided update), fitting it to the scene that is shared
  config.conceal.decoder_opt = ml_collections.ConfigDict()
  config.conceal.decoder_opt.lr = 1e-4
  config.conceal.decoder_opt.adam_eps = 1e-15  # the released code's (torch's default: 1e-8)
  config.conceal.decoder_opt.lr_final_ratio = 1.0
  config.conceal.decoder_opt.update_clip = 0.0
  config.conceal.decoder_opt.polish_steps = 0

  # leakage control (beyond the paper; off = the method as written): the decoder must reveal I at the key only.
  # L_d^- also on the student's render of the normal view (what a viewer of the shared scene sees) and on the
  # clean teacher's check render (the key reveals the student's change, not the pose); decoy_views cameras near
  # every key (moved by a fraction of the scene extent, turned by degrees, within the ranges) trained as normal
  # views with probability decoy_fraction, holding the student to the teacher and F to the identity there
  config.conceal.leakage = ml_collections.ConfigDict()
  config.conceal.leakage.identity_on_student = False
  config.conceal.leakage.identity_on_teacher_check = False
  config.conceal.leakage.decoy_views = 0
  config.conceal.leakage.decoy_fraction = 0.0
  config.conceal.leakage.decoy_translation = (0.01, 0.1)
  config.conceal.leakage.decoy_rotation_deg = (1.0, 10.0)

  # training through attacks (beyond the paper, conceal/augment.py): per step the check render is read through
  # a distortion drawn up to these maxima (blur sigma and noise sigma ~ U[0, max]; brightness ~ U[-max, max] and
  # contrast ~ 1 + U[-max, max], applied first) and rendered from a perturbed student (each Gaussian dropped with
  # a probability ~ U[0, dropout_max], every parameter noised by ~ U[0, param_noise_max] times its spread), so
  # that the hidden image survives them; identity_distorted: L_d^- reads the student's normal render through the
  # same image distortion, so that F stays the identity on distorted views near the key
  config.conceal.attacks = ml_collections.ConfigDict()
  config.conceal.attacks.blur_max = 0.0
  config.conceal.attacks.noise_max = 0.0
  config.conceal.attacks.brightness_max = 0.0
  config.conceal.attacks.contrast_max = 0.0
  config.conceal.attacks.dropout_max = 0.0
  config.conceal.attacks.param_noise_max = 0.0
  config.conceal.attacks.identity_distorted = False

  # baseline mode: a way to hide an image that the paper compares with (see conceal_jax/baselines/baseline.py),
  # of mark's hidden image in mark's teacher at mark's key; the containers' 3D-GS training uses the ConcealGS
  # student's rates and length (conceal.lr, conceal.iterations), the comparison's common ground
  config.baseline = ml_collections.ConfigDict()
  config.baseline.method = "lsb"       # 'lsb', 'deepstega' or 'steganerf'
  config.baseline.iterations = 0       # training steps (3D-GS on the containers, or StegaNeRF's); 0: conceal.iterations
  config.baseline.lsb_bits = 1         # low bits of each 8-bit channel that carry the image (1-4)
  config.baseline.deepstega = ml_collections.ConfigDict()
  config.baseline.deepstega.networks = ""  # saved networks to reuse; empty: <workdir>/deepstega, trained if absent
  config.baseline.deepstega.width = 8      # filters per kernel size (3, 4, 5) in every layer (Baluja: 50)
  config.baseline.deepstega.prep_depth = 2
  config.baseline.deepstega.hide_depth = 4
  config.baseline.deepstega.reveal_depth = 4
  config.baseline.deepstega.cover_skip = False  # hide the change to the cover, C' = C + net (not Baluja's)
  config.baseline.deepstega.beta = 1.0     # weight of the secret term of the loss
  config.baseline.deepstega.noise_std = 0.01  # noise on the container during training
  config.baseline.deepstega.crop_size = 64    # training crops, at the decoder size
  config.baseline.deepstega.batch_size = 8
  config.baseline.deepstega.learning_rate = 1e-3
  config.baseline.deepstega.held_out_pairs = 16  # held-out (cover, secret) crops of the networks' own report
  config.baseline.deepstega.iterations = 3000    # training steps of the networks
  config.baseline.deepstega.log_every = 50
  config.baseline.deepstega.checkpoint_every = 500
  config.baseline.deepstega.progress_bar = True
  # StegaNeRF (Li et al. 2023): the teacher's SH colour, a U-Net decoder and a classifier trained jointly, geometry
  # frozen; the SH learning rates are conceal.lr's (see conceal_jax/baselines/steganerf.py)
  config.baseline.steganerf = ml_collections.ConfigDict()
  config.baseline.steganerf.protocol = "all_views"  # 'all_views' (StegaNeRF's: I from every view) or 'check_view'
  config.baseline.steganerf.weight_render = 1.0     # MSE(render, initial render)
  config.baseline.steganerf.weight_hidden = 0.5     # MSE(U(render), I)
  config.baseline.steganerf.weight_clean = 0.5      # MSE(U(initial render), 0)
  config.baseline.steganerf.weight_classifier = 0.01  # BCE of the watermarked-vs-initial classifier
  config.baseline.steganerf.decoder_width = 16      # U-Net base channels (4 input channels: render + score)
  config.baseline.steganerf.classifier_width = 16   # channels of the classifier's first conv (then x2, x4)
  config.baseline.steganerf.decoder_lr = 1e-3     # fresh networks (no VGG16 start): 1e-4 learns I ~3x slower
  config.baseline.steganerf.classifier_lr = 1e-3
  config.baseline.steganerf.networks_lr_final_ratio = 1.0  # log-linear decay of both rates to this fraction
  config.baseline.steganerf.sh_adam_eps = 1e-8  # Adam eps of the SH colour (torch's default; 3D-GS uses 1e-15)
  config.baseline.steganerf.mask_at = "gradient"    # adaptive SH mask on the 'gradient' (StegaNeRF) or Adam's 'update'
  config.baseline.steganerf.log_every = 10
  config.baseline.steganerf.checkpoint_every = 1000
  config.baseline.steganerf.progress_bar = True

  # reveal mode
  config.reveal = ml_collections.ConfigDict()
  config.reveal.ply = ""      # any standard 3D-GS .ply
  config.reveal.decoder = ""  # decoder.msgpack written by conceal
  config.reveal.key = ""      # key.json written by conceal
  config.reveal.hidden = ""   # optional reference hidden image (path or sample name) to score against
  config.reveal.key_number = 0  # which key of the key file: 0 its check view, k its k-th extra_keys entry
  # the owner's own copy of the marked scene (e.g. the student.ply conceal wrote); set: the suspect scene is
  # registered onto it and the key moved with the similarity found (a turned, moved, resized or reordered
  # scene), reveal.json reporting the transform; empty: the key is used as saved
  config.reveal.owner = ""

  # verify mode: the reveal section's ply, decoder, key and hidden image (required here), scored and
  # decided at the threshold chosen from a calibration file of measured clean and marked scores
  config.verify = ml_collections.ConfigDict()
  config.verify.calibration = ""  # e.g. experiments/results/ownership_calibration.json (make bench-robust)
  return config
