"""CMA-ES (drivesim.cmaes): one update against the tutorial's equations written out element by
element, convergence, determinism, the saved state, bad input."""

import doctest
import math

import numpy as np
import pytest

from drivesim import cmaes
from drivesim.cmaes import CMAES


def tutorial_update(mean, sigma, cov, p_sigma, p_c, generation, x, costs):
    """One generation of Hansen's tutorial (2016), Table 1 and equations (38)-(47) with positive
    weights, in plain loops over the elements: the oracle of ``CMAES.tell``."""
    n, lam = len(mean), len(costs)
    mu = lam // 2
    w = [math.log((lam + 1) / 2) - math.log(i + 1) for i in range(mu)]
    w = [v / sum(w) for v in w]
    mu_eff = 1 / sum(v * v for v in w)
    c_s = (mu_eff + 2) / (n + mu_eff + 5)
    d_s = 1 + 2 * max(0, math.sqrt((mu_eff - 1) / (n + 1)) - 1) + c_s
    c_c = (4 + mu_eff / n) / (n + 4 + 2 * mu_eff / n)
    c_1 = 2 / ((n + 1.3) ** 2 + mu_eff)
    c_mu = min(1 - c_1, 2 * (mu_eff - 2 + 1 / mu_eff) / ((n + 2) ** 2 + mu_eff))
    chi = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    order = sorted(range(lam), key=lambda k: costs[k])[:mu]
    y = [[(x[k][j] - mean[j]) / sigma for j in range(n)] for k in order]
    y_w = [sum(w[i] * y[i][j] for i in range(mu)) for j in range(n)]
    new_mean = [mean[j] + sigma * y_w[j] for j in range(n)]
    values, vectors = np.linalg.eigh(np.array(cov))
    inv_sqrt = [[sum(vectors[a][k] * vectors[b][k] / math.sqrt(values[k]) for k in range(n)) for b in range(n)]
                for a in range(n)]
    whitened = [sum(inv_sqrt[a][b] * y_w[b] for b in range(n)) for a in range(n)]
    p_s = [(1 - c_s) * p_sigma[j] + math.sqrt(c_s * (2 - c_s) * mu_eff) * whitened[j] for j in range(n)]
    norm = math.sqrt(sum(v * v for v in p_s))
    h_s = 1.0 if norm / math.sqrt(1 - (1 - c_s) ** (2 * (generation + 1))) < (1.4 + 2 / (n + 1)) * chi else 0.0
    pc = [(1 - c_c) * p_c[j] + h_s * math.sqrt(c_c * (2 - c_c) * mu_eff) * y_w[j] for j in range(n)]
    delta = (1 - h_s) * c_c * (2 - c_c)
    new_cov = [[(1 + c_1 * delta - c_1 - c_mu) * cov[a][b] + c_1 * pc[a] * pc[b]
                + c_mu * sum(w[i] * y[i][a] * y[i][b] for i in range(mu)) for b in range(n)] for a in range(n)]
    new_sigma = sigma * math.exp((c_s / d_s) * (norm / chi - 1))
    return new_mean, new_sigma, new_cov, p_s, pc


def test_three_updates_are_the_tutorials():
    es = CMAES([0.5, -1.0, 2.0], sigma=0.3, population=7)
    for g in range(3):
        before = (es.mean.tolist(), es.sigma, es.cov.tolist(), es.p_sigma.tolist(), es.p_c.tolist(), es.generation)
        x = es.ask(np.random.default_rng(g))
        costs = ((x - [1, 2, 3]) ** 2 * [1, 10, 100]).sum(axis=1)
        expected = tutorial_update(*before, x.tolist(), costs.tolist())
        es.tell(x, costs)
        found = (es.mean, es.sigma, es.cov, es.p_sigma, es.p_c)
        for name, a, b in zip(("mean", "sigma", "cov", "p_sigma", "p_c"), found, expected):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12, err_msg=name)


def test_it_finds_the_minimum_of_a_rotated_ellipsoid():
    n = 8
    rotation, _ = np.linalg.qr(np.random.default_rng(1).standard_normal((n, n)))
    scales = 10 ** (2 * np.arange(n) / (n - 1))
    cost = lambda x: (((x @ rotation.T) * scales) ** 2).sum(axis=-1)  # noqa: E731
    es = CMAES(np.ones(n), 0.5)
    for g in range(1500):
        x = es.ask(np.random.default_rng([3, g]))
        es.tell(x, cost(x))
    assert cost(es.mean) < 1e-12


def test_the_same_draws_give_the_same_bytes_and_a_saved_state_goes_on_alike():
    def run(es, generations, first=0):
        for g in range(first, first + generations):
            x = es.ask(np.random.default_rng([5, g]))
            es.tell(x, np.abs(x - 0.3).sum(axis=1))
        return es

    whole = run(CMAES(np.zeros(5), 1.0, 6), 20)
    half = run(CMAES(np.zeros(5), 1.0, 6), 10)
    resumed = run(CMAES.from_state(dict(half.state())), 10, first=10)
    for key, value in whole.state().items():
        assert np.array_equal(value, resumed.state()[key]), key
    assert whole.generation == 20


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="mean"):
        CMAES([np.nan, 1.0], 1.0)
    with pytest.raises(ValueError, match="sigma"):
        CMAES([0.0], 0.0)
    with pytest.raises(ValueError, match="population"):
        CMAES([0.0], 1.0, population=3)
    es = CMAES(np.zeros(3), 1.0, 4)
    x = es.ask(np.random.default_rng(0))
    with pytest.raises(ValueError, match="candidates"):
        es.tell(x[:3], np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        es.tell(x, [0.0, np.inf, 1.0, 2.0])
    with pytest.raises(ValueError, match="disagree"):
        CMAES.from_state({**es.state(), "cov": np.eye(2)})


def test_the_module_docstring_runs():
    assert doctest.testmod(cmaes).failed == 0
