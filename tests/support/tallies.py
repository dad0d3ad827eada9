"""Fingerprints of shard tallies for bitwise-determinism tests."""

from __future__ import annotations

import dataclasses
import hashlib

from workers.fold.tally import ShardTally

__all__ = ["tally_digest"]


def tally_digest(tally: ShardTally) -> str:
    """sha256 of everything in a tally but its info (the statistics and the counts): two runs
    that must be bitwise identical have equal digests, whatever their timings."""
    return hashlib.sha256(dataclasses.replace(tally, info={}).to_bytes()).hexdigest()
