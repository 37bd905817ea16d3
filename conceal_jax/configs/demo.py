"""The embedded demo scene (generated, 128x128, 50 train / 10 test views) with short schedules.

`make demo` runs the whole pipeline with it: train the teacher, conceal, reveal:

  python -m conceal_jax.main --config=conceal_jax/configs/demo.py --workdir=workdirs/demo/teacher
  python -m conceal_jax.main --config=conceal_jax/configs/demo.py --workdir=workdirs/demo/conceal \
      --config.mode=conceal --config.mark.teacher=workdirs/demo/teacher/point_cloud.ply
  python -m conceal_jax.main --config=conceal_jax/configs/demo.py --workdir=workdirs/demo/reveal \
      --config.mode=reveal --config.reveal.ply=workdirs/demo/conceal/student.ply \
      --config.reveal.decoder=workdirs/demo/conceal/decoder.msgpack \
      --config.reveal.key=workdirs/demo/conceal/key.json --config.reveal.hidden=astronaut

Its concealment is a short in_scene recipe (the mark in the teacher's Gaussians): leakage control (32 decoys), the
gentle student and the narrow decoder at a constant rate (a decaying one costs a 1300-step run more than it gains).
The survival bench's variants (issue 39): `demo.py:film` is the first faint film (the mark in a carrier film only an
unseen key sees, of faint layers whose colours train at a higher rate, through 8-bit colours) with 64 decoys near the
key; the designs beside it: `film_pub` (film trained through decimation too, recipes.through_decimation), `film_web`
(film_pub at an opacity and within colours the publishing formats store unchanged, recipes.publishable_film),
`film_watch` (film_web with 192 decoys on most steps, recipes.watched_key), `film_long` (the design of the recommended
recipe before it trained through the converter's own groups: film_watch with 768 decoys and twice as long,
FILM_ITERATIONS), `film_deep` (film_long trained through merges
deeper than pairs, recipes.DEEP_MERGE_DEPTH), `film_stack` (film_long's splats in colour-tied stacks of two,
recipes.stacked_film), `film_faint` (its colours at the gentle student's rate), `film_reset` (one layer at opacity
0.5, trained through opacity resets), `film_far` (film_reset with the key half a camera distance from the orbit
target and the film as far again); `demo.py:drift` trains through parameter drift (recipes.through_drift);
`demo.py:pruned` through size pruning with the key watched closely, twice as long (recipes.through_pruning,
watched_key); `demo.py:owned`, the ownership test's demo recipe (issue 40), is `pruned` trained through blur and
noise too, its decoder reading clipped renders (recipes.through_attacks); `demo.py:orbit` keys a secret pose on the
orbit instead of a training camera; `demo.py:tolerant` gives the key a tolerance radius (recipes.tolerant_key);
`demo.py:axial` watches the decoder alone along and about the key's own axes (recipes.axial_decoys);
`demo.py:referenced` is axial with a decoder that reads a reference image (recipes.referenced_decoder) and no blur or
noise of the check render (recipes.owner_rendered); `demo.py:axes` watches the key's axes (recipes.watched_axes: those
decoys on half the steps, L_d^- weighted 2.5, L_kd 4), twice as long."""
from conceal_jax.configs import default, recipes


VARIANTS = ("film", "film_pub", "film_web", "film_watch", "film_long", "film_deep", "film_stack", "film_faint",
            "film_reset", "film_far", "drift", "pruned", "owned", "orbit", "tolerant", "axial", "referenced", "axes")
# The faint films whose colours train at the vivid rate, each building on the one before from film_pub on.
VIVID_FILMS = ("film", "film_pub", "film_web", "film_watch", "film_long", "film_deep", "film_stack")
# A closely watched key needs twice the demo's concealment to read its film (or a pruned student).
FILM_ITERATIONS = 2600
# film_watch's decoys, as its rows were measured (recipes.watched_key's own count came after).
FILM_WATCH_DECOYS = 192


def get_config(variant: str = ""):
  config = default.get_config()
  config.mode = "train"
  config.data.path = "demo"
  config.data.background = "white"
  config.init.num_random_points = 3000
  config.train.iterations = 1500
  config.train.sh_increase_every = 300
  config.train.lr.means_steps = 1500
  config.train.densify.start = 200
  config.train.densify.until = 1000
  config.train.densify.opacity_reset_every = 600
  config.train.checkpoint_every = 500
  config.conceal.iterations = 1300
  config.conceal.checkpoint_every = 200
  config.conceal.eval_every = 100
  config = recipes.leakage_control(recipes.narrow_decoder(config), decoy_views=32)
  config = recipes.gentle_student(config)
  if variant and variant not in VARIANTS:
    raise ValueError(f"unknown demo variant {variant!r}; choose one of {VARIANTS} or none")
  if variant == "drift":
    config = recipes.through_drift(config)
  if variant in ("pruned", "owned"):  # a decoder taught to read pruned students reads near the key too: watch it
    config = recipes.watched_key(recipes.through_pruning(config))
    config.conceal.iterations = FILM_ITERATIONS
  if variant == "owned":
    config = recipes.through_attacks(config)
  if variant == "orbit":
    config.mark.key_kind = "orbit"
  if variant == "tolerant":
    config = recipes.tolerant_key(config)
  if variant in ("axial", "referenced"):
    config = recipes.axial_decoys(config)
  if variant == "referenced":
    config = recipes.referenced_decoder(recipes.owner_rendered(config))
  if variant == "axes":
    config = recipes.watched_axes(config)
    config.conceal.iterations = FILM_ITERATIONS
  if variant.startswith("film"):  # every pose near the key sees the film: 64 decoys, drawn more often
    config = recipes.through_quantization(recipes.unseen_carrier(config))
    config.conceal.decoder.input_norm = "standardize"
    config = recipes.leakage_control(config, recipes.DECOY_VIEWS, decoy_fraction=0.4)
    faint = variant in VIVID_FILMS + ("film_faint",)
    config = recipes.faint_film(config) if faint else recipes.through_reset(config)
  if variant in VIVID_FILMS:
    config = recipes.vivid_film(config)
  if variant in VIVID_FILMS[1:]:  # film_pub and what builds on it
    deep = variant == "film_deep"
    config = recipes.through_decimation(config, depth=recipes.DEEP_MERGE_DEPTH if deep else recipes.MERGE_DEPTH)
  if variant in VIVID_FILMS[2:]:
    config = recipes.publishable_film(config)
  if variant == "film_watch":
    config = recipes.watched_key(config, decoy_views=FILM_WATCH_DECOYS)
  if variant in ("film_long", "film_deep", "film_stack"):
    config = recipes.watched_key(config)
    config.conceal.iterations = FILM_ITERATIONS
  if variant == "film_stack":
    config = recipes.stacked_film(config)
  if variant == "film_far":  # the key half way out and the film as far again: a film alike from nearby poses
    config.mark.key_offset, config.conceal.carrier.distance = 0.5, 0.5
  return config
