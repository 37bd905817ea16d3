"""Atomic writes: a failed write leaves the old file as it was and no temporary file behind."""
import pytest

from conceal_jax.core import fileio


def test_copy_file_replaces_the_target_whole(tmp_path):
  source, target = tmp_path / "source.bin", tmp_path / "out" / "target.bin"
  source.write_bytes(b"new contents")
  fileio.write_bytes(target, b"old")
  fileio.copy_file(source, target)
  assert target.read_bytes() == b"new contents"
  assert sorted(p.name for p in target.parent.iterdir()) == ["target.bin"]


def test_a_failed_copy_or_write_keeps_the_old_file(tmp_path):
  target = tmp_path / "target.json"
  fileio.write_json(target, dict(step=1))
  with pytest.raises(FileNotFoundError):
    fileio.copy_file(tmp_path / "missing.bin", target)
  with pytest.raises(RuntimeError), fileio.atomic_path(target) as tmp:  # a writer that dies half-way
    with open(tmp, "w") as f:
      f.write('{"st')
    raise RuntimeError("killed")
  assert target.read_text() == '{\n  "step": 1\n}\n'
  assert sorted(p.name for p in tmp_path.iterdir()) == ["target.json"]


def test_a_setting_added_since_a_run_was_saved_is_no_change_at_its_default(tmp_path):
  """core.workdir.claim: a saved config without a key the code added since resumes when the key is at its default
  (the run ran as the default does), and is refused when the key is set otherwise or a saved key changed."""
  from conceal_jax.core import workdir
  saved = {"conceal": {"iterations": 10, "progress_bar": True}}
  defaults = {"conceal": {"iterations": 5, "carrier": {"layers": 1}}}
  workdir.claim(str(tmp_path), saved)
  workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "carrier": {"layers": 1}}}, defaults=defaults)
  with pytest.raises(ValueError, match="conceal.carrier.layers"):
    workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "carrier": {"layers": 3}}}, defaults=defaults)
  assert workdir.differing_keys(saved, {"conceal": {"iterations": 10, "carrier": {"layers": 1}}}) == [
      "conceal.carrier.layers"]  # without the defaults, any added key differs
  assert workdir.differing_keys({"a": 1}, {}, defaults={"a": 1}) == ["a"]  # a key the config lost is a change


def test_a_saved_config_takes_the_keys_added_since_at_their_defaults():
  from conceal_jax.core import workdir
  saved = {"conceal": {"iterations": 10, "leakage": {"decoy_views": 4}}, "gone": 1}
  defaults = {"conceal": {"iterations": 5, "leakage": {"decoy_views": 0, "decoy_key_axes": False}}, "seed": 0}
  assert workdir.with_defaults(saved, defaults) == {
      "conceal": {"iterations": 10, "leakage": {"decoy_views": 4, "decoy_key_axes": False}}, "gone": 1, "seed": 0}
  assert workdir.differing_keys(saved, workdir.with_defaults(saved, defaults), defaults=defaults) == []


def test_a_setting_retired_since_a_run_was_saved_is_no_change_at_its_retired_value(tmp_path):
  """core.workdir.claim: a saved config holding a key the code removed since resumes when the run had it at the
  value the code now always has (`retired`), and is refused at any other value; the package's retired settings
  are all gone from the default config."""
  from conceal_jax.configs import default
  from conceal_jax.core import workdir
  retired = {"conceal.decoder.pattern": 0}
  workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "decoder": {"pattern": 0}}})
  workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "decoder": {}}}, retired=retired)
  (tmp_path / workdir.CONFIG_FILE).unlink()
  workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "decoder": {"pattern": 4}}})
  with pytest.raises(ValueError, match="conceal.decoder.pattern"):
    workdir.claim(str(tmp_path), {"conceal": {"iterations": 10, "decoder": {}}}, retired=retired)
  flat = workdir.flatten(default.get_config().to_dict())
  assert default.RETIRED_SETTINGS and not set(default.RETIRED_SETTINGS) & set(flat)


def test_a_figure_saved_with_a_palette_keeps_its_pixels_close_in_fewer_colours(tmp_path):
  """save_figure(palette=N): the same image size, at most N colours, each pixel near the full-colour figure's."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  import numpy as np
  from PIL import Image

  def figure():
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.bar(range(5), [0.2, 0.9, 0.5, 0.7, 0.1], color=["C0", "C3", "C0", "C3", "C0"])
    ax.set_title("bars")
    return fig

  fileio.save_figure(figure(), tmp_path / "full.png", dpi=60)
  fileio.save_figure(figure(), tmp_path / "palette.png", dpi=60, palette=16)
  with Image.open(tmp_path / "full.png") as full, Image.open(tmp_path / "palette.png") as reduced:
    assert reduced.mode == "P" and full.size == reduced.size
    assert len(reduced.getcolors()) <= 16
    difference = np.abs(np.asarray(full.convert("RGB"), float) - np.asarray(reduced.convert("RGB"), float))
  assert np.median(difference) == 0.0 and difference.mean() < 4.0
  assert sorted(p.name for p in tmp_path.iterdir()) == ["full.png", "palette.png"]
