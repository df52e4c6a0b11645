"""experiments/studies/solid_textures.py runs end to end at a tiny size and writes its figure."""
import matplotlib.image

from experiments.studies.solid_textures import main


def test_figure_is_written(tmp_path):
    out = tmp_path / "solid.png"
    score = main(["--size", "32", "--res", "48", "--ao-directions", "4", "--ao-resolution", "32", "--out", str(out)])
    img = matplotlib.image.imread(out)
    assert img.shape[0] > 100 and img.shape[1] > 200 and img.std() > 0.1
    # A 32^2 bake of marble is a blurred copy of the solid texture: 16.6 dB measured (36.2 dB at 256^2).
    assert 13.0 < score < 22.0
