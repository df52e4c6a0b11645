"""difftex.metrics.psnr: the one PSNR of tests, benchmarks and experiments."""
from __future__ import annotations

import math

import pytest
import torch

from difftex.metrics import psnr


def test_hand_computed_value():
    # Errors 0.1, 0.2, 0, 0.2 on four values: MSE = (0.01 + 0.04 + 0 + 0.04) / 4 = 0.0225,
    # PSNR = 10 log10(1 / 0.0225) = 16.4782 dB; peak 2 adds 10 log10(4) = 6.0206 dB.
    ref = torch.tensor([[0.5, 0.5], [0.5, 0.5]])
    x = ref + torch.tensor([[0.1, -0.2], [0.0, 0.2]])
    assert psnr(x, ref) == pytest.approx(16.478175, abs=1e-5)
    assert psnr(x, ref, 2.0) == pytest.approx(16.478175 + 6.020600, abs=1e-5)
    d = torch.tensor([0.1, -0.2, 0.0, 0.2], dtype=torch.float64)
    assert psnr(0.5 + d, torch.full((4,), 0.5, dtype=torch.float64)) == pytest.approx(10 * math.log10(1 / 0.0225),
                                                                                     abs=1e-12)


def test_exact_match_is_inf():
    ref = torch.rand(1, 3, 4, 4, generator=torch.Generator().manual_seed(0))
    assert psnr(ref.clone(), ref) == math.inf  # not clamped (a former copy stopped at 120 dB)


def test_mask_scores_only_its_pixels_and_broadcasts_over_channels():
    ref = torch.zeros(1, 3, 2, 2)
    x = torch.zeros(1, 3, 2, 2)
    x[..., 0, 0] = 0.1   # scored: MSE 0.01 -> 20 dB
    x[..., 1, 1] = 0.5   # unscored
    mask = torch.tensor([[True, True], [True, False]]).view(1, 1, 2, 2)
    # Three scored pixels of three channels, one of them off by 0.1: MSE = 0.01 / 3.
    assert psnr(x, ref, mask=mask) == pytest.approx(10 * math.log10(3 / 0.01), abs=1e-4)
    # A NaN outside the mask does not count; a reference broadcast from one channel does.
    x[..., 1, 1] = float("nan")
    assert psnr(x, ref[:, :1], mask=mask) == pytest.approx(10 * math.log10(3 / 0.01), abs=1e-4)


def test_non_finite_reference_pixels_are_left_out():
    ref = torch.rand(1, 3, 8, 8, generator=torch.Generator().manual_seed(5))
    x = ref + 0.01
    ref_nan = ref.clone()
    ref_nan[..., :2, :] = float("nan")
    assert psnr(x, ref_nan) == pytest.approx(40.0, abs=1e-4)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_output_is_nan(bad):
    ref = torch.rand(1, 1, 4, 4, generator=torch.Generator().manual_seed(1))
    x = ref + 0.01
    x[0, 0, 2, 3] = bad
    assert math.isnan(psnr(x, ref))
    # ... unless the mask leaves that pixel out.
    mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
    mask[0, 0, 2, 3] = False
    assert psnr(x, ref, mask=mask) == pytest.approx(40.0, abs=1e-4)


def test_nothing_scored_is_nan():
    x = torch.rand(2, 2)
    assert math.isnan(psnr(x, x, mask=torch.zeros(2, 2, dtype=torch.bool)))


def test_bad_arguments_raise_naming_them():
    x = torch.rand(1, 3, 4, 4)
    with pytest.raises(ValueError, match=r"ref of shape \(1, 3, 5, 4\) does not broadcast to x's shape \(1, 3, 4, 4\)"):
        psnr(x, torch.rand(1, 3, 5, 4))
    with pytest.raises(ValueError, match=r"mask of shape \(1, 2, 4, 4\) does not broadcast"):
        psnr(x, x, mask=torch.ones(1, 2, 4, 4, dtype=torch.bool))
    with pytest.raises(TypeError, match="mask must be a bool tensor, got torch.float32"):
        psnr(x, x, mask=torch.ones(1, 1, 4, 4))
    with pytest.raises(TypeError, match="ref must be a torch.Tensor, got ndarray"):
        psnr(x, x.numpy())
    with pytest.raises(ValueError, match="peak must be a positive finite number, got 0"):
        psnr(x, x, 0)
