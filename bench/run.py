"""End-to-end throughput: `bssrdf run` with 1 and 2 workers against `bssrdf simulate`.

    python -m bench.run [--photons 16000000] [--shards 8] [--medium M2] [--estimator exits]

Each command runs as a fresh process on a fresh data directory, timed from start to exit, so the
figures include everything a user waits for: interpreter and torch start-up, loading the compiled
walk from the inductor cache (warmed once beforehand, outside the timings), the SQLite job store,
leases and commits, the merge and the dataset write.  Prints one line per run and the ratios the
job-service issue asks about (2 workers against 1; the service against `simulate`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from workers.measure.bench import MEDIA

__all__ = ["main"]


def _spec_doc(medium: str, estimator: str, photons: int, shards: int) -> dict:
    return {
        "name": f"bench-run-{medium}-{estimator}", "medium": MEDIA[medium], "photons": photons,
        "shards": shards, "batches_per_shard": 4, "estimator": estimator, "seed": 11,
    }  # fmt: skip


def _timed(cmd: list[str], cwd: Path) -> float:
    """Wall seconds of cmd, which must succeed."""
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stderr[-2000:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.split("\n\n")[0])
    p.add_argument("--medium", default="M2", choices=sorted(MEDIA))
    p.add_argument("--estimator", default="exits", choices=["exits", "connections"])
    p.add_argument("--photons", type=int, default=16_000_000, help="photons of the job (default 16e6)")
    p.add_argument("--shards", type=int, default=8, help="shards of the job (default 8)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)

    bssrdf = [sys.executable, "-m", "service.cli"]
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bssrdf-bench-run-") as tmp:
        root = Path(tmp)
        spec = root / "spec.json"
        warm = root / "warm.json"
        spec.write_text(json.dumps(_spec_doc(args.medium, args.estimator, args.photons, args.shards)))
        # Warm-up: two shards as large as the job's (up to 2e6 photons), so that every kernel
        # shape the timed runs use (they depend on the lanes per shard) is compiled beforehand.
        warm.write_text(json.dumps(_spec_doc(args.medium, args.estimator, 2 * min(args.photons // args.shards, 2_000_000), 2)))
        _timed(bssrdf + ["simulate", str(warm), "--out", str(root / "warm"), "--json", "--workers", "2"], root)
        runs = [
            ("simulate_1", ["simulate", str(spec), "--out", str(root / "s1"), "--json", "--workers", "1", "--no-progress"]),
            ("simulate_2", ["simulate", str(spec), "--out", str(root / "s2"), "--json", "--workers", "2", "--no-progress"]),
            ("run_1", ["run", str(spec), "--json", "--workers", "1", "--data-dir", str(root / "d1")]),
            ("run_2", ["run", str(spec), "--json", "--workers", "2", "--data-dir", str(root / "d2")]),
        ]
        for name, cmd in runs:
            wall = _timed(bssrdf + cmd, root)
            results[name] = {"wall_s": wall, "photons_per_s": args.photons / wall}
            if not args.json:
                print(f"{name:<11} {wall:8.1f} s  {args.photons / wall:10.4g} photons/s", flush=True)
    ratios = {
        "run_2_over_run_1": results["run_2"]["photons_per_s"] / results["run_1"]["photons_per_s"],
        "simulate_2_over_simulate_1": results["simulate_2"]["photons_per_s"] / results["simulate_1"]["photons_per_s"],
        "run_1_over_simulate_1": results["run_1"]["photons_per_s"] / results["simulate_1"]["photons_per_s"],
        "run_2_over_simulate_2": results["run_2"]["photons_per_s"] / results["simulate_2"]["photons_per_s"],
    }
    if args.json:
        print(json.dumps({"runs": results, "ratios": ratios, "photons": args.photons, "shards": args.shards,
                          "medium": args.medium, "estimator": args.estimator}, sort_keys=True))
    else:
        for k, v in ratios.items():
            print(f"{k:<28} {v:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
