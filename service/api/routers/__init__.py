"""One router per resource: :mod:`.jobs`, :mod:`.datasets`, :mod:`.health` (health and metrics)."""

__all__ = ["jobs", "datasets", "health"]
