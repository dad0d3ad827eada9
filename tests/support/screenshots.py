"""Screenshots of the pages for the README, taken from a real run in headless Chromium.

    bssrdf serve --port 8000 &  bssrdf worker & bssrdf worker &
    bssrdf submit examples/sweep.json --api http://127.0.0.1:8000        # prints the job id
    python -m tests.support.screenshots --api http://127.0.0.1:8000 --job JOB --out docs/images

Takes ``job-page.png`` while the job runs (once ``--at`` of its shards are done, default 40 %),
waits for it to end, then ``dataset-page.png``: the top of its dataset version's page (figures
first). Prints the browser console's errors, if any (there should be none).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import httpx

from tests.support.browser import chromium, console_errors


def _progress(api: str, job: str) -> dict:
    return httpx.get(f"{api}/v1/jobs/{job}", timeout=10).json()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--api", required=True)
    p.add_argument("--job", required=True)
    p.add_argument("--out", default="docs/images")
    p.add_argument("--at", type=float, default=0.4, help="fraction of shards done for the job page's shot")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--job-height", type=int, default=1000)
    p.add_argument("--dataset-height", type=int, default=1500)
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with chromium(args.width, args.job_height) as driver:
        driver.get(f"{args.api}/jobs/{args.job}")
        while True:  # the page updates itself; the API says when to shoot
            job = _progress(args.api, args.job)
            p = job.get("progress") or {}
            if job["state"] in ("succeeded", "failed", "cancelled") or (
                    p.get("shards_total") and p.get("shards_done", 0) >= args.at * p["shards_total"]):
                break
            time.sleep(0.5)
        driver.refresh()  # the page as of now (its script polls every two seconds)
        driver.save_screenshot(str(out / "job-page.png"))
        print("job page:", job["state"], p.get("shards_done"), "/", p.get("shards_total"))
        while job["state"] not in ("succeeded", "failed", "cancelled"):
            time.sleep(1)
            job = _progress(args.api, args.job)
        if job["state"] != "succeeded":
            print("job ended", job["state"], job.get("error"))
            return 1
        driver.set_window_size(args.width, args.dataset_height)
        driver.get(f"{args.api}/datasets/{job['dataset_name']}/versions/{job['dataset_version']}")
        time.sleep(3)  # the figures in view load
        driver.save_screenshot(str(out / "dataset-page.png"))
        print("console errors:", console_errors(driver))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
