"""The Prometheus text exposition format (version 0.0.4), by hand: no client library needed.

    # HELP bssrdf_jobs Jobs by state.
    # TYPE bssrdf_jobs gauge
    bssrdf_jobs{state="queued"} 2
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["CONTENT_TYPE", "render_metrics", "family"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def family(name: str, kind: str, help_text: str, samples: Mapping[tuple[tuple[str, str], ...], float]) -> list[str]:
    """Lines of one metric family; ``samples`` maps label tuples ``(("state", "queued"),)`` to values."""
    lines = [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}"]
    for labels, value in samples.items():
        label_text = ",".join(f'{k}="{_escape(v)}"' for k, v in labels)
        lines.append(f"{name}{{{label_text}}} {value}" if labels else f"{name} {value}")
    return lines


def render_metrics(m: Mapping[str, object]) -> str:
    """The text of ``/metrics`` from ``JobStore.metrics()``."""
    lines = family("bssrdf_jobs", "gauge", "Jobs by state.",
                   {(("state", s),): n for s, n in m["jobs_by_state"].items()})
    counters = (
        ("bssrdf_tasks_claimed_total", "tasks_claimed", "Claims of shard and merge tasks (attempts)."),
        ("bssrdf_shards_completed_total", "shards_completed", "Shard tasks completed."),
        ("bssrdf_merges_completed_total", "merges_completed", "Merge tasks completed (dataset versions published)."),
        ("bssrdf_leases_expired_total", "leases_expired", "Leases that expired (the task was claimed again or failed)."),
        ("bssrdf_photons_simulated_total", "photons_simulated", "Photons of completed shards."),
    )
    for name, key, help_text in counters:
        lines += family(name, "counter", help_text, {(): m[key]})
    return "\n".join(lines) + "\n"
