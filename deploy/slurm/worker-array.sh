#!/bin/bash
# A SLURM array of bssrdf workers draining the PostgreSQL queue.
#
#   export BSSRDF_DATABASE_URL=postgresql+psycopg://user@dbhost:5432/bssrdf
#   export BSSRDF_STORAGE_URI=/shared/project/bssrdf     # a filesystem every node mounts (or s3://...)
#   sbatch --array=0-31 deploy/slurm/worker-array.sh
#
# Each array task runs one worker per allocated CPU. `--once` exits when nothing is claimable,
# `--max-tasks` bounds the work per allocation; 120 s before the time limit SLURM sends SIGTERM to
# this batch shell (`B:` in --signal: without it the signal goes to job steps only, and workers
# started from the batch shell never see it), whose trap forwards it to every worker; each
# releases its lease, and any lease it could not release expires and is redone by another worker:
# results stay bit-identical. `--once` waits while a live job can still produce work (a merge
# waiting for shards, a retry backing off), so the last workers run the merge.
#SBATCH --job-name=bssrdf-worker
#SBATCH --cpus-per-task=4
#SBATCH --mem-per-cpu=1G
#SBATCH --time=04:00:00
#SBATCH --signal=B:TERM@120
#SBATCH --output=bssrdf-worker-%A_%a.log

set -euo pipefail
: "${BSSRDF_DATABASE_URL:?export BSSRDF_DATABASE_URL (PostgreSQL; SQLite cannot span nodes)}"
: "${BSSRDF_STORAGE_URI:?export BSSRDF_STORAGE_URI (shared filesystem path or object store URI)}"
MAX_TASKS="${BSSRDF_MAX_TASKS:-1000}"
BSSRDF="${BSSRDF_COMMAND:-bssrdf}"  # tests run the script with `python -m service.cli`
export OMP_NUM_THREADS=1

pids=()
for i in $(seq 1 "${SLURM_CPUS_PER_TASK:-1}"); do
  $BSSRDF worker --once --max-tasks "$MAX_TASKS" \
    --worker-id "slurm-${SLURM_ARRAY_JOB_ID:-0}-${SLURM_ARRAY_TASK_ID:-0}-$i" &
  pids+=("$!")
done
# Forward SLURM's TERM to every worker, then wait for them to release their leases.
trap 'kill -TERM "${pids[@]}" 2>/dev/null || true' TERM
set +e
for pid in "${pids[@]}"; do
  while kill -0 "$pid" 2>/dev/null; do wait "$pid"; done  # `wait` returns early when the trap runs
done
