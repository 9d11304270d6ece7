"""CMA-ES (Hansen, "The CMA Evolution Strategy: A Tutorial", 2016): the covariance matrix
adaptation evolution strategy that World Models trained its controller with, here for the
dream's drivers (``drivesim.carracing.dreamt``). It minimises: ``tell`` takes costs.

The state is a handful of arrays (``state()``, ``CMAES.from_state``), saved with a run's
checkpoint, and the draws come from the generator the caller passes to ``ask``: a run seeded per
generation resumes to the same bytes.

>>> import numpy as np
>>> es = CMAES(np.full(4, 3.0), sigma=1.0, population=8)
>>> for generation in range(150):
...     x = es.ask(np.random.default_rng(generation))
...     es.tell(x, (x ** 2).sum(axis=1))
>>> bool(np.abs(es.mean).max() < 1e-4)
True
"""

from __future__ import annotations

import math

import numpy as np

from . import _checks


class CMAES:
    """Minimises a cost over vectors of ``len(mean)`` numbers, from ``mean`` with step size
    ``sigma`` (the standard deviation of the first draws) and ``population`` draws a generation
    (at least 4; Hansen's default ``4 + 3 ln n`` when None). The tutorial's default settings:
    the better half recombined with log-decreasing weights, cumulative step-size adaptation,
    rank-one and rank-mu updates of the covariance."""

    def __init__(self, mean, sigma: float, population: int | None = None):
        mean = _checks.floats("mean", mean).astype(np.float64).ravel()
        if len(mean) < 1 or not np.isfinite(mean).all():
            raise ValueError("mean: expected at least one finite number")
        n = len(mean)
        self.n = n
        self.sigma = _checks.number("sigma", sigma, 0.0, above=True)
        default = 4 + int(3 * math.log(n))
        self.population = _checks.integer("population", default if population is None else population, 4)
        mu = self.population // 2
        weights = math.log((self.population + 1) / 2) - np.log(np.arange(1, mu + 1))
        self.weights = weights / weights.sum()
        self.mu_eff = 1.0 / float((self.weights ** 2).sum())
        self.c_sigma = (self.mu_eff + 2) / (n + self.mu_eff + 5)
        self.d_sigma = 1 + 2 * max(0.0, math.sqrt((self.mu_eff - 1) / (n + 1)) - 1) + self.c_sigma
        self.c_c = (4 + self.mu_eff / n) / (n + 4 + 2 * self.mu_eff / n)
        self.c_1 = 2 / ((n + 1.3) ** 2 + self.mu_eff)
        self.c_mu = min(1 - self.c_1, 2 * (self.mu_eff - 2 + 1 / self.mu_eff) / ((n + 2) ** 2 + self.mu_eff))
        self.chi_n = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))  # E ||N(0, I)||
        self.mean = mean
        self.p_sigma, self.p_c = np.zeros(n), np.zeros(n)
        self.cov = np.eye(n)
        self.generation = 0
        self._decompose()

    def _decompose(self):
        """B and D of C = B D² Bᵀ (C kept symmetric), for the draws and C^-1/2."""
        self.cov = (self.cov + self.cov.T) / 2
        eigenvalues, self.basis = np.linalg.eigh(self.cov)
        self.scales = np.sqrt(np.maximum(eigenvalues, 1e-300))

    def ask(self, rng: np.random.Generator) -> np.ndarray:
        """A generation's draws ``(population, n)``: ``mean + sigma B D z``, z standard normal
        from ``rng``."""
        z = rng.standard_normal((self.population, self.n))
        return self.mean + self.sigma * (z * self.scales) @ self.basis.T

    def tell(self, candidates: np.ndarray, costs) -> None:
        """Updates the distribution from the generation ``candidates`` (``ask``'s) and their
        ``costs`` (lower is better; finite)."""
        candidates = np.asarray(candidates, np.float64)
        costs = _checks.floats("costs", costs).astype(np.float64)
        if candidates.shape != (self.population, self.n) or costs.shape != (self.population,):
            raise ValueError(f"expected {self.population} candidates of {self.n} and as many costs, "
                             f"got {candidates.shape} and {costs.shape}")
        if not np.isfinite(costs).all():
            raise ValueError("costs: expected finite numbers")
        best = np.argsort(costs, kind="stable")[: len(self.weights)]
        steps = (candidates[best] - self.mean) / self.sigma  # y_i: the selected draws' steps
        step = self.weights @ steps
        self.mean = self.mean + self.sigma * step
        # C^-1/2 y_w: the step as if the covariance were the identity.
        whitened = self.basis @ ((self.basis.T @ step) / self.scales)
        self.p_sigma = (1 - self.c_sigma) * self.p_sigma + math.sqrt(
            self.c_sigma * (2 - self.c_sigma) * self.mu_eff) * whitened
        self.generation += 1
        norm = float(np.linalg.norm(self.p_sigma))
        h_sigma = norm / math.sqrt(1 - (1 - self.c_sigma) ** (2 * self.generation)) < (1.4 + 2 / (self.n + 1)) * self.chi_n
        self.p_c = (1 - self.c_c) * self.p_c + h_sigma * math.sqrt(self.c_c * (2 - self.c_c) * self.mu_eff) * step
        lost = (1 - h_sigma) * self.c_c * (2 - self.c_c)  # the rank-one update's variance, when p_c stalls
        rank_mu = (steps.T * self.weights) @ steps
        self.cov = ((1 + self.c_1 * lost - self.c_1 - self.c_mu) * self.cov
                    + self.c_1 * np.outer(self.p_c, self.p_c) + self.c_mu * rank_mu)
        self.sigma *= math.exp((self.c_sigma / self.d_sigma) * (norm / self.chi_n - 1))
        self._decompose()

    def state(self) -> dict:
        """The arrays that make up the strategy's state (for a checkpoint)."""
        return {"mean": self.mean, "sigma": np.float64(self.sigma), "population": np.int64(self.population),
                "p_sigma": self.p_sigma, "p_c": self.p_c, "cov": self.cov, "generation": np.int64(self.generation)}

    @classmethod
    def from_state(cls, state) -> "CMAES":
        """The strategy ``state()`` saved (a dict or an ``np.load``'s file), to go on from."""
        es = cls(state["mean"], float(state["sigma"]), int(state["population"]))
        es.p_sigma, es.p_c = np.array(state["p_sigma"], np.float64), np.array(state["p_c"], np.float64)
        es.cov, es.generation = np.array(state["cov"], np.float64), int(state["generation"])
        if es.p_sigma.shape != (es.n,) or es.p_c.shape != (es.n,) or es.cov.shape != (es.n, es.n):
            raise ValueError("a CMA-ES state whose arrays disagree in size")
        es._decompose()
        return es
