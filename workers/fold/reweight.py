"""One walk, several albedos: the tallies of a shared walk's other albedos, by reweighting.

**Why it is exact.**  With weights and Russian roulette (implicit capture) the walk's geometry --
free paths, Fresnel decisions at the surface, scattering directions -- is drawn from
distributions that do not involve the albedo a; only the weight does: at each collision
w <- a w, then roulette below w_min (survive with probability s, w <- w / s).  Walk at a_w.  A
path that leaves after n scatterings carries

    W(a_w) = w_0 a_w^n prod_k R_k,

R_k the roulette factors (1/s on survival; the path ends on a kill), and its exit is tallied with
W.  At another albedo a the same walk with weight W(a_w) (a / a_w)^n = w_0 a^n prod_k R_k is
an unbiased estimate of the exit flux at a: given the path's geometry and its history up to a
roulette decision, E[R_k] = s (1/s) + (1 - s) 0 = 1, whatever threshold triggered it (the
decision is made on the walked weight, a function of the history: a stopping rule, not a bias),
so the expectation over the roulette decisions is w_0 a^n, which is the direct walk's expected
exit weight for that geometry (its own roulette, triggered at other moments, has mean 1 too).
Summed over geometries: E[exit tally at a] is the same as the direct walk's, for every
a <= a_w (a > a_w also holds in expectation, but weights then grow without roulette's
control: not allowed).

- **Path cap**: a path reaching max_scatter scatterings is truncated whatever the albedo (the
  cap counts scatterings, a geometric quantity), so the member's truncated weight is
  W(a_w) (a / a_w)^n_cap, the same quantity a direct walk truncates.  At a_w = 1 no roulette
  ever fires (weights never fall), members' weights a^n w_0 fall alone: exact.
- **Hybrid first vertex**: its connections carry w_0 a (the albedo at the first scattering,
  before any roulette): a member's are (a / a_w)^1 times the leader's; its multiple-scattering
  part is an exit after n >= 2 scatterings: (a / a_w)^n.
- **Absorbed power** is not a function of the exit: the member's per-photon estimate is the
  balance w_0 - (exit + truncated weight at a), unbiased for absorbed power because the walk
  conserves power in expectation (roulette has mean 1); it differs from a direct walk's
  deposit-per-collision estimate only in variance.
- **Albedos used**: the walk multiplies by the float32 albedo; the ratio is that of the float32
  albedos of member and leader, which is what the member's own direct walk would use.

**Variance.**  For a <= a_w the member's weight w_0 a^n prod R_k is its direct walk's weight
with fewer roulette factors (roulette fires on the larger walked weight, later), so the noise
roulette adds is smaller; a path the direct walk would have ended by roulette is followed to its
end with a small weight instead.  Not a theorem for every bin, but measured: the members' Rd
errors per photon are no larger than their direct walks' (tests/workers/test_shared_walks.py),
and far nodes of low albedos walked at a_w ~ 1 need more photons than walked near their own
albedo (BENCHMARKS.md).  The cost is CPU: paths are as long as at a_w.  See :mod:`schema.groups`.

**Correlation.**  All members of a group are estimated from the same photons, so their rows are
positively correlated (nearly 1 for neighbouring albedos); rows of different groups are
independent.  Independent walks per albedo: ``"walks": "independent"``.
"""

from __future__ import annotations

import numpy as np

from .tally import PhotonAccumulator

__all__ = ["member_factors", "MemberTallies", "MEMBER_PREFIX", "member_prefix"]

MEMBER_PREFIX = "member"


def member_prefix(j: int) -> str:
    """Name prefix of member j's quantities in a shared walk's shard tally."""
    return f"{MEMBER_PREFIX}{j}:"


def member_factors(ratios: np.ndarray, n: np.ndarray) -> np.ndarray:
    """f[j, p] = ratios[j] ** n[p] (float64): member j's weight factor for a photon that
    scattered n[p] times (0 ** 0 = 1: a photon that never scattered keeps its weight).

    A block's photons share few distinct counts next to its size, so the powers are taken once
    per distinct count and gathered: the same np.power of the same operands, a fraction of the
    work (a power costs ~20 ns, a gather ~1 ns; a group has up to a hundred members)."""
    ratios = np.asarray(ratios, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    if n.ndim == 1 and n.size > 32:
        counts, at = np.unique(n, return_inverse=True)
        if 2 * counts.size <= n.size:
            return np.take(np.power(ratios[:, None], counts[None, :]), at, axis=1)
    return np.power(ratios[:, None], n[None, :])


class MemberTallies:
    """The member albedos' accumulators of a shared walk (one :class:`PhotonAccumulator` each).

    albedos: the members' albedos (float32 values used), leader: the walked albedo (float32),
    w0: float64 [n_cfg] weight entering the medium (1 - R_spec) per configuration.
    """

    def __init__(self, albedos, leader: float, w0: np.ndarray, estimators, n_cfg: int, hist_shape):
        leader32 = float(np.float32(leader))
        self.ratios = np.array([float(np.float32(a)) / leader32 if leader32 > 0 else 0.0 for a in albedos], dtype=np.float64)
        if np.any(self.ratios > 1.0):
            raise ValueError(f"member albedos {list(albedos)} must not exceed the walked albedo {leader}")
        self.w0 = np.asarray(w0, dtype=np.float64)
        self.accs = [PhotonAccumulator(list(estimators), n_cfg, hist_shape) for _ in albedos]

    def __len__(self) -> int:
        return len(self.accs)

    def _offsets(self, flat: np.ndarray, size: int) -> np.ndarray:
        """Indices [members * n] of one bincount over all members: member j's entries at j * size + flat."""
        return (np.arange(len(self.accs))[:, None] * size + flat[None, :]).ravel()

    def _sums(self, at: np.ndarray, w: np.ndarray | None, size: int) -> np.ndarray:
        """[members, size]: one bincount over all members at indices ``at`` (:meth:`_offsets`)
        with weights w [members, n]; w None counts the entries (integers, the same values as
        summing ones).  Member j's sums take its entries in their order, as its own bincount would."""
        b = np.bincount(at, weights=None if w is None else w.ravel(), minlength=len(self.accs) * size)
        return b.reshape(len(self.accs), size)

    def _bincounts(self, parts, size: int) -> np.ndarray:
        """[members, size]: per member the sum over ``parts`` (index [n], weights [members, n]) of
        the bincounts, one bincount over all members per part (member j's entries offset by j * size)."""
        total = None
        for flat, w in parts:
            b = self._sums(self._offsets(flat, size), w, size)
            total = b if total is None else total + b
        return total

    def _add(self, estimator: str, row: int, size: int, parts) -> None:
        """Add to row ``row`` of every member's linear accumulator the sum of bincounts of
        (flat index [n], weights [J, n]) parts: one bincount over all members per part (member
        j's entries offset by j * size), summed per member in the order of its entries."""
        for acc, t in zip(self.accs, self._bincounts(parts, size)):
            acc.linear[estimator][row] += t

    def add_exits(self, flat: np.ndarray, g: np.ndarray, s: np.ndarray, nscat: np.ndarray) -> None:
        """The exit tally's entries of one block, each member's weighted by ratio ** nscat."""
        f = member_factors(self.ratios, nscat)
        gm, sm = g[None, :] * f, s[None, :] * f
        size = self.accs[0].linear["exits"].shape[1]
        for row, w in enumerate((gm, gm * gm, sm, sm * sm, (gm != 0.0).astype(np.float64))):
            self._add("exits", row, size, [(flat, w)])

    def add_hybrid(self, flat2: np.ndarray, g: np.ndarray, s: np.ndarray, key: np.ndarray, nscat: np.ndarray) -> None:
        """The hybrid's entries of one block ([P, E]: E - 1 first-vertex samples, then the
        multiple-scattering exit) with their square keys [8, P, E] (workers.walk.hybrid.photon_entries:
        the values of the 8 key sets are g, s, g, g, g, s, g, g).

        Member j scales the first-vertex entries by r_j = a_j / a_w and the exit by r_j^n.  Its
        per-photon squares (sum over a photon's entries with one key)^2 are then
        r^2 Q_ss + 2 r^(n+1) Q_se + r^(2n) Q_ee, with Q the squares and cross terms of the
        leader's entries among first-vertex samples (ss), between them and the exit (se) and of
        the exit (ee): formed once per block, combined per member.
        """
        value = np.stack([g, s, g, g, g, s, g, g])  # [8, P, E]
        e = value.shape[-1]
        single, ex = value[..., :-1], value[..., -1]
        same_ex = key[..., :-1] == key[..., -1:]  # a first-vertex entry sharing its key with the exit
        cross_ss = np.zeros_like(single)
        for j in range(e - 2):
            same = key[..., j + 1 : -1] == key[..., j : j + 1]
            cross_ss[..., j] = np.sum(np.where(same, single[..., j + 1 :], 0.0), axis=-1)
        q_ss = (single * (single + 2.0 * cross_ss)).reshape(-1)
        q_se = (np.sum(np.where(same_ex, single, 0.0), axis=-1) * ex).reshape(-1)  # sum_j x_j x_exit over shared keys
        q_ee = (ex * ex).reshape(-1)
        r = self.ratios[:, None]
        f = member_factors(self.ratios, nscat)  # [J, P]
        flat_single, flat_ex = flat2[:, :-1].reshape(-1), flat2[:, -1]
        g_single, s_single = g[:, :-1].reshape(-1), s[:, :-1].reshape(-1)
        ge, se = g[None, :, -1] * f, s[None, :, -1] * f
        size = self.accs[0].linear["hybrid"].shape[1]
        # Every member scales the first-vertex entries by the same r_j: their sums per bin (and
        # their squares per key) are the leader's, times r_j (r_j^2), formed once per block;
        # only the exit's factor r_j^n differs per photon.  A member's events are the leader's
        # entries != 0 where r_j > 0.
        live = (self.ratios > 0.0).astype(np.float64)[:, None]
        single = [np.bincount(flat_single, weights=w, minlength=size) for w in (g_single, s_single, (g_single != 0.0).astype(np.float64))]
        at_ex = self._offsets(flat_ex, size)
        exits = [self._sums(at_ex, ge, size), self._sums(at_ex, se, size), self._sums(at_ex[(ge != 0.0).ravel()], None, size)]
        for row, lead, scale, ex_j in ((0, single[0], r, exits[0]), (2, single[1], r, exits[1]), (4, single[2], live, exits[2])):
            for acc, sc, t in zip(self.accs, scale[:, 0], ex_j):
                acc.linear["hybrid"][row] += sc * lead + t
        n_sq = int(self.accs[0].layout.square_offsets[-1])
        key_s, key_e = key[..., :-1].reshape(-1), key[..., -1].reshape(-1)
        sq_single = np.bincount(key_s, weights=q_ss, minlength=n_sq)
        # Member j's exit squares: q_se 2 r_j f + q_ee f^2 for every (key set, photon), f its factor
        # r_j^n of the photon; one member at a time keeps the [8, P] temporaries in cache.
        q_se8, q_ee8 = q_se.reshape(-1, len(nscat)), q_ee.reshape(-1, len(nscat))
        two_rf, ff = (2.0 * r) * f, f * f
        w_se, w_ee = np.empty_like(q_se8), np.empty_like(q_ee8)
        for j, (acc, r2) in enumerate(zip(self.accs, r[:, 0] * r[:, 0])):
            np.multiply(q_se8, two_rf[j], out=w_se)
            np.add(w_se, np.multiply(q_ee8, ff[j], out=w_ee), out=w_se)
            t = np.bincount(key_e, weights=w_se.ravel(), minlength=n_sq)
            sq = r2 * sq_single + t
            if "hybrid" in acc.squares:
                acc.squares["hybrid"] += sq
            else:
                acc.squares["hybrid"] = sq

    def add_walk(self, cfg: np.ndarray, status_exit: np.ndarray, status_trunc: np.ndarray, w: np.ndarray, nscat: np.ndarray) -> None:
        """Walk totals of finished photons: truncated weight w r^n of truncated photons, and the
        absorbed power as the balance w_0 - r^n w (exited or truncated) (module docstring).
        Sums are the bincounts over all members; the truncated weight, zero for nearly every
        block, is skipped where no photon was truncated (adding zeros changes no sum)."""
        f = member_factors(self.ratios, nscat)  # [J, P]
        w = np.asarray(w, dtype=np.float64)
        left = np.where(status_exit | status_trunc, w, 0.0)
        n_cfg = self.accs[0].n_cfg
        at = self._offsets(cfg, n_cfg)
        totals = [("absorbed", self.w0[cfg][None, :] - left[None, :] * f)]
        if np.any(status_trunc):
            totals.append(("truncated", np.where(status_trunc, w, 0.0)[None, :] * f))
        for q, v in totals:  # one bincount over all members per row
            for row, t in enumerate((self._sums(at, v, n_cfg), self._sums(at, v * v, n_cfg), self._sums(at[(v != 0.0).ravel()], None, n_cfg))):
                for acc, x in zip(self.accs, t):
                    acc.walk[q][row] += x

    def finish(self, n_photons: int) -> list[tuple[dict, dict]]:
        """(stats, counts) of every member, as :meth:`PhotonAccumulator.finish`."""
        return [acc.finish(n_photons) for acc in self.accs]
