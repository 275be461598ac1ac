#!/usr/bin/env bash
# Several commands at once, command k on GPU k alone (CUDA_VISIBLE_DEVICES=k), each output line prefixed [gpu<k>]:
# e.g. two different studies on one 2-GPU lease, inside a device_job.sh call,
#   bash tools/device_job.sh zs bash tools/per_gpu.sh \
#     'python -m experiments.study paper ... workers=1 ...' 'python -m experiments.study ab_solver ... workers=1 ...'
# (each command one string, run by bash -c). Not `a & b & wait`: bash starts a background command with Ctrl-C
# ignored, and Python then never sees it, so at device_job.sh's time limit the runs would save no checkpoint and be
# killed 20 s later, and the shell would not wait for them. Here every command gets Ctrl-C as from a terminal (a run
# checkpoints, a study waits for its runs), also where this script itself was started with it ignored (bash cannot
# undo that: `trap - INT` does nothing then, so a one-line Python resets it before running the command), the script
# waits for all of them, and exits with the first nonzero exit status in the order given (0 when all succeed).
# Two commands sharing one GPU (two processes, which it time-slices) ran slower together than one alone, for
# throughput-bound runs (0.96x, session 46) and for 32-env rollouts (~0.8-0.9x, session 58; docs/benchmarks.md).
set -o pipefail
[ $# -ge 1 ] || { echo "usage: bash tools/per_gpu.sh '<command for GPU 0>' ['<command for GPU 1>' ...]" >&2; exit 2; }
default_int='import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL)
os.execvp("bash", ["bash", "-c", sys.argv[1]])'
pids=()
k=0
for cmd in "$@"; do
  # the command with Ctrl-C at its default; the prefixing sed keeps ignoring it, to pass on the last lines
  (export CUDA_VISIBLE_DEVICES=$k; exec python3 -c "$default_int" "$cmd") 2>&1 | sed -u "s/^/[gpu$k] /" &
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
