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
        # Every member's accumulators are rows of one array, so a block adds to all members in one
        # operation (a group has up to a hundred members; a loop over them cost ~0.5 ms a block).
        self.linear = {e: self._rows("linear", e, a.shape) for e, a in self.accs[0].linear.items()}
        self.walk = {q: self._rows("walk", q, a.shape) for q, a in self.accs[0].walk.items()}
        self.squares: dict[str, np.ndarray] = {}  # estimator -> [members, n_sq] (once added), as above

    def _rows(self, attr: str, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """A zero array [members, *shape] whose row j becomes member j's ``getattr(acc, attr)[key]``."""
        stacked = np.zeros((len(self.accs), *shape))
        for acc, row in zip(self.accs, stacked):
            getattr(acc, attr)[key] = row
        return stacked

    def __len__(self) -> int:
        return len(self.accs)

    def _offsets(self, flat: np.ndarray, size: int) -> np.ndarray:
        """Indices [members * n] of one bincount over all members: member j's entries at j * size + flat."""
        return (np.arange(len(self.accs))[:, None] * size + flat[None, :]).ravel()

    def _sums(self, at: np.ndarray, w: np.ndarray, size: int) -> np.ndarray:
        """[members, size]: one bincount over all members at indices ``at`` (:meth:`_offsets`)
        with weights w [members, n].  Member j's sums take its entries in their order, as its own
        bincount would."""
        return np.bincount(at, weights=w.ravel(), minlength=len(self.accs) * size).reshape(len(self.accs), size)

    def add_exits(self, flat: np.ndarray, g: np.ndarray, s: np.ndarray, nscat: np.ndarray) -> None:
        """The exit tally's entries of one block, each member's weighted by ratio ** nscat."""
        f = member_factors(self.ratios, nscat)
        gm, sm = g[None, :] * f, s[None, :] * f
        size = self.accs[0].linear["exits"].shape[1]
        at = self._offsets(flat, size)
        for row, w in enumerate((gm, gm * gm, sm, sm * sm, (gm != 0.0).astype(np.float64))):
            self.linear["exits"][:, row] += self._sums(at, w, size)

    def add_hybrid(self, flat2: np.ndarray, g: np.ndarray, s: np.ndarray, key: np.ndarray, nscat: np.ndarray) -> None:
        """The hybrid's entries of one block ([P, E]: E - 1 first-vertex samples, then the
        multiple-scattering exit) with their square keys [8, P, E] (workers.fold.tally.entry_square_keys:
        the values of the 8 key sets are g, s, g, g, g, s, g, g).

        Member j scales the first-vertex entries by r_j = a_j / a_w and the exit by r_j^n.  Its
        per-photon squares (sum over a photon's entries with one key)^2 are then
        r^2 Q_ss + 2 r^(n+1) Q_se + r^(2n) Q_ee, with Q the squares and cross terms of the
        leader's entries among first-vertex samples (ss), between them and the exit (se) and of
        the exit (ee): formed once per block, combined per member.
        """
        if len(nscat) == 0:
            return
        # Entry-major: [E, P] and [8, E, P], each entry a contiguous row (the kernel's arrays are
        # entry-major: no copy), so that every operation below runs over a photon row (numpy on a
        # short last axis of E cost ~1 us a photon, five times the walk of a low albedo).
        fT, gT, sT = (np.ascontiguousarray(a.T) for a in (flat2, g, s))
        keyT = np.ascontiguousarray(np.moveaxis(key, 2, 1))
        e, n_p = gT.shape
        q_ss, q_se = np.empty((8, e - 1, n_p)), np.empty((8, n_p))
        for k, v in enumerate((gT, sT, gT, gT, gT, sT, gT, gT)):  # the values of the 8 key sets
            kk = keyT[k]
            for j in range(e - 1):  # x_j (x_j + 2 sum_{i > j} x_i [same key]): the photon's square at x_j's key, once per pair
                cross = 0.0
                for i in range(j + 1, e - 1):
                    cross = cross + np.where(kk[i] == kk[j], v[i], 0.0)
                q_ss[k, j] = v[j] * (v[j] + 2.0 * cross)
            shared = 0.0  # sum_j x_j x_exit over the first-vertex samples sharing the exit's key
            for j in range(e - 1):
                shared = shared + np.where(kk[j] == kk[e - 1], v[j], 0.0)
            q_se[k] = shared * v[e - 1]
        r = self.ratios[:, None]
        flat_single, flat_ex = fT[:-1].T.reshape(-1), fT[-1]  # first-vertex samples photon-major
        g_single, s_single = gT[:-1].T.reshape(-1), sT[:-1].T.reshape(-1)
        size = self.accs[0].linear["hybrid"].shape[1]
        n_sq = int(self.accs[0].layout.square_offsets[-1])
        key_s, key_e = keyT[:, :-1].transpose(0, 2, 1).reshape(-1), keyT[:, -1]  # key_e [8, P]: the exit's keys
        q_ss = q_ss.transpose(0, 2, 1).reshape(-1)  # as key_s: set, photon, sample
        # Every member scales the first-vertex entries by the same r_j: their sums per bin (and
        # their squares per key) are the leader's, times r_j (r_j^2), formed once per block;
        # only the exit's factor r_j^n differs per photon.  A member's events are the leader's
        # entries != 0 where r_j > 0.
        live = (self.ratios > 0.0).astype(np.float64)[:, None]
        single = [np.bincount(flat_single, weights=w, minlength=size) for w in (g_single, s_single, (g_single != 0.0).astype(np.float64))]
        sq_single = np.bincount(key_s, weights=q_ss, minlength=n_sq)
        # The exit's terms differ per member and photon (r_j^n): photons are grouped by where
        # they left (the exit bin and its eight square keys), and every member's sums are formed
        # per group in one pass over [members, photons] arrays in group order (_Groups).
        grp = _Groups(np.concatenate((flat_ex[None, :], key_e)), max(size, n_sq))
        o = grp.order
        f = member_factors(self.ratios, nscat[o])  # [J, P], photons in group order
        ge, se = gT[-1, o][None, :] * f, sT[-1, o][None, :] * f
        at = self._offsets(grp.labels[0], size)
        exits = [self._sums(at, grp.sums(w), size) for w in (ge, se, (ge != 0.0).astype(np.float64))]
        for row, lead, scale, ex_j in ((0, single[0], r, exits[0]), (2, single[1], r, exits[1]), (4, single[2], live, exits[2])):
            self.linear["hybrid"][:, row] += scale * lead[None, :] + ex_j
        exit_sq = self._exit_squares(grp, ge, se, f, q_se[:, o], n_sq)
        if "hybrid" not in self.squares:
            self.squares["hybrid"] = self._rows("squares", "hybrid", (n_sq,))
        self.squares["hybrid"] += (r * r) * sq_single[None, :] + exit_sq

    def _exit_squares(self, grp: "_Groups", ge: np.ndarray, se: np.ndarray, f: np.ndarray, q_se: np.ndarray, n_sq: int) -> np.ndarray:
        """[members, n_sq]: member j's exit terms of the per-photon squares, summed per key:
        f_jp^2 ex[k, p]^2 + 2 r_j f_jp q_se[k, p] over key sets k and photons p, at the exit's key
        of set k (:meth:`add_hybrid`; ex is G in the sets 0, 2, 3, 4, 6, 7 and S in 1 and 5).
        Photons in group order (``grp``): ge = f G and se = f S of the exits [J, P], q_se [8, P].

        - f^2 ex^2: per member the sums of ge^2 and se^2 over each group, each going to the
          group's eight keys (two passes over the block, not eight);
        - 2 r f q_se: nonzero only where a first-vertex sample shares a key with the exit (never
          in the component sets 0-3, whose keys hold the component): summed over those entries.
        The sums over keys are ordered bincounts over all members at once (member j's entries
        offset by j * n_sq): the same bits on every machine."""
        by_group = {"g": grp.sums(ge * ge), "s": grp.sums(se * se)}  # [J, U]
        sets = ("g", "s", "g", "g", "g", "s", "g", "g")
        keys = grp.labels[1:]  # [8, U]
        ee_at = np.concatenate([self._offsets(keys[k], n_sq) for k in range(len(sets))])
        ee_w = np.concatenate([by_group[v].ravel() for v in sets])  # set-major, then member, then group: as ee_at
        total = np.bincount(ee_at, weights=ee_w, minlength=len(self.accs) * n_sq)
        nz = np.flatnonzero(q_se)  # (set, photon) entries, set-major
        if nz.size:
            n_p = q_se.shape[1]
            by_key = _Groups(keys[nz // n_p, grp.group_of[nz % n_p]][None, :], n_sq)  # the entries grouped by key
            nz = nz[by_key.order]
            t = by_key.sums(f[:, nz % n_p] * q_se.reshape(-1)[nz][None, :])  # [J, keys reached]
            total.reshape(len(self.accs), n_sq)[:, by_key.labels[0]] += (2.0 * self.ratios)[:, None] * t
        return total.reshape(len(self.accs), n_sq)

    def add_walk(self, cfg: np.ndarray, status_exit: np.ndarray, status_trunc: np.ndarray, w: np.ndarray, nscat: np.ndarray) -> None:
        """Walk totals of finished photons: truncated weight w r^n of truncated photons, and the
        absorbed power as the balance w_0 - r^n w (exited or truncated) (module docstring).
        Sums per configuration over the photons in configuration order (_Groups), all members at
        once; the truncated weight, zero for nearly every block, is skipped where no photon was
        truncated (adding zeros changes no sum)."""
        if len(cfg) == 0:
            return
        grp = _Groups(np.asarray(cfg)[None, :], self.accs[0].n_cfg)
        o, at = grp.order, grp.labels[0]
        f = member_factors(self.ratios, nscat[o])  # [J, P], photons in configuration order
        w = np.asarray(w, dtype=np.float64)[o]
        left = np.where((status_exit | status_trunc)[o], w, 0.0)
        totals = [("absorbed", self.w0[cfg[o]][None, :] - left[None, :] * f)]
        if np.any(status_trunc):
            totals.append(("truncated", np.where(status_trunc[o], w, 0.0)[None, :] * f))
        for q, v in totals:
            for row, t in enumerate((v, v * v, (v != 0.0).astype(np.float64))):
                self.walk[q][:, row, at] += grp.sums(t)

    def finish(self, n_photons: int) -> list[tuple[dict, dict]]:
        """(stats, counts) of every member, as :meth:`PhotonAccumulator.finish`."""
        return [acc.finish(n_photons) for acc in self.accs]


class _Groups:
    """The photons of a block grouped by a tuple of integer labels (the rows of labels [K, P],
    each in [0, bound)): ``order`` sorts the photons by group (stably), ``sums(w)`` adds the
    columns of w [J, P] (photons in that order) over each group, giving [J, U]; ``labels``
    [K, U] are each group's labels and ``group_of`` [P] the group of each photon in that order.
    One pass over w per sum (np.add.reduceat on contiguous runs) where a bincount over all
    members needs an index per element; the additions run in a fixed order (numpy's pairwise sum
    of each run), so the bits do not depend on the machine."""

    def __init__(self, labels: np.ndarray, bound: int):
        group, n_group = np.zeros(labels.shape[1], dtype=np.int64), 1
        for row in labels:  # one number per tuple of labels so far; renumbered before it could overflow
            if n_group * bound >= 1 << 62:
                _, group = np.unique(group, return_inverse=True)
                group, n_group = group.reshape(-1), int(group.max()) + 1
            group, n_group = group * bound + row, n_group * bound
        # One stable sort: the order of the numbers is the order of their ranks (np.unique's
        # inverse, sorted again, cost a second sort), and the ranks in that order count the runs.
        self.order = np.argsort(group, kind="stable")
        ordered = group[self.order]
        first = np.concatenate(([True], ordered[1:] != ordered[:-1]))
        self.starts = np.flatnonzero(first)
        self.group_of = np.cumsum(first) - 1
        self.labels = labels[:, self.order[self.starts]]

    def sums(self, w: np.ndarray) -> np.ndarray:
        return np.add.reduceat(w, self.starts, axis=1)
