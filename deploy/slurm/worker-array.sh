#!/bin/bash
# A SLURM array of bssrdf workers draining the PostgreSQL queue.
#
#   export BSSRDF_DATABASE_URL=postgresql+psycopg://user@dbhost:5432/bssrdf
#   export BSSRDF_STORAGE_URI=/shared/project/bssrdf     # a filesystem every node mounts (or s3://...)
#   export BSSRDF_KERNEL_CACHE=/shared/project/kernels   # compiled walks, shared by the fleet
#   sbatch --array=0-31 deploy/slurm/worker-array.sh [WORKER OPTIONS...]
#
# Submit once the jobs are queued: `--once` workers exit when nothing is left that could become
# claimable. sbatch passes the submitting shell's environment (its default --export=ALL), so the
# variables above, PATH (to find `bssrdf`) and any other BSSRDF_* setting reach every worker.
# Options after the script name go to every `bssrdf worker` (e.g. `--lease-seconds 120`).
# sbatch options on the command line override the #SBATCH lines below (`--cpus-per-task=2`).
#
# Each array task runs one worker per allocated CPU. `--max-tasks` bounds the work per worker.
# Stopping: 120 s before the time limit SLURM sends SIGTERM to this batch shell (`B:` in
# --signal: without it the signal goes to job steps only, and workers started from the batch
# shell never see it), whose trap forwards it to every worker. `scancel` and preemption send
# SIGTERM to every process of the allocation (shell and workers) and SIGKILL KillWait seconds
# later (30 s by default). A worker told to stop abandons its shard, releases the lease (queued
# again, not counted as a try) and exits 0; a lease it could not release (SIGKILL, node lost)
# expires and another worker redoes the shard. Results stay bit-identical either way.
# `--once` waits while a live job can still produce work (a merge waiting for shards, a retry
# backing off), so the last workers run the merge. The array task exits with the first non-zero
# worker status, so a failing worker shows as FAILED in squeue/sacct.
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
BSSRDF="${BSSRDF_COMMAND:-bssrdf}"  # e.g. `python -m service.cli` where the package is not on PATH
export OMP_NUM_THREADS=1

pids=()
signals=0
# Forward SLURM's TERM to every worker started so far. Set before the first worker starts, so a
# signal that arrives while they start is not lost (nor kills this shell and orphans them).
trap 'signals=$((signals + 1)); kill -TERM "${pids[@]}" 2>/dev/null || true' TERM
for i in $(seq 1 "${SLURM_CPUS_PER_TASK:-1}"); do
  $BSSRDF worker --once --max-tasks "$MAX_TASKS" \
    --worker-id "slurm-${SLURM_ARRAY_JOB_ID:-${SLURM_JOB_ID:-0}}-${SLURM_ARRAY_TASK_ID:-0}-$i" "$@" &
  pids+=("$!")
done
# Wait for every worker to exit. `wait` also returns when a trapped signal arrives (status > 128,
# the trap runs right after, the worker may still be running): then wait again, for the worker's
# own exit status.
set +e
status=0
for pid in "${pids[@]}"; do
  while true; do
    before=$signals
    wait "$pid"
    rc=$?
    [ "$signals" -eq "$before" ] && break
  done
  if [ "$rc" -ne 0 ] && [ "$status" -eq 0 ]; then status=$rc; fi
done
exit "$status"
