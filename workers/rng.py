"""Counter-based random numbers: Philox-4x32-10 written in torch integer ops.

Every random number of a run is a pure function of a *key* and a *counter*:

    key     = (k0, k1)          derived from (seed, medium configuration)   -- :func:`stream_key`
    counter = (c0, c1, c2, c3)  = (photon index low, photon index high, draw index, purpose)

so a photon's random stream does not depend on the lane it runs in, the batch size, the number
of threads or workers, or the order in which shards run.  That is what makes the tables bitwise
reproducible (ARCHITECTURE.md, "Statistics and determinism"), and because the generator is plain
integer arithmetic it fuses into the compiled walk step (research/performance.md).

Philox-4x32-10 is the generator of Salmon, Moraes, Dror and Shaw, "Parallel random numbers: as easy
as 1, 2, 3", SC'11, with the Random123 round constants; :func:`philox4x32` is checked against the
Random123 known-answer vectors in the tests.

Values are carried in int64 tensors holding unsigned 32-bit values (torch has no full unsigned
32-bit arithmetic on the CPU).
"""

from __future__ import annotations

import hashlib

import torch

__all__ = [
    "PHILOX_M0",
    "PHILOX_M1",
    "PHILOX_W0",
    "PHILOX_W1",
    "philox4x32",
    "philox4x32_scalar",
    "stream_key",
    "uniform_open",
    "uniform_halfopen",
]

PHILOX_M0 = 0xD2511F53
PHILOX_M1 = 0xCD9E8D57
PHILOX_W0 = 0x9E3779B9  # golden ratio
PHILOX_W1 = 0xBB67AE85  # sqrt(3) - 1
_MASK32 = 0xFFFFFFFF
_ROUNDS = 10


def _mulhilo(a: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(hi, lo) 32-bit halves of the 64-bit product a * m, for 0 <= a, m < 2**32.

    The product is below 2**64 but may exceed 2**63: int64 multiplication then wraps modulo 2**64
    (two's complement, as torch's CPU kernels and the compiled code do on every supported
    platform), leaving the bit pattern of the unsigned product; the masks recover the halves.
    The known-answer tests run this in eager and compiled mode, so a platform where the wrap
    assumption failed would be caught.  (Splitting m into 16-bit halves avoids the wrap but made
    the compiled generator about 30 % slower here.)
    """
    p = a * m
    return (p >> 32) & _MASK32, p & _MASK32


def philox4x32(
    c0: torch.Tensor, c1: torch.Tensor, c2: torch.Tensor, c3: torch.Tensor, k0: torch.Tensor, k1: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Philox-4x32-10 block: four 32-bit outputs (as int64 in [0, 2**32)) per counter.

    All inputs are int64 tensors (or broadcastable) holding values in [0, 2**32).  One round is

        (hi0, lo0) = M0 * c0 ;  (hi1, lo1) = M1 * c2
        c = (hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0)

    and the key is bumped by the Weyl constants (W0, W1) between rounds.
    """
    for r in range(_ROUNDS):
        if r:
            k0 = (k0 + PHILOX_W0) & _MASK32
            k1 = (k1 + PHILOX_W1) & _MASK32
        hi0, lo0 = _mulhilo(c0, PHILOX_M0)
        hi1, lo1 = _mulhilo(c2, PHILOX_M1)
        c0, c1, c2, c3 = hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0
    return c0, c1, c2, c3


def philox4x32_scalar(counter: tuple[int, int, int, int], key: tuple[int, int]) -> tuple[int, int, int, int]:
    """Plain-Python Philox-4x32-10 on ints: the reference the tensor version is tested against."""
    c0, c1, c2, c3 = counter
    k0, k1 = key
    for r in range(_ROUNDS):
        if r:
            k0 = (k0 + PHILOX_W0) & _MASK32
            k1 = (k1 + PHILOX_W1) & _MASK32
        p0 = PHILOX_M0 * c0
        p1 = PHILOX_M1 * c2
        c0, c1, c2, c3 = (p1 >> 32) ^ c1 ^ k0, p1 & _MASK32, (p0 >> 32) ^ c3 ^ k1, p0 & _MASK32
    return c0, c1, c2, c3


def uniform_open(x: torch.Tensor) -> torch.Tensor:
    """Map 32 random bits to float32 in the open interval (0, 1): ((x >> 9) + 0.5) / 2**23.

    A 23-bit grid offset by half a step: every value, up to 1 - 2**-24, is exact in float32, so
    the result is never 0 or 1 and -log(u), log(1 - u) are finite.  (A 24-bit grid + 0.5 would
    need 25 significant bits at the top and round up to exactly 1.)
    """
    return ((x >> 9).to(torch.float32) + 0.5) * (1.0 / 8388608.0)


def uniform_halfopen(x: torch.Tensor) -> torch.Tensor:
    """Map 32 random bits to float32 in [0, 1): (x >> 8) / 2**24 (exact in float32)."""
    return (x >> 8).to(torch.float32) * (1.0 / 16777216.0)


def stream_key(seed: int, config_fingerprint: str) -> tuple[int, int]:
    """The Philox key (k0, k1) of one medium configuration of a run.

    sha256 over the seed and a canonical description of the configuration (the optical
    parameters, incidence angle and channel), so different media, channels or angles of the same
    seed draw independent streams, and the key is stable across Python processes (unlike hash()).
    """
    digest = hashlib.sha256(f"{seed}|{config_fingerprint}".encode()).digest()
    return int.from_bytes(digest[0:4], "little"), int.from_bytes(digest[4:8], "little")
