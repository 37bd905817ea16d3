"""Every concealment recipe and demo variant builds a config the concealment accepts, and the ownership test's
recipes are what their docs say: the in_scene recipe plus one reading or training change each."""
import pytest

from conceal_jax.conceal import settings
from conceal_jax.configs import demo, lego_conceal, recipes


@pytest.fixture
def teacher(tmp_path):
  """A file where the teacher is named (validate checks that it exists; nothing reads it)."""
  path = tmp_path / "teacher.ply"
  path.write_text("")
  return str(path)


@pytest.mark.parametrize("recipe", recipes.RECIPES)
def test_each_lego_recipe_is_a_valid_concealment(recipe, teacher):
  config = lego_conceal.get_config(recipe)
  config.mark.teacher = teacher
  settings.validate(config)


@pytest.mark.parametrize("variant", ("",) + demo.VARIANTS)
def test_each_demo_variant_is_a_valid_concealment(variant, teacher):
  config = demo.get_config(variant)
  config.mode, config.mark.teacher = "conceal", teacher
  settings.validate(config)


def test_the_ownership_recipes_change_only_what_they_name():
  standardized, in_scene = lego_conceal.get_config("standardized"), lego_conceal.get_config("in_scene")
  assert standardized.conceal.decoder.input_norm == "standardize"
  standardized.conceal.decoder.input_norm = in_scene.conceal.decoder.input_norm
  assert standardized.to_dict() == in_scene.to_dict()
  owned, pruned = demo.get_config("owned"), demo.get_config("pruned")
  assert owned.conceal.attacks.prune_small_max == recipes.PRUNE_SHARE
  assert owned.conceal.attacks.blur_max == recipes.ATTACK_BLUR and owned.conceal.decoder.clip_input
  assert recipes.through_attacks(pruned).to_dict() == owned.to_dict()


def test_the_recipe_at_the_decoders_size_changes_only_the_keys_size_and_its_decoys():
  fast, slow = lego_conceal.get_config("recommended_at_decoder_size"), lego_conceal.get_config("recommended")
  assert fast.conceal.carrier.at_decoder_size and fast.conceal.leakage.decoy_views == recipes.DECODER_SIZE_DECOYS
  for section, names in (("carrier", ("at_decoder_size", "linear_maps_mb")),
                         ("leakage", ("decoy_views", "decoy_translation"))):
    for name in names:
      setattr(getattr(fast.conceal, section), name, getattr(getattr(slow.conceal, section), name))
  assert fast.to_dict() == slow.to_dict()


def test_the_recommended_recipe_is_the_random_decoy_one_with_its_key_axes_watched_and_its_decoder_polished():
  """recipes.recommended differs from the recipe before 2026-12-01 (bench-conceal's recommended_random_decoys row)
  only in the decoys' directions and the decoder's polish (its length and its share of decimated copies)."""
  from experiments import bench_conceal
  now, before = (bench_conceal.run_config("lego", "TEACHER.ply", row, 16, 0, 0)
                 for row in ("recommended", "recommended_random_decoys"))
  assert now.conceal.leakage.decoy_key_axes and not before.conceal.leakage.decoy_key_axes
  polish, unpolished = now.conceal.decoder_opt, before.conceal.decoder_opt
  assert (polish.polish_steps, polish.polish_merge_fraction) == (recipes.POLISH_STEPS, recipes.POLISH_MERGE_FRACTION)
  assert (unpolished.polish_steps, unpolished.polish_merge_fraction) == (0, None)
  assert recipes.POLISH_MERGE_FRACTION > now.conceal.attacks.merge_fraction > 0  # the polish reads more merges
  now.conceal.leakage.decoy_key_axes, polish.polish_steps, polish.polish_merge_fraction = False, 0, None
  assert now.to_dict() == before.to_dict()
