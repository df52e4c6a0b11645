"""experiments/studies/envmap_poles.py: the seed's "spherical map, prone to distortion", measured."""
from experiments.studies.envmap_poles import errors_by_elevation


def test_equirect_is_worst_at_the_poles_and_oversamples_them():
    # Equal texel count (cube 6 x 24^2 = 3456, equirect 42 x 84 = 3528), bilinear, 2.5-degree bins.
    r = errors_by_elevation(24, n=100_000, bins=36)
    assert abs(r["texels"]["equirect"] - r["texels"]["cube"]) < 0.03 * r["texels"]["cube"]
    # Within 2.5 degrees of either pole the equirect map's largest error is over twice the cube's (measured
    # 2.7x / 4.3x): above its last texel row a lookup can only clamp, a first-order error.
    for b in (0, 35):
        assert r["equirect"]["max"][b] > 2 * r["cube"]["max"][b], b
    # On average it is better there (measured 0.42-0.9x): its rows crowd the pole with texels, the distortion
    # spending texels where the cube spends fewer.
    for b in (0, 1, 34, 35):
        assert r["equirect"]["mean"][b] < r["cube"]["mean"][b], b
