#!/usr/bin/env bash
# One shard of the woven training set, for a cluster array job (see datagen/README.md, "On a cluster").
#
# The shard index i comes from the scheduler: WOVEN_SHARD_INDEX if set, else SLURM_ARRAY_TASK_ID
# (Slurm array job, --array=0-(K-1)), else JOB_COMPLETION_INDEX (Kubernetes Indexed Job).
# The number of shards K: WOVEN_SHARDS if set, else SLURM_ARRAY_TASK_COUNT.
# Each shard writes its own folder $WOVEN_DATA/shard-i (no shared folder needed); `woven merge`
# assembles them. Extra arguments go to `woven generate` (e.g. --recipe, --count, --threads).
# Rerunning a task resumes its shard (finished images are verified and kept).
set -euo pipefail
i="${WOVEN_SHARD_INDEX:-${SLURM_ARRAY_TASK_ID:-${JOB_COMPLETION_INDEX:-}}}"
k="${WOVEN_SHARDS:-${SLURM_ARRAY_TASK_COUNT:-}}"
if [[ -z "$i" || -z "$k" ]]; then
    echo "shard.sh: no shard index/count: set SLURM_ARRAY_TASK_ID (Slurm array), JOB_COMPLETION_INDEX + WOVEN_SHARDS (Kubernetes Indexed Job) or WOVEN_SHARD_INDEX + WOVEN_SHARDS" >&2
    exit 2
fi
if ! [[ "$i" =~ ^[0-9]+$ && "$k" =~ ^[0-9]+$ ]] || (( i >= k )); then
    echo "shard.sh: shard index $i is not in 0..$k (Slurm arrays must start at 0: --array=0-$((k - 1)))" >&2
    exit 2
fi
data="${WOVEN_DATA:?shard.sh: set WOVEN_DATA to the folder that receives shard-0 … shard-$((k - 1))}"
exec "${WOVEN:-woven}" generate --shard "$i/$k" --out "$data/shard-$i" "$@"
