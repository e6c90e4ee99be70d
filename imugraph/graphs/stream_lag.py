"""A fixed-lag smoother over gtsam.ISAM2 for the stream: incremental updates, marginalisation once per hold_s
(between updates, in deferred mode).

gtsam's IncrementalFixedLagSmoother does, per update: stamp the new keys, find the keys older than the lag,
update iSAM2 with those keys constrained to be eliminated first (all the others in one group: COLAMD), then
marginalise them (`ISAM2.marginalizeLeaves`). With the field perturbation (stream_field: a second chain
d_k − d_{k+1} beside the keyframes) that re-eliminated and re-linearised the whole window at every update
(measured on BROAD 01, 60 s, lag 2 s: iSAM2's update 3.3× the cost without d; every factor of the window
linearised at every update). Here:

- an ordinary update is iSAM2's own incremental one (its default order puts the new factors' keys last, at
  the root), with no constraint groups;
- once the oldest key is older than lag_s + hold_s, one update re-eliminates every key with those older
  than lag_s first, then the keyframes in time order, gravity and the bias segments last
  (order = [marginalised] [x_k, v_k, d_k oldest] … [newest] [g, b], the chain order of solver.chain_ordering),
  and the old keys are marginalised. `marginalizeLeaves` crashed the process (no exception) on keys that were
  not leaves, so this re-elimination is not optional; the Python wheel does not expose the Bayes tree to
  check. The window holds lag_s to lag_s + hold_s.

Deferred mode (`deferred=True`, what the stream uses): the periodic work leaves the keyframe updates. An update
then only adds its factors and solves (iSAM2 relinearisation off); `maintain`, which the stream calls once per
keyframe interval on a sample between keyframes, does the due marginalisation above or else iSAM2's
relinearisation step (`force_relinearize`: the same check an update makes before adding its factors, on the
previous update's delta — same results), keeping the last update's keys (newest keyframe, g, b) at the root.
Why (BROAD 34, first 150 s, iSAM2 result counters): the p99 of the updates came from (i) the marginalisation
update (whole window re-eliminated, ≈ +3 ms, 9 % of updates) and (ii) updates where a relinearised old
variable re-eliminated its path to the root, i.e. the window (14 % of updates re-eliminated > 60 of ≈ 96
variables, 3–6 ms; after moving relinearisation into `maintain` without the root constraint, the next update
re-eliminated the window again, COLAMD having put the newest keys deep). With both in `maintain`, no update
re-eliminates more than 52 variables (median 18).

Measured (simulation, 286 Hz, 30 s, lag 2 s, field on, CPU time): the smoother's calls 0.78 s
(IncrementalFixedLagSmoother: update + calculateEstimate) → 0.25 s, the whole stream 20.6× → 34.3× real time;
60 s: the same filtered error (0.245° vs 0.244°). tests/test_stream_lag.py checks exact marginalisation on a
linear Gaussian chain.
"""

from __future__ import annotations

import gtsam


class ChainLagSmoother:
    """Fixed-lag smoothing with ISAM2 (`params`), keys grouped by `group_of(key)` (int, small = eliminated
    first; None = a global key, eliminated last). A key is marginalised when its stamp is older than the lag
    (re-stamp the keys to keep).

    Interface as used by `StreamSmoother`: update(graph, values, stamps: dict key → time s), calculateEstimate().
    """

    def __init__(self, lag_s: float, params: gtsam.ISAM2Params, group_of, hold_s: float = 1.0, deferred: bool = False):
        self.lag_s, self.hold_s, self.deferred = float(lag_s), float(hold_s), bool(deferred)
        if deferred:          # relinearisation only in `maintain` (or an update with no maintain before it)
            params.enableRelinearization = False
        self.isam = gtsam.ISAM2(params)
        self.group_of = group_of
        self.stamps: dict = {}
        self.group: dict = {}            # key → group_of(key), cached (symbol parsing costs ~1 µs)
        self._due = False                # a marginalisation is due (see due)
        self._maintained = True          # `maintain` ran since the last update
        self._last_keys: list = []       # the keys stamped by the last update

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict,
               remove: tuple = (), force: bool = False) -> dict | None:
        """Add factors and new values; when a marginalisation is due (`due`), do it in this update.

        With `deferred` the caller runs `maintain` between updates: this update then only adds the factors and
        solves (no relinearisation, no marginalisation) unless no `maintain` ran since the last update, in
        which case it does that work itself. `remove`: iSAM2 indices of factors to remove (a temporary pin,
        stream_realign); `force`: relinearise in this update (iSAM2's threshold check). Returns None, or after a
        marginalisation the keyframe rotations (nRb 3×3 by keyframe index) of the marginalised pose keys as they
        left the window."""
        for k in stamps:
            if k not in self.stamps:
                self.group[k] = self.group_of(k)
        self.stamps.update(stamps)
        self._last_keys = list(stamps)
        missed = self.deferred and not self._maintained
        self._maintained = False
        self._check_due()
        if not self._due or (self.deferred and not missed):
            # iSAM2's own order for an incremental update: the new factors' keys last (at the root)
            self.isam.update(graph, values, list(remove), None, None, None, missed or force)
            return None
        return self._marginalize(graph, values, remove, force)

    def due(self) -> bool:
        """A marginalisation is due: the oldest stamp is more than lag_s + hold_s older than the newest."""
        return self._due

    def _check_due(self) -> None:
        stamps = self.stamps.values()
        self._due = bool(self.stamps) and min(stamps) < max(stamps) - self.lag_s - self.hold_s

    def maintain(self) -> dict | None:
        """Between two updates (no new factors; the stream calls it on a sample between keyframes, so that
        this work does not add to a keyframe update's latency): the due marginalisation (the window's
        re-elimination), else iSAM2's relinearisation step — the same relinearisation check an update makes
        before adding its factors (on the delta of the previous update), so the results are the same; a
        relinearised old variable re-eliminates its path to the root, i.e. most of the window. Returns None,
        or after a marginalisation as `update`."""
        self._maintained = True
        if self._due:
            return self._marginalize(gtsam.NonlinearFactorGraph(), gtsam.Values())
        # the keys of the last update (newest keyframe, gravity, bias segment) stay last, at the root, where the
        # next update adds its factors: unconstrained, COLAMD put them deep in the re-eliminated part and the
        # next update re-eliminated the window again (BROAD 34: 14 % of the updates, 3–6 ms each)
        last = gtsam.KeyGroupMap()
        for key in self._last_keys:
            last.insert2(key, 1)
        self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], last, None, None, self.deferred)
        return None

    def _marginalize(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, remove: tuple = (),
                     force: bool = False) -> dict:
        """One update that re-eliminates the whole window (keys older than lag_s first), then their
        marginalisation."""
        now = max(self.stamps.values())
        new = set(values.keys())
        old = {k for k, s in self.stamps.items() if s < now - self.lag_s}
        existing = _key_list(k for k in self.stamps if k not in new)
        # marginalizeLeaves needs leaves (it crashed, not raised, on a key that was not one): this update
        # re-eliminates the whole window with those keys first, then they are marginalised
        self.isam.update(graph, values, list(remove), self._groups(old), None, existing, self.deferred or force)
        left = _pose_rotations(self.isam, old)
        self.isam.marginalizeLeaves(_key_list(old))
        for k in old:
            del self.stamps[k]
            del self.group[k]
        self._check_due()
        return left

    def _groups(self, first: set) -> gtsam.KeyGroupMap:
        """Elimination groups of every key: `first` (0), the keyframes in time order, the global keys last.
        Every key is re-eliminated with them (ccolamd fails on group labels beyond the size of a subset)."""
        kept = sorted({g for k in self.stamps if k not in first and (g := self.group[k]) is not None})
        rank = {g: i + 1 for i, g in enumerate(kept)}
        groups = gtsam.KeyGroupMap()
        for key in self.stamps:
            g = self.group[key]
            groups.insert2(key, 0 if key in first else (len(rank) + 1 if g is None else rank[g]))
        return groups

    def calculateEstimate(self) -> gtsam.Values:
        return self.isam.calculateEstimate()


_INDEX_MASK, _X = (1 << 56) - 1, ord("x")      # gtsam.Symbol's key layout (chr << 56 | index)


def keyframe_group(key: int):
    """The stream's grouping: keyframe index of a pose (x), velocity (v), field perturbation (f) or bounded
    position (p, stream_position) key; None for gravity and the bias segments (in every clique of their span:
    eliminated last)."""
    return key & _INDEX_MASK if chr(key >> 56) in "xvfp" else None       # gtsam.Symbol: 8-bit chr, 56-bit index


def _key_list(keys) -> gtsam.KeyList:
    out = gtsam.KeyList()
    for k in keys:
        out.push_back(k)
    return out


def window_rotations(smoother: ChainLagSmoother) -> dict:
    """Keyframe index → nRb (3×3) of every pose key still in the window (latest estimate)."""
    return _pose_rotations(smoother.isam, smoother.stamps)


def _pose_rotations(isam: gtsam.ISAM2, keys) -> dict:
    """Keyframe index → nRb (3×3), iSAM2's latest estimate, of the pose keys (x) among `keys`."""
    out = {}
    for k in keys:
        if k >> 56 == _X:                                     # gtsam.Symbol(k).chr() == "x"
            out[k & _INDEX_MASK] = isam.calculateEstimatePose3(k).rotation().matrix()
    return out
