"""Subprocess of the claim race test: claim and complete until nothing is claimable.

    python -m tests.support.claimer URL START_AT  -> prints a JSON list of [task_id, token, kind]
"""

from __future__ import annotations

import json
import os
import sys
import time

from service.store import JobStore, TaskKind
from tests.support.files import stored


def main(url: str, start_at: float) -> None:
    store = JobStore(url, migrate=False)
    store.now()  # connect before the start line
    time.sleep(max(0.0, start_at - time.time()))
    claims = []
    idle = 0
    while idle < 3:  # merges become claimable only after the last shard: look a few times
        lease = store.claim(f"claimer-{os.getpid()}", 60)
        if lease is None:
            idle += 1
            time.sleep(0.05)
            continue
        idle = 0
        claims.append([lease.task_id, lease.token, str(lease.kind)])
        if lease.kind == TaskKind.SHARD:
            store.complete_shard(lease, stored(os.urandom(64)), photons=1, elapsed_s=0.0)
    print(json.dumps(claims))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
