"""`bssrdf simulate`: measure a BSSRDF table without the job service and write its tables.

Runs the shards of the spec on this machine without the job service (one worker process per
core, see :mod:`workers.run.pool`), merges them and writes radial.parquet, bins.parquet,
summary.parquet and summary.json into --out.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from schema import COMPONENTS, SpecError, load_spec

from .cores import default_workers

# torch and the walk are imported where they are used: `bssrdf run` and `bssrdf --help` build
# this module's parser, and a worker-launching parent must not spend seconds importing torch.

__all__ = ["add_parser", "main", "positive_int", "simulate", "simulate_to_target", "simulate_sweep", "run_shards", "run_tasks", "format_summary"]


def simulate(spec, *, progress=None, threads: int | None = None, processes: int | None = None):
    """Run every shard of a single-medium `spec` and merge them; returns the Result.

    processes > 1 runs the shards on that many worker processes (:class:`workers.run.pool.ShardPool`,
    what the command line does); otherwise they run in this process on `threads` threads (default:
    one per core), each with one torch intra-op thread.  The merge sums in shard order, so the
    result is bitwise the same for any number of threads or processes.  A spec with a ``target``
    runs to it (:func:`simulate_to_target`).  A sweep has one Result per medium:
    :func:`simulate_sweep` writes its tables.
    """
    from workers.fold.merge import merge

    if spec.is_sweep:
        raise ValueError("simulate() runs one medium; a sweep's tables are written by simulate_sweep(spec, out_dir)")
    if spec.target is not None:
        return simulate_to_target(spec, progress=progress, threads=threads, processes=processes)
    return merge(spec, run_shards(spec, range(spec.shards), progress=progress, threads=threads, processes=processes))


def simulate_to_target(spec, *, progress=None, threads: int | None = None, processes: int | None = None):
    """Run shards in shard order until the merge of shards 0..K-1 meets ``spec.target``.

    Shards run in waves of as many as run at once (processes, else threads); after each wave the
    finished shards are folded in order and :func:`workers.fold.target.target_status` is checked after
    every one of them, so K is the first prefix that meets the target whatever the wave size, and
    the result is bitwise the merge of those K shards (shards after K that ran in the same wave
    are dropped).  Without meeting it, all ``spec.shards`` shards run (``photons`` is the cap).
    ``result.target`` holds the status of the returned merge.
    """
    from workers.fold.merge import Fold
    from .pool import ShardPool
    from workers.fold.target import target_status

    width = max(1, min(spec.shards, processes if processes is not None else threads or os.cpu_count() or 1))
    with contextlib.ExitStack() as stack:
        if processes is not None and width > 1:
            pool = stack.enter_context(ShardPool(width))  # one pool for every wave: processes start once
            run = lambda indices: pool.run(spec, indices, progress)  # noqa: E731
        else:
            run = lambda indices: run_shards(spec, indices, progress=progress, threads=threads)  # noqa: E731
        fold = Fold(spec)
        for start in range(0, spec.shards, width):
            for tally in run(range(start, min(spec.shards, start + width))):
                fold.add(tally)
                result = fold.result()
                result.target = target_status(result, spec.target)
                if result.target.reached:
                    return result
    return result


def run_shards(spec, indices, *, progress=None, threads: int | None = None, processes: int | None = None) -> list:
    """run_shard for each index, on `processes` worker processes or `threads` threads of this
    process (one torch thread each); the tallies in the order of indices."""
    indices = list(indices)
    return list(run_tasks(((spec, i) for i in indices), progress=progress, threads=threads, processes=processes,
                          workers_hint=len(indices), window=max(1, len(indices))))


def run_tasks(items, *, progress=None, threads: int | None = None, processes: int | None = None,
              workers_hint: int | None = None, window: int | None = None):
    """run_shard(spec, index) of each item (spec, index) of `items` (lazily drawn; an item
    (spec, index, member albedos) also tallies those albedos from the walk, workers.fold.reweight), on `processes` worker
    processes or `threads` threads; yields the tallies in item order with at most `window`
    (default two per worker) running or waiting ahead (:func:`workers.run.pool.in_order`).
    `workers_hint`, if given, caps the workers (no more than there are items)."""
    import torch

    from .pool import ShardPool, in_order
    from .shard import run_shard

    cap = workers_hint if workers_hint is not None else 1 << 30
    if processes is not None and min(processes, cap) > 1:
        with ShardPool(min(processes, cap)) as pool:
            yield from pool.imap(items, progress, window=window)
        return
    threads = max(1, min(threads or os.cpu_count() or 1, cap))
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if threads == 1:
            for spec, i, *members in items:
                yield run_shard(spec, i, progress=progress, members=tuple(members[0]) if members else ())
            return
        with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="shard") as pool:
            submit = lambda item: pool.submit(run_shard, item[0], item[1], progress=progress,  # noqa: E731
                                              members=tuple(item[2]) if len(item) > 2 else ())
            yield from in_order(submit, items, window or 2 * threads)
    finally:
        torch.set_num_threads(previous)


def simulate_sweep(spec, out_dir: str, *, filesystem=None, progress=None, threads: int | None = None,
                   processes: int | None = None, stop_rule=None) -> list[str]:
    """Run every medium of the sweep `spec` in task order and write the job's
    tables into `out_dir`; returns the file names.

    Tallies are folded as they arrive in task order (:class:`workers.fold.job.JobFold`), each
    finished medium's tables go to a part under ``out_dir/.parts`` and the parts are streamed
    into the tables at the end, so memory is one medium's accumulator and tables plus the shards
    in flight.  A medium stops early when `stop_rule` holds (default: the spec's target error,
    :func:`workers.fold.job.target_rule`); its shards past the stop are skipped.
    """
    import functools
    from collections import deque

    import pyarrow.fs as pafs

    from workers.fold.job import JobFold, read_part, target_rule, write_part, write_sweep_tables

    from workers.run.task import group_walk

    fs = filesystem or pafs.LocalFileSystem()
    fold = JobFold(spec, stop_rule if stop_rule is not None else target_rule(spec))
    medium_spec = functools.lru_cache(maxsize=4)(spec.medium_spec)  # one object per medium: the pool sends it once
    parts = f"{out_dir}/.parts"
    submitted: deque[int] = deque()

    def items():
        task, n = 0, spec.task_count()
        while (task := max(task, fold.next_task)) < n:
            group, shard = spec.task_of(task)
            leader, members = group_walk(spec, group)
            submitted.append(task)
            yield medium_spec(leader), shard, members
            task += 1

    for tally in run_tasks(items(), progress=progress, threads=threads, processes=processes):
        task = submitted.popleft()
        if task < fold.next_task:
            continue  # past its medium's early stop: never counted
        if fold.add(task, tally) is not None:
            for result in fold.finished:
                write_part(result, f"{parts}/m{result.medium_index:06d}", fs)
    tables = (read_part(f"{parts}/m{m:06d}", fs) for m in range(spec.n_media))
    files = write_sweep_tables(spec, fold.media, tables, out_dir, fs)
    fs.delete_dir(parts)
    return files


def format_summary(doc: dict, max_rows: int = 60) -> str:
    """Human-readable table of a summary document (see workers.fold.output.summary); a sweep's rows
    carry the medium's coordinates; beyond `max_rows` lines the rest is counted, not shown."""
    results = doc["results"]
    sweep = "media" in doc["run"]
    photons = doc["run"]["photons_per_config"]
    per = "photons per angle and channel" + (" of each medium" if sweep else "")
    if sweep:  # one count, or the range (a run to a target stops each medium at its own)
        photons = photons[0] if len(set(photons)) == 1 else f"{min(photons)}-{max(photons)}"
    lines = [f"{doc['name']}  (spec {doc['spec_hash'][:12]}, {photons} {per}"
             + (f", {doc['run']['media']} media)" if sweep else ")")]
    medium_cols = f"{'medium':>6} {'albedo':>8} {'g':>6} {'eta':>6}  " if sweep else ""
    lines.append(f"{medium_cols}{'estimator':<12}{'theta_i':>8} {'ch':<4}{'R_spec':>9}  {'single':>20}  {'multiple':>20}  {'total':>20}")
    rows: dict[tuple, dict] = {}
    for r in results:
        rows.setdefault((r.get("medium", 0), r["estimator"], r["incidence_deg"], r["channel"]), {})[r["component"]] = r
    for n, ((medium, est, inc, ch), comps) in enumerate(rows.items()):
        if n == max_rows:
            lines.append(f"... {len(rows) - max_rows} more rows (all of them in summary.json / summary.parquet)")
            break
        cells = [f"{comps[c]['Rd']:.5f} +- " + ("    n/a" if comps[c]["Rd_stderr"] is None else f"{comps[c]['Rd_stderr']:.5f}")
                 for c in COMPONENTS]  # fmt: skip
        total = comps["total"]
        prefix = f"{medium:>6} {total['albedo']:>8.5f} {total['g']:>6.3f} {total['eta']:>6.3f}  " if sweep else ""
        lines.append(f"{prefix}{est:<12}{inc:>8.1f} {ch:<4}{total['R_spec']:>9.5f}  {cells[0]:>20}  {cells[1]:>20}  {cells[2]:>20}")
    lines.append("Rd = diffuse reflectance (specular excluded) per unit incident power, +- one standard error.")
    if "target" in doc:
        lines += target_lines(doc["target"], results)
    return "\n".join(lines)


def _worst_check(w: dict) -> str:
    what = "Rd" if w["r_lo_mm"] is None else f"Rd(r) in [{w['r_lo_mm']:.4g}, {w['r_hi_mm']:.4g}) mm"
    rel = "no estimate" if w["rel_stderr"] is None else f"{w['rel_stderr']:.3g}"
    return (f"{what}, {w['estimator']}, {w['channel']}, theta_i {w['incidence_deg']:g}: relative error {rel} on {w['dof']} dof, "
            f"limit {w['limit']:g}")


def _severity(t: dict) -> float:
    """How far a medium's worst check is from its limit (relative error / limit; no estimate: inf)."""
    w = t["worst"]
    return math.inf if w["rel_stderr"] is None else w["rel_stderr"] / w["limit"]


def target_lines(target: dict | list, results: list[dict], max_listed: int = 10) -> list[str]:
    """What a run to a target error reached: a single medium's status (a dict), or a sweep's
    (a list, one status per medium): the media and checks met, the photon counts, the medium
    whose worst check is nearest its limit (or beyond it) and the media that did not reach it."""
    if isinstance(target, dict):
        t = target
        return [f"target {'reached' if t['reached'] else 'NOT reached'} with {t['photons']} photons per angle and channel "
                f"({t['met']} of {t['checks']} checks met; worst: {_worst_check(t['worst'])})"]  # fmt: skip
    judged = [(m, t) for m, t in enumerate(target) if t is not None]
    if not judged:
        return ["target: no medium was judged"]
    reached = [m for m, t in judged if t["reached"]]
    photons = sorted(t["photons"] for _, t in judged)
    span = f"{photons[0]}" if photons[0] == photons[-1] else f"{photons[0]}-{photons[-1]}"
    coords = {r["medium"]: r for r in results if "medium" in r}
    m, t = max(judged, key=lambda mt: _severity(mt[1]))
    where = f"medium {m}" + (f" (albedo {coords[m]['albedo']:.5g}, g {coords[m]['g']:.3g}, eta {coords[m]['eta']:.3g})" if m in coords else "")
    lines = [f"target reached in {len(reached)} of {len(target)} media with {span} photons per angle and channel "
             f"({sum(t['met'] for _, t in judged)} of {sum(t['checks'] for _, t in judged)} checks met); "
             f"worst: {where}, {_worst_check(t['worst'])}"]  # fmt: skip
    missed = [m for m, t in judged if not t["reached"]] + [m for m, t in enumerate(target) if t is None]
    if missed:
        shown = ", ".join(map(str, sorted(missed)[:max_listed])) + (f" and {len(missed) - max_listed} more" if len(missed) > max_listed else "")
        lines.append(f"target NOT reached in media {shown}")
    return lines


class _Progress:
    """A tqdm bar on a terminal, nothing otherwise."""

    def __init__(self, total: int, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="photon", unit_scale=True, dynamic_ncols=True, file=sys.stderr)

    def __call__(self, n: int) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="measure a BSSRDF table on this machine (no job service)",
        description="Run the photon random walk for SPEC on this machine (one process per core, no "
        "job service or database), write "
        "radial.parquet, bins.parquet, summary.parquet and summary.json into --out, and print "
        "R_spec and the diffuse reflectance Rd (single / multiple / total, with standard errors) "
        "per incidence angle and channel.",
    )
    p.add_argument("spec", help="simulation spec (JSON); see examples/ and schema/spec.schema.json")
    p.add_argument("--out", default="out", help="output directory (created; default ./out)")
    p.add_argument("--photons", type=int, help="override the spec's photons per incidence angle and channel")
    p.add_argument("--seed", type=int, help="override the spec's seed")
    p.add_argument("--workers", type=positive_int, default=default_workers(),
                   help="shards run concurrently, each in its own process on one core (default: one "
                   "per core, %(default)s here); 1 runs them one after another in this process")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    p.set_defaults(func=main)


def positive_int(text: str) -> int:
    """argparse type of an option that counts something: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def load_with_overrides(path: str, photons: int | None, seed: int | None):
    """Load a spec and apply --photons / --seed, re-validating so the limits still hold."""
    spec = load_spec(path)
    update = {k: v for k, v in (("photons", photons), ("seed", seed)) if v is not None}
    if update:
        from schema import parse_spec

        data = spec.model_dump(mode="json")
        data.update(update)
        spec = parse_spec(data, source=f"{path} with --photons/--seed")
    return spec


def main(args: argparse.Namespace) -> int:
    from workers.fold.output import summary, write_tables

    try:
        spec = load_with_overrides(args.spec, args.photons, args.seed)
    except (SpecError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n_cfg = len(spec.incidence_deg) * len(spec.medium_spec(0).channels())
    progress = _Progress(spec.photons * n_cfg * spec.n_media, enabled=sys.stderr.isatty() and not args.no_progress)
    out = str(Path(args.out).resolve())
    t0 = time.perf_counter()
    try:
        if spec.is_sweep:
            simulate_sweep(spec, out, progress=progress, threads=1, processes=args.workers)
        else:
            result = simulate(spec, progress=progress, threads=1, processes=args.workers)
    finally:
        progress.close()
    if spec.is_sweep:
        doc = json.loads(Path(out, "summary.json").read_text())
    else:
        write_tables(result, out)
        doc = summary(result)
    elapsed = time.perf_counter() - t0
    if args.json:
        print(json.dumps(dict(doc, out=str(args.out), elapsed_s=round(elapsed, 3)), sort_keys=True))
    else:
        print(format_summary(doc))
        print(f"wrote {', '.join(sorted(p.name for p in Path(args.out).iterdir()))} to {args.out} in {elapsed:.1f} s")
    return 0
