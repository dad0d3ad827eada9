"""Random numbers: counter-based Philox-4x32-10, and the per-photon xoshiro128+ streams it seeds,
written in torch integer ops.

Every random number of a run is a pure function of a *key* and a *counter*:

    key     = (k0, k1)          derived from (seed, medium configuration)   -- :func:`stream_key`
    counter = (c0, c1, c2, c3)  = (photon index low, photon index high, draw index, purpose)

so a photon's random stream does not depend on the lane it runs in, the batch size, the number
of threads or workers, or the order in which shards run.  That is what makes the tables bitwise
reproducible (docs/architecture.md, "Determinism"), and because the generator is plain
integer arithmetic it fuses into the compiled walk step (research/performance.md).

Philox-4x32-10 is the generator of Salmon, Moraes, Dror and Shaw, "Parallel random numbers: as easy
as 1, 2, 3", SC'11, with the Random123 round constants; :func:`philox4x32` is checked against the
Random123 known-answer vectors in the tests.

torch has no unsigned 32-bit arithmetic on the CPU, so words are carried as int32 *bit patterns*
(a word >= 2**31 reads as negative) and every product is formed in 32-bit lanes: AVX2 has native
32-bit vector multiplies but no 64-bit one (ATen emulates int64 multiplication there one element at
a time, which made an int64 generator the slowest part of the compiled walk).  :func:`to_i32` and
:func:`to_u32` convert from and to int64 tensors holding the unsigned values.

**The walk's draws.**  Ten Philox rounds per step were about a third of a compiled walk step (about 400
vector operations per block on AVX2, where each 32 x 32 -> 64-bit product is built from 16-bit partial
products).  The walk therefore keys only the *start* of a photon's stream by its counter: at launch
the block Philox(photon, 0, PURPOSE_WALK) becomes the 128-bit state of a xoshiro128+ generator
(Blackman and Vigna, "Scrambled linear pseudorandom number generators", 2021) carried in the
photon's lane, and every step takes the next four 32-bit outputs of that state (11 vector
operations per output: an add, xors and shifts).  A photon's draws remain a function of (seed,
configuration, photon) alone -- not of its lane, the lane count or the threads -- because the state
moves with the photon and is advanced once per step of that photon.  xoshiro128+ has period
2^128 - 1 and passes BigCrush except in its lowest bits, which have low linear complexity; the
uniform mappings below use the top 23 or 24 bits only.  One bit of the Philox block is forced (the
second word is made odd), which keeps the state away from the all-zero fixed point.  Other draws
(roulette rounds, connection samples) stay plain counter-based Philox.
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
    "native_wide_multiply",
    "photon_words",
    "stream_start",
    "stream_next",
    "stream_draws",
    "xoshiro128p_scalar",
    "to_i32",
    "to_u32",
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


def _signed(v: int) -> int:
    """The int32 reading of the 32-bit word v."""
    return v - (1 << 32) if v >= 1 << 31 else v


def to_i32(x: torch.Tensor) -> torch.Tensor:
    """int32 bit patterns of int64 values in [0, 2**32) (no overflow anywhere: exact)."""
    return (x - ((x & 0x80000000) << 1)).to(torch.int32)


def to_u32(x: torch.Tensor) -> torch.Tensor:
    """int64 unsigned values in [0, 2**32) of int32 bit patterns."""
    return x.to(torch.int64) & _MASK32


def _hi16(x: torch.Tensor) -> torch.Tensor:
    """The top 16 bits of a 32-bit word as a value in [0, 2**16) (>> on int32 is arithmetic)."""
    return (x >> 16) & 0xFFFF


def _mulhilo(a: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(hi, lo) words of the 64-bit product a * m, a an int32 bit pattern, m < 2**32 a constant.

    lo is the wrapping 32-bit product.  hi is the unsigned high word formed from 16-bit halves
    a = ah 2**16 + al, m = mh 2**16 + ml (Hacker's Delight, 8-2, mulhu):

        t  = ah ml + (al ml >> 16)             < 2**32
        w1 = (t mod 2**16) + al mh             < 2**32
        hi = ah mh + (t >> 16) + (w1 >> 16)

    Every partial value is below 2**32, so its int32 bit pattern (wrapping where it passes 2**31)
    is exact and the masked shifts read it as unsigned.  Wrapping int32 arithmetic is what the
    vector instructions do; the known-answer tests run this eager and compiled.
    """
    ml, mh = m & 0xFFFF, m >> 16
    al = a & 0xFFFF
    ah = _hi16(a)
    t = ah * ml + _hi16(al * ml)
    w1 = (t & 0xFFFF) + al * mh
    hi = ah * mh + _hi16(t) + _hi16(w1)
    return hi, a * _signed(m)


def philox4x32(
    c0: torch.Tensor, c1: torch.Tensor, c2: torch.Tensor, c3: torch.Tensor, k0: torch.Tensor, k1: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Philox-4x32-10 block: four 32-bit outputs per counter.

    Inputs are broadcastable tensors, either all int32 (bit patterns; the outputs are int32 bit
    patterns too: the walk's form, and the only one allowed inside torch.compile) or int64
    holding values in [0, 2**32) (outputs likewise; eager only).  Compiled, the rounds run in
    int32 lanes (:func:`_mulhilo`) or, where the vector ISA multiplies int64 natively
    (:func:`native_wide_multiply`), in int64 like the eager form (:func:`_philox_u64`).
    One round is

        (hi0, lo0) = M0 * c0 ;  (hi1, lo1) = M1 * c2
        c = (hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0)

    and the key is bumped by the Weyl constants (W0, W1) between rounds.
    """
    wide = c0.dtype == torch.int64
    if torch.compiler.is_compiling():
        if wide:
            # Inductor may carry the int32 products of a value cast from int64 in 64-bit
            # registers, losing the wrap the high word relies on: compiled code passes int32.
            raise TypeError("philox4x32: compiled code must pass int32 words (see to_i32)")
        if not _native_wide:
            return _philox_i32(c0, c1, c2, c3, k0, k1)
        out = _philox_u64(*(to_u32(v) for v in (c0, c1, c2, c3, k0, k1)))
        return tuple(to_i32(w) for w in out)
    # Eager: one int64 multiply per product is ~2.5x fewer tensor operations than the 16-bit
    # partial products, and eager cost is per operation.  Same words either way (tested).
    if not wide:
        c0, c1, c2, c3, k0, k1 = (to_u32(torch.as_tensor(v)) for v in (c0, c1, c2, c3, k0, k1))
    out = _philox_u64(c0, c1, c2, c3, k0, k1)
    return out if wide else tuple(to_i32(w) for w in out)


_native_wide: bool | None = None  # set by native_wide_multiply(), read inside compiled graphs


def native_wide_multiply() -> bool:
    """Whether compiled CPU kernels multiply int64 vectors in hardware (AVX-512: vpmullq).

    Then the compiled rounds run on int64 words (one multiply per product, as in the eager form;
    about 1.8x faster than the 16-bit partial products there); elsewhere (AVX2: ATen emulates the
    int64 vector multiply one element at a time) on int32 words.  Both forms give the same words
    (tested), so this only selects the arithmetic.  Asks ATen's CPU capability, the vector ISA
    inductor generates for unless told otherwise (asking inductor itself costs seconds of probe
    builds per process).  Call it before tracing (workers.walk.kernels does): traced code only reads
    the cached answer, and takes the int32 form while nobody has asked.
    """
    global _native_wide
    if _native_wide is None:
        _native_wide = torch.backends.cpu.get_cpu_capability().startswith("AVX512")
    return _native_wide


def _rounds(c0, c1, c2, c3, k0, k1, mulhilo, w0: int, w1: int, mask: int | None):
    """The ten Philox rounds with the given (hi, lo) product and key bump (masked if given)."""
    for r in range(_ROUNDS):
        if r:
            k0, k1 = k0 + w0, k1 + w1
            if mask is not None:
                k0, k1 = k0 & mask, k1 & mask
        hi0, lo0 = mulhilo(c0, PHILOX_M0)
        hi1, lo1 = mulhilo(c2, PHILOX_M1)
        c0, c1, c2, c3 = hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0
    return c0, c1, c2, c3


def _philox_i32(c0, c1, c2, c3, k0, k1):
    """Philox-4x32-10 on int32 bit patterns (the compiled walk's form): wrapping int32 key bumps."""
    return _rounds(c0, c1, c2, c3, k0, k1, _mulhilo, _signed(PHILOX_W0), _signed(PHILOX_W1), None)


def _mulhilo_u64(a: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(hi, lo) of a * m for int64 a in [0, 2**32).  The product may exceed 2**63: int64
    multiplication wraps modulo 2**64 in torch's CPU kernels, leaving the bit pattern of the
    unsigned product, and the masks recover the halves."""
    p = a * m
    return (p >> 32) & _MASK32, p & _MASK32


def _philox_u64(c0, c1, c2, c3, k0, k1):
    """Philox-4x32-10 on int64 tensors holding words in [0, 2**32) (eager form)."""
    return _rounds(c0, c1, c2, c3, k0, k1, _mulhilo_u64, PHILOX_W0, PHILOX_W1, _MASK32)


def photon_words(photon: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Counter words 0 and 1 of an int64 photon index: its low and high 32 bits as int32 bit
    patterns (exact casts, see :func:`to_i32`)."""
    return to_i32(photon & _MASK32), to_i32(photon >> 32)


def stream_start(c_lo, c_hi, purpose: int, k0, k1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The xoshiro128+ state that starts a photon's stream: the Philox block of counter
    (c_lo, c_hi, 0, purpose) under key (k0, k1), with the second word made odd (never all zero).
    int32 bit patterns in and out (broadcastable)."""
    zero = torch.zeros_like(c_lo)
    b0, b1, b2, b3 = philox4x32(c_lo, c_hi, zero, zero + purpose, k0, k1)
    return b0, b1 | 1, b2, b3


def stream_next(s0, s1, s2, s3):
    """One xoshiro128+ output and the next state, on int32 bit patterns (wrapping arithmetic):

        out = s0 + s3;  t = s1 << 9
        s2 ^= s0;  s3 ^= s1;  s1 ^= s2;  s0 ^= s3;  s2 ^= t;  s3 = rotl(s3, 11)
    """
    out = s0 + s3
    t = s1 << 9
    s2 = s2 ^ s0
    s3 = s3 ^ s1
    s1 = s1 ^ s2
    s0 = s0 ^ s3
    s2 = s2 ^ t
    s3 = (s3 << 11) | ((s3 >> 21) & 0x7FF)  # rotl(s3, 11); >> on int32 is arithmetic, hence the mask
    return out, (s0, s1, s2, s3)


def stream_draws(state, n: int = 4):
    """The next n outputs of xoshiro128+ states (a tuple of four int32 tensors) and the state after
    them: ((out_1, ..., out_n), state)."""
    outs = []
    for _ in range(n):
        out, state = stream_next(*state)
        outs.append(out)
    return tuple(outs), state


def xoshiro128p_scalar(state: tuple[int, int, int, int], n: int) -> tuple[list[int], tuple[int, int, int, int]]:
    """Plain-Python xoshiro128+ on unsigned ints (the reference for the tensor version): n outputs
    and the state after them."""
    s0, s1, s2, s3 = state
    outs = []
    for _ in range(n):
        outs.append((s0 + s3) & _MASK32)
        t = (s1 << 9) & _MASK32
        s2 ^= s0
        s3 ^= s1
        s1 ^= s2
        s0 ^= s3
        s2 ^= t
        s3 = ((s3 << 11) | (s3 >> 21)) & _MASK32
    return outs, (s0, s1, s2, s3)


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
    """Map 32 random bits (int32 bit pattern or int64 value) to float32 in the open interval (0, 1): ((x >> 9) + 0.5) / 2**23.

    A 23-bit grid offset by half a step: every value, up to 1 - 2**-24, is exact in float32, so
    the result is never 0 or 1 and -log(u), log(1 - u) are finite.  (A 24-bit grid + 0.5 would
    need 25 significant bits at the top and round up to exactly 1.)
    """
    return (((x >> 9) & 0x7FFFFF).to(torch.float32) + 0.5) * (1.0 / 8388608.0)


def uniform_halfopen(x: torch.Tensor) -> torch.Tensor:
    """Map 32 random bits to float32 in [0, 1): (x >> 8) / 2**24 (exact in float32)."""
    return ((x >> 8) & 0xFFFFFF).to(torch.float32) * (1.0 / 16777216.0)


def stream_key(seed: int, config_fingerprint: str) -> tuple[int, int]:
    """The Philox key (k0, k1) of one medium configuration of a run.

    sha256 over the seed and a canonical description of the configuration (the optical
    parameters, incidence angle and channel), so different media, channels or angles of the same
    seed draw independent streams, and the key is stable across Python processes (unlike hash()).
    """
    digest = hashlib.sha256(f"{seed}|{config_fingerprint}".encode()).digest()
    return int.from_bytes(digest[0:4], "little"), int.from_bytes(digest[4:8], "little")
