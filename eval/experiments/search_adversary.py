"""A search adversary: the cross-entropy method over the adversary's parameters and start
state, minimising the smallest TRUE clearance a scenario reaches.

A scenario is a vector theta of DIMENSIONS numbers: the start (a direction from the eye
centre, three numbers normalised, and a depth inside the wall, START_DEPTH_MM through a
logistic), then SEGMENTS segments of the command (`ParametricCommand`: a direction in
the frame of the tip's outward normal and two tangents at the segment's start, a speed
up to the filter's tip speed limit, a roll rate up to 3 rad/s, a duration of 0.05-0.2 s:
the random adversary's ranges). The cross-entropy method (Rubinstein) keeps a Gaussian
over theta: each generation draws `population` scenarios, runs them in the closed loop
(eval.experiments.boundary.start_at, ClosedLoop.run), and refits the Gaussian to the
`elite` fraction with the smallest clearance (smoothed, with a floor on the spread). A
scenario whose start is not allowed or not reachable scores +inf. The cross-entropy
method converges to one basin within a few dozen generations, and a 10x budget is
hundreds of generations: once a run has not improved its own best for `patience`
generations, the search restarts from the broad initial Gaussian (a restart strategy as
in IPOP-CMA-ES, Auger & Hansen 2005), each restart with a larger population, keeping the
worst scenario found over all runs. The search stops at its budget of simulations; the
worst scenario is returned with its theta, which `run_theta` replays. Units: mm, s, rad.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from eval.experiments.boundary import SCENARIO_S, START_DEPTH_MM, start_at, stops_by_reason

SEGMENTS = 5
PER_SEGMENT = 6  # direction (3), speed, roll, duration
DIMENSIONS = 4 + SEGMENTS * PER_SEGMENT
MAX_ROLL_RATE = 3.0  # rad/s, the random adversary's


def _logistic(x: float) -> float:
    return 1.0 / (1.0 + np.exp(-x))


class ParametricCommand:
    """The command source of theta's segments (module docstring); `p_WE_center` the eye
    centre (W, mm), `max_speed_mm_s` the speed of a logistic 1."""

    def __init__(self, theta, p_WE_center, max_speed_mm_s: float):
        self.theta = np.asarray(theta, dtype=float)
        self.center, self.max_speed = np.asarray(p_WE_center, dtype=float), float(max_speed_mm_s)
        self._k, self._until, self._v, self._roll = -1, -np.inf, np.zeros(3), 0.0

    def __call__(self, t_s: float, p_WT, q):
        if t_s >= self._until:
            self._k = min(self._k + 1, SEGMENTS - 1)
            s = self.theta[4 + PER_SEGMENT * self._k: 4 + PER_SEGMENT * (self._k + 1)]
            out = np.asarray(p_WT, dtype=float) - self.center
            out /= max(np.linalg.norm(out), 1e-9)
            t1 = np.cross(out, [0.0, 0.0, 1.0] if abs(out[2]) < 0.9 else [1.0, 0.0, 0.0])
            t1 /= np.linalg.norm(t1)
            u = s[0] * out + s[1] * t1 + s[2] * np.cross(out, t1)
            u /= max(np.linalg.norm(u), 1e-9)
            self._v = _logistic(s[3]) * self.max_speed * u
            self._roll = MAX_ROLL_RATE * np.tanh(s[4])
            self._until = t_s + 0.05 + 0.15 * _logistic(s[5])
        return self._v.copy(), self._roll


def start_of(theta) -> tuple[np.ndarray, float]:
    """(unit direction u_E, depth mm) of theta's start."""
    u = np.asarray(theta[:3], dtype=float)
    u = u / max(np.linalg.norm(u), 1e-9)
    lo, hi = START_DEPTH_MM
    return u, lo + (hi - lo) * _logistic(theta[3])


def run_theta(loop, model, coverage, theta, duration_s: float = SCENARIO_S, sensor_seed=None):
    """The LoopRun of scenario theta against copies of `model` and `coverage` (the sensor's
    draws from `sensor_seed`: the same run again), or None when its start is not allowed
    or not reachable."""
    u_E, depth = start_of(theta)
    q0 = start_at(loop, model.shape, u_E, depth)
    if q0 is None:
        return None
    command = ParametricCommand(theta, loop.scenario.eye_pose.p_WE, loop.config.filter.max_tip_speed_mm_s)
    return loop.run(command, q0, duration_s, model=copy.deepcopy(model), coverage=copy.deepcopy(coverage),
                    sensor_seed=sensor_seed)


@dataclass
class SearchResult:
    """The search's worst scenario: its clearance (mm), theta and sensor seed, and every
    evaluation's clearance."""

    worst_clearance_mm: float
    worst_theta: np.ndarray
    worst_sensor_seed: list = field(default_factory=list)
    clearances: list = field(default_factory=list)
    failsafe_stops: int = 0
    stops_by_reason: dict = field(default_factory=dict)
    restarts: int = 0

    def add(self, clearances: list, failsafe_stops: int, stops_by_reason: dict, restarts: int = 0) -> None:
        """Count in evaluations (their clearances, stops and stops by reason) and restarts."""
        self.clearances += clearances
        self.failsafe_stops += failsafe_stops
        self.restarts += restarts
        for key, count in stops_by_reason.items():
            self.stops_by_reason[key] = self.stops_by_reason.get(key, 0) + count


def minimise(objective, mean0, budget: int, seed: int, population: int = 20, elite: float = 0.2,
             smoothing: float = 0.7, min_sd: float = 0.05, patience: int = 15, tol: float = 1e-3,
             progress=None) -> tuple:
    """The cross-entropy method with restarts (module docstring) on `objective(theta,
    index) -> score` (+inf: infeasible), `budget` evaluations from N(mean0, I), seeded: a
    run restarts after `patience` generations without improving its best by more than
    `tol` (the score's units: 1 um of clearance), with twice the population of the run
    before. Returns (best score, its theta, its index, restarts)."""
    rng = np.random.default_rng(seed)
    mean0 = np.asarray(mean0, dtype=float)
    best = (np.inf, mean0.copy(), -1)
    done, size, restarts = 0, population, 0
    while done < budget:
        mean, sd = mean0.copy(), np.ones(len(mean0))
        run_best, stale = np.inf, 0
        while done < budget and stale < patience:
            n = min(size, budget - done)
            thetas = mean + sd * rng.standard_normal((n, len(mean0)))
            scores = np.full(n, np.inf)
            for i, theta in enumerate(thetas):
                scores[i] = objective(theta, done)
                if scores[i] < best[0]:
                    best = (float(scores[i]), theta.copy(), done)
                done += 1
                if progress is not None:
                    progress(done, budget)
            stale = 0 if scores.min() < run_best - tol else stale + 1
            run_best = min(run_best, float(scores.min()))
            finite = np.flatnonzero(np.isfinite(scores))
            if len(finite) >= 2:
                top = finite[np.argsort(scores[finite])][:max(2, int(round(elite * n)))]
                mean = smoothing * thetas[top].mean(axis=0) + (1 - smoothing) * mean
                sd = np.maximum(smoothing * thetas[top].std(axis=0) + (1 - smoothing) * sd, min_sd)
        if done < budget:
            restarts += 1
            size *= 2
    return (*best, restarts)


ISLAND_BUDGET = 1000  # simulations per independent search at least (the budget split into islands)
MAX_ISLANDS = 16


def islands(budget: int) -> list[int]:
    """The budget split into independent searches of ISLAND_BUDGET or more (at most
    MAX_ISLANDS): the split depends on the budget alone, not on who runs them."""
    k = max(1, min(MAX_ISLANDS, budget // ISLAND_BUDGET))
    return [budget // k + (1 if i < budget % k else 0) for i in range(k)]


@dataclass(frozen=True)
class _Island:
    """One independent search (a campaign task, eval.experiments.campaign): island i runs
    minimise with seed [seed, i] and its budget; its scenario k the sensor seed [seed, i, k]."""

    model: object
    coverage: object
    budgets: tuple
    seed: int
    duration_s: float
    options: tuple

    def __call__(self, loop, i: int) -> SearchResult:
        found = SearchResult(np.inf, np.zeros(DIMENSIONS))

        def objective(theta, k: int) -> float:
            run = run_theta(loop, self.model, self.coverage, theta, self.duration_s, [self.seed, i, k])
            if run is None or not len(run.t):
                return np.inf
            score = float(np.min(run.true_clearance_mm))
            found.add([score], run.failsafe_stops, stops_by_reason([run]))
            return score

        mean0 = np.zeros(DIMENSIONS)
        mean0[2] = -1.0  # start posterior of the trocar plane
        seed = int(np.random.SeedSequence([self.seed, i]).generate_state(1)[0])
        score, theta, k, found.restarts = minimise(objective, mean0, self.budgets[i], seed, **dict(self.options))
        if k >= 0:
            found.worst_clearance_mm, found.worst_theta, found.worst_sensor_seed = score, theta, [self.seed, i, k]
        return found


def cross_entropy_search(loop, model, coverage, budget: int, seed: int, duration_s: float = SCENARIO_S,
                         workers=None, progress=None, **options) -> SearchResult:
    """The search (module docstring) with `budget` simulations, seeded, as independent
    islands (`islands`) on `workers` (eval.experiments.campaign.Workers; None: this
    process); `options` those of minimise; `progress(simulations done, budget)` as islands
    finish. The worst
    scenario over the islands, every clearance, the stops and restarts of all."""
    from eval.experiments.campaign import Workers, run_tasks

    budgets = tuple(islands(budget))
    task = _Island(model, coverage, budgets, int(seed), float(duration_s), tuple(sorted(options.items())))
    found = SearchResult(np.inf, np.zeros(DIMENSIONS))
    done = None if progress is None else (lambda k, n: progress(sum(budgets[:k]), budget))
    for part in run_tasks(loop, task, range(len(budgets)), workers or Workers(), done):
        found.add(part.clearances, part.failsafe_stops, part.stops_by_reason, part.restarts)
        if part.worst_clearance_mm < found.worst_clearance_mm:
            found.worst_clearance_mm, found.worst_theta = part.worst_clearance_mm, part.worst_theta
            found.worst_sensor_seed = part.worst_sensor_seed
    return found
