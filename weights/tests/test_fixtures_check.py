"""`fixtures.py --check` on another CPU: rounding that differs is not a difference, a change is."""

import torch

from drivesim_reference.fixtures import difference

WEIGHT = "f64.grad.encoder.conv1.weight"
BIAS = "f64.grad.encoder.conv1.bias"


def gradients(bias):
    return {WEIGHT: torch.full((4, 3, 5, 5), 0.01, dtype=torch.float64), BIAS: bias}


def test_a_float64_bias_gradient_before_batchnorm_is_rounding_s_zero_on_any_cpu():
    # Zero in exact arithmetic: the committed run's 1e-17 and another CPU's 3e-18 are both noise
    # (before, compared as any tensor: 0.7 of its scale apart, a failure on Intel AVX-512).
    committed = gradients(torch.tensor([1e-17, -4e-18, 2e-18, 0.0], dtype=torch.float64))
    fresh = gradients(torch.tensor([-3e-18, 5e-18, 0.0, 1e-18], dtype=torch.float64))
    assert difference(BIAS, committed[BIAS], fresh[BIAS], committed, fresh, 0.0) is None


def test_a_float64_bias_gradient_that_is_not_zero_is_named():
    committed = gradients(torch.zeros(4, dtype=torch.float64))
    fresh = gradients(torch.tensor([0.0, 1e-8, 0.0, 0.0], dtype=torch.float64))
    problem = difference(BIAS, committed[BIAS], fresh[BIAS], committed, fresh, 0.0)
    assert problem is not None and "not rounding's zero" in problem


def test_float32_results_within_another_cpu_s_rounding_pass_and_a_change_does_not():
    x = torch.linspace(-1, 1, 100, dtype=torch.float64)
    assert difference("generate.frames", x, x + 3e-6, {}, {}, 0.0) is None
    assert difference("generate.frames", x, x + 1e-4, {}, {}, 0.0) is not None
