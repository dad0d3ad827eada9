"""A client host's part of the multi-host test (tests/service/test_multihost.py), run on its
namespace: submit a spec over HTTP, follow the job to its end through API restarts and database
outages, download the version's tables, read the metrics; write what it saw as JSON.

    python -m tests.support.netns_client BASE_URL TOKEN SPEC.json OUT_DIR TIMEOUT_S

OUT_DIR/result.json: ``job`` (the last answer of GET /v1/jobs/{id}), ``unreachable`` (polls
with no answer: the API was down), ``statuses`` (count per HTTP status of the polls; 503 while
the database restarts), ``files`` (downloaded names), ``metrics`` (the /metrics text at the end).
"""

from __future__ import annotations

import json
import sys
import time
from collections import Counter
from pathlib import Path

import httpx

TABLES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")


def _retry(call, deadline: float, seen: Counter):
    """``call()`` until it answers something other than an outage (no answer, 502-504)."""
    while True:
        try:
            r = call()
            seen[r.status_code] += 1
            if r.status_code not in (502, 503, 504):
                return r
        except httpx.TransportError:
            seen["unreachable"] += 1
        if time.monotonic() > deadline:
            raise TimeoutError("the API did not answer in time")
        time.sleep(0.3)


def main(base: str, token: str, spec_file: str, out_dir: str, timeout: float) -> int:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + timeout
    seen: Counter = Counter()
    http = httpx.Client(base_url=base, timeout=10, headers={"Authorization": f"Bearer {token}"})
    spec = json.loads(Path(spec_file).read_text())
    r = _retry(lambda: http.post("/v1/jobs", json={"spec": spec}, headers={"Idempotency-Key": spec["name"]}),
               deadline, seen)
    assert r.status_code in (200, 201), r.text
    job = r.json()
    while job["state"] not in ("succeeded", "failed", "cancelled") and time.monotonic() < deadline:
        time.sleep(0.5)
        r = _retry(lambda: http.get(f"/v1/jobs/{job['id']}"), deadline, seen)
        assert r.status_code == 200, r.text
        job = r.json()
    files = []
    if job["state"] == "succeeded":
        for name in TABLES:
            r = _retry(lambda: http.get(f"/v1/datasets/{job['dataset_name']}/versions/{job['dataset_version']}"
                                        f"/files/{name}"), deadline, seen)
            assert r.status_code == 200, r.text
            (out / name).write_bytes(r.content)
            files.append(name)
    metrics = _retry(lambda: http.get("/metrics"), deadline, seen).text
    (out / "result.json").write_text(json.dumps({
        "job": job, "unreachable": seen.pop("unreachable", 0), "statuses": {str(k): v for k, v in seen.items()},
        "files": files, "metrics": metrics}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], float(sys.argv[5])))
