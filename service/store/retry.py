"""Retry decision after a task error: a pure function of the attempt count.

An attempt is one claim of a task. An expired lease also counts as an attempt (the claim that
re-takes the task increments ``attempts``), so a task whose worker keeps dying ends as failed too.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RetryPolicy", "RetryDecision", "decide_retry"]


@dataclass(frozen=True)
class RetryPolicy:
    """Exponential backoff parameters (seconds)."""

    base_delay_s: float = 1.0
    factor: float = 2.0
    max_delay_s: float = 60.0


@dataclass(frozen=True)
class RetryDecision:
    """Whether to queue the task again, and after how many seconds."""

    retry: bool
    delay_s: float = 0.0


def decide_retry(attempts: int, max_attempts: int, policy: RetryPolicy = RetryPolicy()) -> RetryDecision:
    """Decide what follows the ``attempts``-th failed attempt of a task.

    retry  = attempts < max_attempts
    delay  = min(max_delay_s, base_delay_s * factor ** (attempts - 1))      (seconds)

    so with the defaults the delays are 1, 2, 4, ... s, capped at 60 s. ``attempts >= 1`` is the
    number of claims so far, including the one that just failed.
    """
    if attempts < 1:
        raise ValueError(f"attempts must be >= 1 (claims so far); received {attempts}")
    if attempts >= max_attempts:
        return RetryDecision(retry=False)
    delay = min(policy.max_delay_s, policy.base_delay_s * policy.factor ** (attempts - 1))
    return RetryDecision(retry=True, delay_s=delay)
