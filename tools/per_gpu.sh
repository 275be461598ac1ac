#!/usr/bin/env bash
# Several commands at once, command k on GPU k alone (CUDA_VISIBLE_DEVICES=k), each output line prefixed [gpu<k>]:
# e.g. two different studies on one 2-GPU lease, inside a device_job.sh call,
#   bash tools/device_job.sh zs bash tools/per_gpu.sh \
#     'python -m experiments.study paper ... workers=1 ...' 'python -m experiments.study ab_solver ... workers=1 ...'
# (each command one string, run by bash -c). Not `a & b & wait`: bash starts a background command with Ctrl-C
# ignored, and Python then never sees it, so at device_job.sh's time limit the runs would save no checkpoint and be
# killed 20 s later, and the shell would not wait for them. Here every command gets Ctrl-C as from a terminal (a run
# checkpoints, a study waits for its runs), the script waits for all of them, and exits with the first nonzero exit
# status in the order given (0 when all succeed).
set -o pipefail
[ $# -ge 1 ] || { echo "usage: bash tools/per_gpu.sh '<command for GPU 0>' ['<command for GPU 1>' ...]" >&2; exit 2; }
pids=()
k=0
for cmd in "$@"; do
  # the command: Ctrl-C back to its default; the prefixing sed keeps ignoring it, to pass on the last lines
  (trap - INT; export CUDA_VISIBLE_DEVICES=$k; exec bash -c "$cmd") 2>&1 | sed -u "s/^/[gpu$k] /" &
  pids+=($!)
  k=$((k + 1))
done
trap '' INT             # Ctrl-C reaches the commands (one process group with this script), which waits for them
rc=0
for p in "${pids[@]}"; do
  wait "$p"
  r=$?
  [ $rc = 0 ] && rc=$r
done
exit $rc
