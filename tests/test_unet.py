"""Tests of the ConcealGS decoder: shapes, size, VGG16 weight loading, FLOP estimate, gradients."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import unet
from conceal_jax.gs import metrics
from tests.helpers import assert_finite_tree

SMALL = 8


@pytest.fixture(scope="module")
def small_params():
  return unet.init_decoder(jax.random.key(0), SMALL)


@pytest.fixture(scope="module")
def paper_params():
  return unet.init_decoder(jax.random.key(1), unet.PAPER_WIDTH)


def expected_param_count(base: int) -> int:
  """Independent count from the architecture description: 3x3 convs, 2x2 transposed convs, 1x1 out."""
  c1, c2, c3, c4 = base, 2 * base, 4 * base, 8 * base
  conv = lambda k, cin, cout: k * k * cin * cout + cout
  encoder = (conv(3, 3, c1) + conv(3, c1, c1) + conv(3, c1, c2) + conv(3, c2, c2) + conv(3, c2, c3)
             + 2 * conv(3, c3, c3) + conv(3, c3, c4) + 2 * conv(3, c4, c4))
  decoder = sum(conv(2, 2 * c, c) + conv(3, 2 * c, c) + conv(3, c, c) for c in (c3, c2, c1))
  return encoder + decoder + conv(1, c1, 3)


def test_output_shape(small_params):
  x = jnp.zeros((2, 64, 64, 3))
  y = unet.UNet(SMALL).apply({"params": small_params}, x)
  assert y.shape == (2, 64, 64, 3) and y.dtype == jnp.float32


def test_rejects_bad_input_shape(small_params):
  model = unet.UNet(SMALL)
  with pytest.raises(ValueError, match="divisible"):
    model.apply({"params": small_params}, jnp.zeros((1, 60, 64, 3)))
  with pytest.raises(ValueError, match=r"\[B, H, W, C\]"):
    model.apply({"params": small_params}, jnp.zeros((64, 64, 3)))
  with pytest.raises(ValueError, match="multiple of 8"):
    unet.init_decoder(jax.random.key(0), SMALL, image_size=60)
  with pytest.raises(ValueError, match="in_channels"):
    unet.init_decoder(jax.random.key(0), SMALL, in_channels=0)


def test_input_channels_come_from_the_input():
  """A decoder made for 4 input channels (StegaNeRF: render + classifier score) differs from the 3-channel one
  only in enc1_1's kernel, and still outputs an image."""
  three, four = (unet.init_decoder(jax.random.key(0), SMALL, 16, in_channels=c) for c in (3, 4))
  assert four["enc1_1"]["kernel"].shape == (3, 3, 4, SMALL)
  assert {k: jax.tree.map(jnp.shape, v) for k, v in three.items() if k != "enc1_1"} == \
      {k: jax.tree.map(jnp.shape, v) for k, v in four.items() if k != "enc1_1"}
  y = unet.UNet(SMALL).apply({"params": four}, jnp.ones((2, 16, 16, 4)))
  assert y.shape == (2, 16, 16, 3) and bool(jnp.all(jnp.isfinite(y)))
  with pytest.raises(Exception):  # a 3-channel input does not fit the 4-channel kernel
    unet.UNet(SMALL).apply({"params": four}, jnp.ones((2, 16, 16, 3)))


def test_module_names_follow_vgg16():
  shapes = jax.eval_shape(unet.UNet(SMALL).init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)))["params"]
  assert set(unet.ENCODER_NAMES) == {n for n in shapes if n.startswith("enc")}
  assert unet.ENCODER_NAMES[0] == "enc1_1" and unet.ENCODER_NAMES[-1] == "enc4_3"
  assert len(unet.ENCODER_NAMES) == 10


@pytest.mark.parametrize("base", [SMALL, 16, unet.PAPER_WIDTH])
def test_param_count(base):
  shapes = jax.eval_shape(unet.UNet(base).init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)))["params"]
  assert unet.count_params(shapes) == expected_param_count(base)


def test_paper_width_param_count():
  # VGG16 conv1_1..conv4_3 alone is 7.63M parameters; the decoder adds about 3M.
  assert expected_param_count(unet.PAPER_WIDTH) == 10_647_363


def test_vgg16_copy(paper_params):
  vgg = metrics.vgg16_conv_params()
  loaded = unet.load_vgg16_encoder(paper_params)
  for k, name in enumerate(unet.ENCODER_NAMES[1:], 1):
    np.testing.assert_array_equal(np.asarray(loaded[name]["kernel"]), vgg[k][0])
    np.testing.assert_array_equal(np.asarray(loaded[name]["bias"]), vgg[k][1])
  # conv1_1 stays fresh (not VGG's), and nothing else changes, the input included.
  assert not np.allclose(np.asarray(loaded["enc1_1"]["kernel"]), vgg[0][0])
  for name in paper_params:
    if name not in unet.ENCODER_NAMES[1:]:
      for leaf in ("kernel", "bias"):
        assert loaded[name][leaf] is paper_params[name][leaf]
  assert not np.array_equal(np.asarray(paper_params["enc1_2"]["kernel"]), vgg[1][0])


def test_vgg16_layout_matches_torchvision():
  # torchvision vgg16 features[0].weight[0, 0] (output 0, input channel R), rows = kernel height.
  kernel = metrics.vgg16_conv_params()[0][0]
  np.testing.assert_allclose(kernel[:, :, 0, 0], [[-0.5537, 0.1427, 0.5290],
                                                  [-0.5831, 0.3566, 0.7657],
                                                  [-0.6902, -0.0480, 0.4841]], atol=1e-4)


def test_vgg16_wrong_width(small_params):
  with pytest.raises(ValueError, match="base_channels=64"):
    unet.load_vgg16_encoder(small_params)


def test_flops_paper_width():
  flops = unet.count_flops(unet.PAPER_WIDTH)
  # The task estimate is ~4 GFLOP forward (~12 forward + backward); this architecture computes 5.2.
  assert 3e9 < flops < 7e9
  assert flops == pytest.approx(5.2e9, rel=0.01)
  # Every conv's cost scales with channels squared except the 3-channel input and output convs.
  assert unet.count_flops(32) == pytest.approx(flops / 4, rel=0.01)


def test_flops_match_xla_cost_analysis(small_params):
  x = jnp.zeros((1, 64, 64, 3))
  compiled = jax.jit(unet.UNet(SMALL).apply).lower({"params": small_params}, x).compile()
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, list) else cost
  if not cost or "flops" not in cost:
    pytest.skip("backend gives no cost analysis")
  # XLA skips taps on the zero padding (about 6% at this width), the analytic count keeps them.
  assert 0.88 < cost["flops"] / unet.count_flops(SMALL) < 1.0


def test_jit_and_finite_gradients(small_params):
  model = unet.UNet(SMALL)
  x = jax.random.uniform(jax.random.key(2), (2, 64, 64, 3))
  target = jax.random.uniform(jax.random.key(3), (2, 64, 64, 3))

  @jax.jit
  def loss_and_grad(params):
    loss = lambda p: jnp.mean(jnp.abs(model.apply({"params": p}, x) - target))
    return jax.value_and_grad(loss)(params)

  loss, grads = loss_and_grad(small_params)
  assert np.isfinite(float(loss))
  assert_finite_tree(grads, "gradient")
  assert jax.tree.structure(grads) == jax.tree.structure(small_params)
  # The network is connected end to end: every layer, enc1_1 included, gets a nonzero gradient.
  for path, g in jax.tree_util.tree_leaves_with_path(grads):
    assert np.any(np.asarray(g) != 0), jax.tree_util.keystr(path)



def _reference_statistics(images, input_norm):
  """float64 numpy: each image's mean over pixels and channels, and sqrt(variance + floor^2) or 1."""
  x = np.asarray(images, np.float64)
  mean = x.mean(axis=(1, 2, 3), keepdims=True)
  std = np.sqrt(((x - mean)**2).mean(axis=(1, 2, 3), keepdims=True) + unet.STD_FLOOR**2)
  return mean, std if input_norm == "standardize" else np.ones_like(std)


@pytest.mark.parametrize("input_norm", ["center", "standardize"])
def test_input_statistics_match_float64_reference_and_invert(input_norm):
  x = jax.random.uniform(jax.random.key(4), (3, 16, 16, 3))
  mean, std = unet.image_statistics(x, input_norm)
  ref_mean, ref_std = _reference_statistics(x, input_norm)
  np.testing.assert_allclose(mean, ref_mean, rtol=1e-6)
  np.testing.assert_allclose(std, ref_std, rtol=1e-6)
  np.testing.assert_allclose(unet.standardize_images(x, mean, std), (np.asarray(x, np.float64) - ref_mean) / ref_std,
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(unet.unstandardize_images(unet.standardize_images(x, mean, std), mean, std), x,
                             atol=1e-6)


@pytest.mark.parametrize("input_norm, changes", [("center", ((1.0, -0.1), (1.0, 0.07))),
                                                 ("standardize", ((1.0, -0.1), (1.2, 0.0), (0.8, 0.05)))])
def test_normalised_unet_is_equivariant(small_params, input_norm, changes):
  """F(a x + b) = a F(x) + b for the changes the norm undoes: the U-Net reads the same image (up to the std
  floor, far below these images' spread); the plain U-Net does not."""
  model = unet.UNet(SMALL, input_norm=input_norm)
  x = jax.random.uniform(jax.random.key(5), (2, 64, 64, 3), minval=0.2, maxval=0.8)
  base = model.apply({"params": small_params}, x)
  for a, b in changes:
    np.testing.assert_allclose(model.apply({"params": small_params}, a * x + b), a * base + b, atol=2e-3)
  plain = unet.UNet(SMALL).apply({"params": small_params}, x - 0.1)
  assert np.max(np.abs(plain - (unet.UNet(SMALL).apply({"params": small_params}, x) - 0.1))) > 1e-2


@pytest.mark.parametrize("input_norm", ["center", "standardize"])
def test_normalised_unet_uses_the_same_params_and_stays_finite_on_flat_images(small_params, input_norm):
  """A flat image (zero spread) is the hard case: the floor keeps values and gradients finite."""
  model = unet.UNet(SMALL, input_norm=input_norm)
  flat = jnp.full((1, 16, 16, 3), 0.7)
  out = jax.jit(model.apply)({"params": small_params}, flat)
  assert np.all(np.isfinite(out))
  grads = jax.jit(jax.grad(lambda p, x: jnp.mean(model.apply({"params": p}, x)), argnums=(0, 1)))(small_params, flat)
  assert_finite_tree(grads, "gradient")
  assert jax.tree.structure(grads[0]) == jax.tree.structure(small_params)


def test_unknown_input_norm_is_named(small_params):
  with pytest.raises(ValueError, match="input_norm"):
    unet.UNet(SMALL, input_norm="whiten").apply({"params": small_params}, jnp.zeros((1, 8, 8, 3)))


def test_clipped_reading_ignores_values_outside_the_unit_range(small_params):
  """Reading.clip: a render with whites above 1 and blacks below 0 reveals exactly what its clipped image
  does (no signal can live outside [0, 1]); the paper's reading sees the difference. Gradients stay finite."""
  from conceal_jax.conceal import reveal
  rng = np.random.default_rng(6)
  renders = jnp.asarray(rng.uniform(-0.2, 1.3, (2, 32, 32, 3)), jnp.float32)
  clipped = jnp.clip(renders, 0.0, 1.0)
  reading = reveal.Reading("center", clip=True)
  np.testing.assert_allclose(reveal.reveal_renders(small_params, renders, SMALL, 16, reading),
                             reveal.reveal_renders(small_params, clipped, SMALL, 16, reading), atol=1e-6)
  paper = lambda x: reveal.reveal_renders(small_params, x, SMALL, 16)
  assert np.max(np.abs(paper(renders) - paper(clipped))) > 1e-3
  grads = jax.grad(lambda x: jnp.sum(reveal.decode(small_params, SMALL, reveal.resize_for_decoder(x, 16, True))))(
      renders)
  assert np.all(np.isfinite(grads)) and np.all(np.asarray(grads)[np.asarray(renders) > 1.0] == 0)
  info = dict(hidden_size=16, **reading.key_fields())
  assert reveal.Reading.from_key(info) == reading and reveal.Reading.from_key({}) == reveal.PAPER_READING


def test_a_key_of_a_retired_decoder_reading_is_refused_by_name():
  """Keys that recorded the retired keyed decoders (sign channels, sign field) cannot be revealed by today's U-Net:
  one clear error naming the field; the same fields at their no-op value read as the plain reading."""
  from conceal_jax.conceal import reveal
  plain = dict(hidden_size=16, decoder_input_norm="standardize", decoder_clip_input=True)
  assert reveal.Reading.from_key(dict(plain, decoder_pattern=0, decoder_modulation=0.0)) == reveal.Reading(
      "standardize", True)
  for field, value in (("decoder_pattern", 4), ("decoder_modulation", 1.5)):
    with pytest.raises(ValueError, match=field):
      reveal.Reading.from_key(dict(plain, **{field: value}))


@pytest.mark.parametrize("input_norm", ("none", "standardize"))
def test_a_reference_decoder_reads_its_reference_beside_the_input(input_norm):
  """UNet.reference_size: the params hold the reference started at the given image and enc1_1 reads 3 more
  channels; the output is the plain U-Net's on the input with the reference as channels 4-6 (normalised with the
  input's statistics), so a change of the reference changes it; gradients (the reference's too) are finite; the
  key records the reading."""
  from conceal_jax.conceal import reveal
  rng = np.random.default_rng(7)
  reference = jnp.asarray(rng.uniform(size=(16, 16, 3)), jnp.float32)
  params = unet.init_decoder(jax.random.key(2), SMALL, 16, reference=reference)
  np.testing.assert_array_equal(params["reference"], reference)
  assert params["enc1_1"]["kernel"].shape == (3, 3, 6, SMALL)
  images = jnp.asarray(rng.uniform(size=(2, 16, 16, 3)), jnp.float32)
  reading = reveal.Reading(input_norm, reference=True)
  out = reveal.decode(params, SMALL, images, reading)
  plain = {name: value for name, value in params.items() if name != "reference"}
  mean, std = unet.image_statistics(images, input_norm) if input_norm != "none" else (0.0, 1.0)
  read = jnp.concatenate([(images - mean) / std, jnp.broadcast_to((reference - mean) / std, images.shape)], -1)
  expected = unet.UNet(SMALL).apply({"params": plain}, read) * std + mean
  np.testing.assert_allclose(out, expected, atol=1e-5)
  moved = reveal.decode(dict(params, reference=reference[::-1]), SMALL, images, reading)
  assert np.max(np.abs(np.asarray(moved - out))) > 1e-4
  assert_finite_tree(jax.grad(lambda p: jnp.sum(reveal.decode(p, SMALL, images, reading) ** 2))(params))
  assert reveal.Reading.from_key(dict(hidden_size=16, **reading.key_fields())) == reading
  with pytest.raises(ValueError, match="reference"):
    reveal.decode(params, SMALL, images[:, :8, :8], reading)
  with pytest.raises(ValueError, match="disagree on a reference"):
    reveal.decode(params, SMALL, images, reveal.Reading(input_norm))
  with pytest.raises(ValueError, match="reference must be"):
    unet.init_decoder(jax.random.key(2), SMALL, 16, reference=reference[:8])
