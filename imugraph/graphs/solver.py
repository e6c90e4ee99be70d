"""Levenberg–Marquardt and Gauss–Newton driven from Python (GTSAM_NOTES.md: gtsam's C++ optimizers copy
every Values into each Python callback, O(N²); this loop linearises once per iteration instead).

The problem is a C++ `NonlinearFactorGraph` (gyro factors, priors) plus optional vectorised blocks that
return their own linearisation (`imugraph.graphs.measurements.MeasurementBlock`). Each iteration:

    A δ = b  from graph.linearize(x) ∪ block.linear_factors(x) ∪ {√λ I per variable}      (LM damping)
    δ = gfg.optimize(ordering);  accept x ⊕ δ if the cost drops (λ ← λ/10) else λ ← 10λ
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, Protocol

import gtsam
import numpy as np

from imugraph import keys


class LinearBlock(Protocol):
    def cost(self, values: gtsam.Values) -> float: ...
    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph: ...


@dataclass
class SolverParams:
    method: str = "lm"              # "lm" or "gn"
    max_iterations: int = 50
    relative_tol: float = 1e-6
    absolute_tol: float = 1e-9
    lambda_initial: float = 1e-4
    lambda_max: float = 1e8
    verbose: bool = False
    elimination: str = "sequential"   # "sequential" (a Bayes net, variables one by one in the ordering) or
    #   "multifrontal" (a Bayes tree, gtsam's GaussianFactorGraph.optimize). Same Cholesky, so the steps agree to
    #   rounding (BROAD 01 final solve: max |Δδ| 3e-11 of 0.18); on the chain-ordered single-IMU graphs the
    #   sequential one is ≈ 25 % faster (BROAD 01 final solve, 9133 dims: 38–45 ms against 47–57 ms at load ≈ 8)


@dataclass
class SolveInfo:
    iterations: int = 0
    converged: bool = False
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    history: list = field(default_factory=list)


_DAMPING_CACHE: dict = {}     # (λ, key_dims) → graph: LM restarts from the same λ in every ML round


def _damping(key_dims: list[tuple[int, int]], lam: float) -> gtsam.GaussianFactorGraph:
    """√λ I on every variable: the Levenberg–Marquardt damping as unary factors (reused for a repeated
    λ and variable set; GTSAM's elimination reads its input factors without changing them). Keyed by the
    variable set too: the gyro-map rounds (β_k, e keys) and the final solve (without them) alternate, and a
    cache keyed by λ alone rebuilt the damping of every final-solve iteration (BROAD 04: 0.16 s CPU)."""
    key_dims = tuple(key_dims)
    cache_key = (lam, key_dims)
    hit = _DAMPING_CACHE.get(cache_key)
    if hit is not None:
        return hit
    damp = gtsam.GaussianFactorGraph()
    s = float(np.sqrt(lam))
    blocks = {d: (s * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)) for d in {d for _, d in key_dims}}
    for key, dim in key_dims:
        A, b, model = blocks[dim]
        damp.push_back(gtsam.JacobianFactor(key, A, b, model))
    if len(_DAMPING_CACHE) > 48:
        _DAMPING_CACHE.clear()
    _DAMPING_CACHE[cache_key] = damp
    return damp


class _StateCache:
    """Numpy arrays extracted from the Values the solver is evaluating (rotations, velocities), computed
    once per Values and shared by the blocks. Active only inside `optimize`, whose Values are never
    modified after creation (each step makes a new one by retract), so an identity check is sufficient."""

    def __init__(self):
        self.depth = 0
        self.values = None
        self.items: dict = {}

    def get(self, values: gtsam.Values, tag, compute: Callable[[gtsam.Values], object]):
        if self.depth == 0:
            return compute(values)
        if self.values is not values:
            self.values, self.items = values, {}
        if tag not in self.items:
            self.items[tag] = compute(values)
        return self.items[tag]

    def reset(self):
        self.values, self.items = None, {}


STATE_CACHE = _StateCache()


def cached_state(values: gtsam.Values, tag, compute: Callable[[gtsam.Values], object]):
    """compute(values), memoised per Values while `optimize` runs (callers must not modify the result)."""
    return STATE_CACHE.get(values, tag, compute)


def keyframe_rotations(values: gtsam.Values, K: int) -> np.ndarray:
    """(K, 3, 3) keyframe orientations nRk = R(0..K−1) from values (once per Values inside `optimize`)."""
    return cached_state(values, ("rot", K), lambda v: _rotations(v, K))


def keyframe_vectors(values: gtsam.Values, key_of: Callable[[int], int], K: int) -> np.ndarray:
    """(K, d) vector values key_of(0..K−1), e.g. keyframe velocities (once per Values inside `optimize`)."""
    return cached_state(values, ("vec", key_of, K), lambda v: _vectors(v, key_of, K))


def _vectors(values: gtsam.Values, key_of: Callable[[int], int], K: int) -> np.ndarray:
    """(K, d) values of key_of(0..K−1). When those keys are the symbols (c, 0..K−1), two C++ calls
    (Values.extract of exactly those keys, which raises on a missing one as atVector does, then
    gtsam.utilities.extractVectors, rows in key order = index order) replace K atVector calls (≈ 3×
    faster at K = 1000); otherwise key by key."""
    wanted = state_keys(key_of, K)
    if K > 0:
        c = chr(gtsam.Symbol(wanted[0]).chr())
        if wanted == _symbol_range(c, K):
            rows = gtsam.utilities.extractVectors(values.extract(list(wanted)), c)
            return np.array(rows, float).reshape(K, -1)
    return np.array([values.atVector(key) for key in wanted]).reshape(K, -1)


@lru_cache(maxsize=16)
def _symbol_range(c: str, K: int) -> tuple:
    """The keys gtsam.symbol(c, 0..K−1)."""
    return tuple(gtsam.symbol(c, k) for k in range(K))


def _rotations(values: gtsam.Values, K: int) -> np.ndarray:
    return np.array([values.atRot3(key).matrix() for key in state_keys(keys.rot, K)]).reshape(K, 3, 3)


@lru_cache(maxsize=16)
def state_keys(key_of: Callable[[int], int], K: int) -> tuple:
    """The keys key_of(0..K−1) as a tuple (memoised: building gtsam symbols costs ~1 µs each)."""
    return tuple(key_of(k) for k in range(K))


def total_cost(graph: gtsam.NonlinearFactorGraph, blocks: list, values: gtsam.Values) -> float:
    return float(graph.error(values)) + sum(b.cost(values) for b in blocks)


def optimize(graph: gtsam.NonlinearFactorGraph, blocks: list, values: gtsam.Values,
             ordering: gtsam.Ordering, params: SolverParams | None = None,
             on_iteration: Callable[[int, float], None] | None = None) -> tuple[gtsam.Values, SolveInfo]:
    """Minimise graph.error + Σ block.cost over `values` (a copy is returned).

    Args:
        graph: C++ factors; blocks: vectorised blocks (may be empty); values: initial estimate;
        ordering: elimination ordering (chain order with global variables last suits these graphs).
    Returns:
        (optimised values, SolveInfo).
    """
    STATE_CACHE.depth += 1
    try:
        return _optimize(graph, blocks, values, ordering, params or SolverParams(), on_iteration)
    finally:
        STATE_CACHE.depth -= 1
        STATE_CACHE.reset()


def _optimize(graph, blocks, values, ordering, p: SolverParams, on_iteration):
    """The LM / GN loop of `optimize` (see there)."""
    x = gtsam.Values(values)
    cost = total_cost(graph, blocks, x)
    info = SolveInfo(cost_initial=cost, history=[cost])
    lam = p.lambda_initial if p.method == "lm" else 0.0
    key_dims = tuple(x.dims().items())      # (key, dim) in key order, as x.keys()
    for it in range(1, p.max_iterations + 1):
        gfg = graph.linearize(x)
        for b in blocks:
            gfg.push_back(b.linearize(x))
        accepted = False
        while True:
            sys_ = gfg
            if lam > 0:
                sys_ = gtsam.GaussianFactorGraph()
                sys_.push_back(gfg)
                sys_.push_back(_damping(key_dims, lam))
            try:
                delta = _solve(sys_, ordering, p.elimination)
                x_new = x.retract(delta)
                new_cost = total_cost(graph, blocks, x_new)
            except RuntimeError:          # indeterminate linear system: damp harder (LM) or give up (GN)
                if p.method == "gn":
                    raise
                new_cost = float("inf")
                lam = max(lam, 1e-6)
            if new_cost <= cost or (p.method == "gn" and np.isfinite(new_cost)):
                accepted = True
                break
            lam *= 10.0
            if lam > p.lambda_max:
                break
        info.iterations = it
        if not accepted:
            info.converged = True      # no descent possible: at a minimum within numerical precision
            break
        decrease = cost - new_cost
        x, cost = x_new, new_cost
        info.history.append(cost)
        if on_iteration:
            on_iteration(it, cost)
        if p.method == "lm":
            lam = max(lam / 10.0, 1e-12)
        if decrease <= p.relative_tol * max(cost, 1e-300) or decrease <= p.absolute_tol:
            info.converged = True
            break
    info.cost_final = cost
    return x, info


def _solve(gfg: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, elimination: str) -> gtsam.VectorValues:
    """δ minimising ‖A δ − b‖² of a linear graph, eliminated in `ordering` (SolverParams.elimination)."""
    if elimination == "sequential":
        return gfg.eliminateSequential(ordering).optimize()
    if elimination == "multifrontal":
        return gfg.optimize(ordering)
    raise ValueError(f"SolverParams.elimination: found {elimination!r}, expected 'sequential' or 'multifrontal'")


def chain_ordering(rot_keys: list[int], global_keys: list[int]) -> gtsam.Ordering:
    """Keyframes in time order, then the global variables: fill-in stays O(K) for chain graphs."""
    return gtsam.Ordering(list(rot_keys) + list(global_keys))
