"""What a spec will store before it runs: the shard payload and the dataset size (torch-free).

A shard's result (``workers.fold.tally.ShardTally``) holds, per estimator, three float64 sums
(S1, S2, SXN: workers.fold.tally) and an int64 event count of every quantity, for every configuration c (incidence angle x
channel of its medium) and component (single, multiple, total):

    bins_G, bins_S   [c, 3, n_r + 1, n_theta_s, n_cos, n_phi]   (radial index n_r: beyond r_max)
    radial_G         [c, 3, n_r + 1]
    Rd               [c, 3]

plus the walk's absorbed and truncated weights [c] (once), so

    payload = 3 * 8 * (n_est * c * 3 * ((n_r + 1) * (2 n_theta n_cos n_phi + 1) + 1) + 2 c)  bytes

before compression, times the members of the largest walk group of a sweep with shared walks
(schema.groups: one task tallies every albedo of its group) (the file is the compressed npz of those arrays; the merge holds them
uncompressed, one shard and one accumulator). Shards do not shrink it: every shard tallies
every bin. The dataset's tables have, per estimator, medium, configuration and component,
n_r radial rows, n_r n_theta n_cos n_phi bins rows and one summary row; their size before
compression is rows x (8 bytes per numeric column + the strings), plus summary.json.

Both estimates are upper bounds of what Parquet and npz store (their encodings and zstd /
deflate shrink them, by 5-50x on small test specs where most bins are empty; measured: the
payload estimate is the arrays' exact size); the service refuses a spec whose estimate exceeds a configured
limit (:func:`size_limit_problems`), so that no shard or merge outgrows a worker's memory or disk,
and a job whose shard tasks (rows of the job store, all created at submission) exceed one.
"""

from __future__ import annotations

from dataclasses import dataclass

from .spec import SimulationSpec
from .tables import BINS_SCHEMA, RADIAL_SCHEMA, SUMMARY_SCHEMA

__all__ = ["SizeEstimate", "estimate_sizes", "size_limit_problems", "format_bytes", "SUMMARY_JSON_ROW_BYTES"]

SUMMARY_JSON_ROW_BYTES = 450
"""Bytes of one row of summary.json (indented JSON of the summary columns; ~300 measured)."""
_COMPONENT_CHARS = (len("single") + len("multiple") + len("total")) / 3


@dataclass(frozen=True)
class SizeEstimate:
    """Bytes before compression: one shard's tally, and the dataset version's files."""

    shard_payload_bytes: int
    dataset_bytes: int
    media: int
    rows: int  # table rows of the dataset (radial + bins + summary)


def _row_bytes(schema, channel_chars: float, estimator_chars: float) -> float:
    """Bytes of one row before compression: 8 per numeric column plus the strings."""
    strings = {"estimator": estimator_chars, "channel": channel_chars, "component": _COMPONENT_CHARS}
    return sum(strings.get(f.name, 8.0) for f in schema)


def estimate_sizes(spec: SimulationSpec) -> SizeEstimate:
    """The shard payload (largest medium) and dataset size of ``spec`` (module docstring)."""
    est = spec.table_estimators
    n_r, n_t = spec.bins.radial.count, spec.theta_s_count()
    n_c, n_p = spec.bins.cos_theta_o.count, spec.bins.phi_o.count
    n_angles = len(spec.incidence_deg)
    names = spec.medium.channel_names if spec.sweep is None else ["c0"]  # a sweep medium has one channel
    c = n_angles * len(names)
    per_estimator = c * 3 * ((n_r + 1) * (2 * n_t * n_c * n_p + 1) + 1)
    payload = 4 * 8 * (len(est) * per_estimator + 2 * c) + 16 * (len(est) + 1)
    payload *= max(len(g) for g in spec.walk_groups())  # a shared walk's task tallies every member of its group
    keys = len(est) * spec.n_media * c * 3  # (estimator, medium, configuration, component)
    channel_chars = sum(map(len, names)) / len(names)
    est_chars = sum(map(len, est)) / len(est)
    rows = {"radial": keys * n_r, "bins": keys * n_r * n_t * n_c * n_p, "summary": keys}
    dataset = sum(rows[name] * _row_bytes(schema, channel_chars, est_chars)
                  for name, schema in (("radial", RADIAL_SCHEMA), ("bins", BINS_SCHEMA), ("summary", SUMMARY_SCHEMA)))
    dataset += keys * SUMMARY_JSON_ROW_BYTES
    return SizeEstimate(int(payload), int(dataset), spec.n_media, sum(rows.values()))


def format_bytes(n: float) -> str:
    """1234567 -> '1.23 MB' (decimal units)."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def size_limit_problems(spec: SimulationSpec, max_shard_bytes: int, max_dataset_bytes: int,
                        max_tasks: int | None = None) -> list[tuple[str, str, str, object]]:
    """``(field, message, allowed, received)`` for each size limit ``spec`` exceeds (empty: fits):
    the shard payload, the dataset, and (``max_tasks``) the job's shard tasks, walk groups x
    shards (schema.media), each a row of the job store created at submission.

    The message carries the estimate and says what shrinks it.
    """
    size = estimate_sizes(spec)
    out = []
    tasks = spec.task_count()
    if max_tasks is not None and tasks > max_tasks:
        groups = tasks // spec.shards
        out.append((
            "spec.shards",
            f"the job would have {tasks} shard tasks ({groups} walk groups x {spec.shards} shards, schema.media), "
            f"over the limit {max_tasks} (BSSRDF_MAX_JOB_TASKS); use fewer shards per medium, shared walks or "
            "fewer media (split the sweep)", f"shard tasks <= {max_tasks}", spec.shards))
    bins = (f"{spec.bins.radial.count} x {spec.theta_s_count()} x {spec.bins.cos_theta_o.count} x "
            f"{spec.bins.phi_o.count} bins (n_r x n_theta_s x n_cos x n_phi)")
    if size.shard_payload_bytes > max_shard_bytes:
        out.append((
            "spec.bins",
            f"a shard's tally would hold an estimated {format_bytes(size.shard_payload_bytes)} "
            f"({size.shard_payload_bytes} bytes before compression: {bins}, {len(spec.incidence_deg)} incidence "
            f"angles, 3 components, 3 sums and a count each, schema.sizes), over the limit {format_bytes(max_shard_bytes)} "
            "(BSSRDF_MAX_SHARD_BYTES); use fewer bins or incidence angles (more shards do not help: every shard "
            "tallies every bin)",
            f"estimated shard payload <= {max_shard_bytes} bytes", size.shard_payload_bytes))
    if size.dataset_bytes > max_dataset_bytes:
        field = "spec.sweep" if spec.sweep is not None else "spec.bins"
        out.append((
            field,
            f"the dataset would hold an estimated {format_bytes(size.dataset_bytes)} ({size.dataset_bytes} bytes "
            f"before compression: {size.rows} table rows over {size.media} media, {bins}), over the limit "
            f"{format_bytes(max_dataset_bytes)} (BSSRDF_MAX_DATASET_BYTES); use fewer bins, incidence angles or "
            "media", f"estimated dataset size <= {max_dataset_bytes} bytes", size.dataset_bytes))
    return out
