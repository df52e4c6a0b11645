"""difftex.texture.wrap: every wrap rule against its definition, and the continuous forms against the integer one."""
from __future__ import annotations

import pytest
import torch

from difftex.texture.wrap import (WRAP_CODES, WRAP_MODES, drop_periods, floor_index, fold, fold_slope, pad_index,
                                  parse_wrap, wrap_index)

f64 = torch.float64


def _definition(i: int, n: int, mode: str) -> tuple[int, bool]:
    """The table of the module docstring, one index at a time: (texel, inside)."""
    if mode == "repeat":
        return i % n, True
    if mode == "mirror":
        r = i % (2 * n)
        return (r if r < n else 2 * n - 1 - r), True
    return min(max(i, 0), n - 1), 0 <= i < n  # clamp; border reads the constant outside


@pytest.mark.parametrize("mode", WRAP_MODES)
@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_wrap_index_follows_the_definition(mode, n):
    i = torch.arange(-3 * n - 2, 3 * n + 3)
    idx, valid = wrap_index(i, n, mode)
    want = [_definition(int(k), n, mode) for k in i]
    assert idx.tolist() == [w[0] for w in want]
    if mode == "border":
        assert valid.tolist() == [w[1] for w in want]
    else:
        assert valid is None


def test_floor_index_maps_bad_coordinates_inside():
    x = torch.tensor([-1.5, 0.0, 2.7, float("nan"), float("inf"), -float("inf"), 1e300], dtype=f64)
    assert floor_index(x).tolist() == [-2, 0, 2, 0, 0, 0, 2 ** 52]
    assert wrap_index(torch.tensor([2.5, -0.5]), 2, "repeat")[0].tolist() == [0, 1]  # floats go through floor


@pytest.mark.parametrize("mode", ["repeat", "mirror"])
@pytest.mark.parametrize("n", [1, 3, 4])
def test_pad_index_reads_what_wrap_index_reads(mode, n):
    p = 2
    assert pad_index(mode, p, n, torch.device("cpu")).tolist() == \
        wrap_index(torch.arange(-p, n + p), n, mode)[0].tolist()


@pytest.mark.parametrize("mode", ["repeat", "mirror"])
def test_fold_lands_on_the_texel_wrap_index_reads(mode):
    # Texel j of an n-texel axis covers u in [j / n, (j + 1) / n); folding u and reading the texel under it
    # must give the texel that wrap_index gives for floor(u n). Points off the texel edges.
    n = 5
    u = (torch.arange(-40, 41, dtype=f64) + 0.37) / 7
    folded = fold(u, mode)
    assert ((folded >= 0) & (folded <= 1)).all()
    under = torch.floor(folded * n).clamp(max=n - 1).long()
    assert torch.equal(under, wrap_index(torch.floor(u * n).long(), n, mode)[0])


@pytest.mark.parametrize("mode", WRAP_MODES)
def test_fold_slope_is_the_derivative_of_fold(mode):
    u = (torch.arange(-30, 31, dtype=f64) + 0.29) / 9  # away from the folds' kinks
    h = 1e-7
    fd = (fold(u + h, mode) - fold(u - h, mode)) / (2 * h)
    slope = fold_slope(u, mode)
    torch.testing.assert_close(fd, torch.ones_like(u) if slope is None else slope, atol=1e-6, rtol=0)
    if mode in ("clamp", "border"):
        assert torch.equal(fold(u, mode), u)


@pytest.mark.parametrize("mode", WRAP_MODES)
def test_drop_periods_keeps_the_texel_and_the_gradient(mode):
    u = torch.tensor([-1e6 + 0.3, -2.6, -0.4, 0.2, 1.7, 3.5, 1e6 + 0.25], dtype=f64, requires_grad=True)
    v = drop_periods(u, mode)
    period = {"repeat": 1.0, "mirror": 2.0}.get(mode)
    if period is None:
        assert torch.equal(v, u)
    else:
        assert ((v >= 0) & (v < period)).all()
        k = (u - v) / period
        assert torch.equal(k, torch.round(k))  # whole periods only
    (g,) = torch.autograd.grad(v.sum(), u)
    assert torch.equal(g, torch.ones_like(u))


def test_parse_wrap_and_codes():
    assert parse_wrap("mirror") == ("mirror", "mirror")
    assert parse_wrap(["repeat", "border"]) == ("repeat", "border")
    with pytest.raises(ValueError, match=r"wrap: unknown mode 'wrap'; expected one of \('repeat', 'clamp'"):
        parse_wrap("wrap")
    with pytest.raises(ValueError, match=r"wrap: expected one mode or a pair \(wrap_u, wrap_v\), got 3 items"):
        parse_wrap(("repeat",) * 3)
    with pytest.raises(TypeError, match=r"wrap: expected a str or a \(wrap_u, wrap_v\) pair, got int"):
        parse_wrap(3)
    with pytest.raises(TypeError, match=r"wrap: modes must be strings, got NoneType"):
        parse_wrap(("repeat", None))
    assert WRAP_CODES == {"repeat": 0, "clamp": 1, "mirror": 2, "border": 3}
