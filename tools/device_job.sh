#!/usr/bin/env bash
# Work on a lent GPU machine (the workplace's `device` tool), in two steps.
#
# Here, once per checkout:   bash tools/device_job.sh prepare
#   fetches the wheels the GPU machine lacks into .whl/ (../shared/tools/gpu-wheels.sh), copies the original robots
#   (../shared/unimals_100) into .gpu/ and searches their self-collision pairs into .gpu/pairs (the train, val, test70
#   and variants sets: ~1 minute on 2 cores, which the GPU host's env builds then skip; they are read only by the
#   same version of mjx_morph/sim/selfcontact.py, so rerun `prepare` after a change to it): both git-ignored, both carried (carry: [".whl", ".gpu"]).
# There, in every call:      bash tools/device_job.sh <name> <command ...>
#   (within DEVICE_JOB_LIMIT_S, default 560 s of the call's 600, at most 570: then Ctrl-C, so that a run saves a
#   checkpoint; a command still running 20 s later is killed, and packing its artefacts takes the last seconds; or
#   earlier, at DEVICE_JOB_UNTIL_S seconds after the machine's first call: the lease's clock, below)
#   installs the wheels, points the robots at .gpu/unimals_100, runs the command (XLA's W/I log lines dropped) with
#   its output in $OUT/<name>.log, then packs the small artefacts of every run under runs/ (config, metrics.csv,
#   eval/*.json; no checkpoints) into $OUT/<name>-runs.tar.gz: `tar xzf <it> -C results/` unpacks a study's runs
#   here as results/<study>/<run>/. With DEVICE_JOB_SAVE_XLA=1 it also packs JAX's compilation cache (the training
#   programs first; this lease's, then those carried in that it read) into $OUT/xla-cache.tar.gz (at most 15 MiB);
#   copied to .gpu/ here, a fresh machine's first call starts from it (tools/xla_cache.py).
# Example (three calls back to back: a machine left idle 30 s goes back, with runs/ and its checkpoints; so send
# the chain's calls together, as one batch of tool calls that run one after another a few seconds apart: session 31
# sent each after reading the last one's reply and lost two chains so, one on 4 GPUs and one on 1, ~1000 of its
# 1800 counted s):
#   bash tools/device_job.sh fp32 python -m experiments.study ab_precision 'only=[fp32]' 'archs=[modumorph]' \
#     'seeds=[0,1]' time_limit_min=8.7 -- progress=false
#   bash tools/device_job.sh --continue fp32 python -m experiments.study ...    # the second and third calls
# --continue stops at once (exit status 3) on a machine without runs/: the chain broke, and the command would
# start the runs again from nothing. Different commands one per GPU (say two studies): `bash tools/device_job.sh zs
# bash tools/per_gpu.sh '<command>' '<command>'`, never `bash -c 'a & b & wait'` (see tools/per_gpu.sh).
set -o pipefail
if [ "$1" = prepare ]; then
  [ -d ../shared ] || { echo "../shared is missing: clone the project beside it" >&2; exit 2; }
  ls .whl/*.whl >/dev/null 2>&1 || ../shared/tools/gpu-wheels.sh || exit 1
  # what the GPU host never reads stays here, room for the carried cache (tools/slim_wheels.py): mujoco-studio and
  # pyopengl whole (rendering alone), MJX's own test robots from mujoco-mjx's wheel (6.2 MiB)
  python3 "$(dirname "$0")/slim_wheels.py" .whl || exit 1
  [ -d .gpu/unimals_100 ] || { mkdir -p .gpu && cp -r ../shared/unimals_100 .gpu/; } || exit 1
  py=python3; [ -x .venv/bin/python ] && py=.venv/bin/python
  rm -rf .gpu/pairs      # the searches of an earlier version of selfcontact.py are never read again: not carried
  MJX_MORPH_PAIR_CACHE=$PWD/.gpu/pairs MJX_MORPH_UNIMALS=$PWD/.gpu/unimals_100 $py -c '
import time
from mjx_morph.sim.selfcontact import robots_pairs
from mjx_morph.unimal.sets import load_set
if __name__ == "__main__":      # the search processes are spawned: they import this file
    for name in ("unimal100/train", "unimal100/val", "unimal100/test70", "unimal100/train/variants"):
        t = time.perf_counter(); robots = load_set(name).robots; robots_pairs(robots)
        print(f"self-collision pairs of {name} ({len(robots)} robots): {time.perf_counter() - t:.1f} s")
' || exit 1
  du -shc .whl .gpu | tail -1 | sed 's/total/to carry (64 MiB at most with the checkout)/'
  exec bash "$0" fit
fi
# Here, after copying a lease's xla-cache.tar.gz to .gpu/:   bash tools/device_job.sh fit
#   A call takes at most 64 MiB: the checkout's files (tracked and untracked-not-ignored) and the carried .whl and .gpu.
#   The checkout grows with every session's results; the carried compilation cache is what gives way: fit keeps its
#   first (most useful) programs within the room the rest leaves (tools/xla_cache.py, `room_mb`); those that give way
#   go to the overflow, .xla/xla-cache.tar.gz (git-ignored), which the next lease's first call carries alone:
#   `bash tools/device_job.sh place .xla` (carry: [".xla"]) unpacks it on the machine.
if [ "$1" = fit ]; then
  cache=.gpu/xla-cache.tar.gz
  [ -f $cache ] || { echo "[device_job] no $cache: nothing to fit"; exit 0; }
  { git ls-files -z; git ls-files -z --others --exclude-standard; find .whl .gpu -type f ! -path $cache -print0 2>/dev/null; } |
    python3 "$(dirname "$0")/xla_cache.py" fit $cache .xla/xla-cache.tar.gz
  exit "${PIPESTATUS[1]}"      # fit's own (find fails where .whl is missing, which changes nothing)
fi
# Here, after a lease:   bash tools/device_job.sh home results/<study>_s<session> <files_at> [<files_at> ...]
#   (the calls' folders in the order they ran): the runs of the last call that brought any into the results folder
#   (new: nothing on file is overwritten), each call's log as call<k>.log, the newest compilation cache into .gpu/
#   (then fit), and the runs' Returns, Rates and Health tables (tools/bring_home.py).
if [ "$1" = home ]; then
  [ $# -ge 3 ] || { echo "usage: bash tools/device_job.sh home <results folder> <files_at> [<files_at> ...]" >&2; exit 2; }
  shift
  py=python3; [ -x .venv/bin/python ] && py=.venv/bin/python
  $py "$(dirname "$0")/bring_home.py" "$@" || exit $?
  exec bash "$0" fit
fi
# Moving an unfinished run to the next session's machine (tools/move_runs.py; packed: MetaMorph 36 MiB, R-MeMo 86):
#   there, in the lease's last call: DEVICE_JOB_MOVE_OUT="<run dir> ..." (runs/studies/<study>/<run>, several
#     separated by spaces) packs each run's newest checkpoint into outgoing/move.<study>.<run>.tar.gz.000, .001,
#     ... (15 MiB each) and sends the first parts back in $OUT, as many as fit beside the log, the runs and a cache
#     (a call brings back at most 8 files, 64 MiB);
#     `bash tools/device_job.sh send` (carry nothing), a call each, sends the next ones, up to four a call;
#   here: python3 tools/move_runs.py stage <files_at> [<files_at> ...] .mv   (folders .mv1, .mv2, ... of two parts
#     each, once every part is here);
#   there, the next lease's first calls, one per folder: bash tools/device_job.sh place .mv1   (carry: [".mv1"]),
#     which keeps the parts in moving/ on the machine; then every later call puts the run back before its command
#     (exit status 4, nothing run, where parts are missing or corrupt), and the study resumes it.
# The lease's clock: a machine's first call (`place`, `send` or a command) notes the time in .lease-start, which stays
# on the warm machine (git-ignored, like runs/) and goes back with it. DEVICE_JOB_UNTIL_S=<s> interrupts the command
# that many seconds after that first call (or at DEVICE_JOB_LIMIT_S, where that comes first): a batch's last call then
# spends what the calls before it left, however long they ran. The lease counts more than the clock: <s> = the budget
# left in the first call's reply less ~110 s (a call ended on the clock replied 37-38 s later, its run saved and
# packed, in sessions 67-69; then a `send` or two, none where the parts fit the call: session 69). Where the machine
# came at the first try, the budget left before the batch less ~160 s is the same (session 67: the first call came
# 85 s into the lease); failed starts before it (session 68: 182 s) are not on the clock, so count from the first
# call's reply. Every call logs the clock.
[ -f .lease-start ] || date +%s > .lease-start
need_out() { [ -n "$OUT" ] || { echo "\$OUT is not set: run this through the device tool" >&2; exit 2; }; }
# JAX's compilation cache on the machine (`place .xla` and every command's call unpack into it; below)
export MJX_MORPH_XLA_CACHE=${MJX_MORPH_XLA_CACHE:-$HOME/.cache/mjx_morph/xla}
if [ "$1" = place ]; then
  [ $# -eq 2 ] || { echo "usage: bash tools/device_job.sh place <folder of parts>" >&2; exit 2; }
  if [ -f "$2/xla-cache.tar.gz" ]; then      # the cache's overflow (fit, here): into the cache before any training
    exec python3 "$(dirname "$0")/xla_cache.py" unpack "$2/xla-cache.tar.gz" "$MJX_MORPH_XLA_CACHE"
  fi
  exec python3 "$(dirname "$0")/move_runs.py" place "$2" moving
fi
if [ "$1" = send ]; then
  [ $# -eq 1 ] || { echo "usage: bash tools/device_job.sh send" >&2; exit 2; }
  need_out
  [ -d outgoing ] || { echo "[device_job] send: no outgoing/ here: nothing was packed on this machine (a fresh" \
                         "machine: the one that packed the run went back, and its parts with it)" >&2; exit 3; }
  exec python3 "$(dirname "$0")/move_runs.py" send outgoing "$OUT"
fi
continuing=0
[ "$1" = --continue ] && { continuing=1; shift; }
[ $# -ge 2 ] || { echo "usage: bash tools/device_job.sh prepare | [--continue] <name> <command ...>" >&2; exit 2; }
need_out
name=$1; shift
if [ -d moving ]; then          # parts that `place` kept: the moved runs back under runs/studies before the command
  python3 "$(dirname "$0")/move_runs.py" assemble moving runs/studies || exit 4
fi
if [ $continuing = 1 ] && [ ! -d runs ]; then
  echo "[device_job] $name: --continue, but runs/ is not here: this is a fresh machine (the warm one went back, and" \
       "the runs of the earlier calls with it). Nothing was run; the device time left is better spent otherwise." >&2
  exit 3
fi
# Ctrl-C at the limit, kill 20 s later (a jitted evaluation sweep does not stop mid-chunk), then ~5 s to pack: a limit
# above 570 s lets the device tool kill the whole call at 600 s, and then no file comes back (session 20 lost a call's
# evaluations and metrics that way, with DEVICE_JOB_LIMIT_S=588)
most=570
limit=${DEVICE_JOB_LIMIT_S:-560}
[[ "$limit" =~ ^[0-9]+$ ]] || { echo "DEVICE_JOB_LIMIT_S=$limit: expected whole seconds (default 560, at most $most)" >&2; exit 2; }
if [ "$limit" -gt $most ]; then
  echo "[device_job] DEVICE_JOB_LIMIT_S=$limit leaves too little of the call's 600 s to stop and pack: $most used" >&2
  limit=$most
fi
until_s=${DEVICE_JOB_UNTIL_S:-}
[ -z "$until_s" ] || [[ "$until_s" =~ ^[0-9]+$ ]] ||
  { echo "DEVICE_JOB_UNTIL_S=$until_s: expected whole seconds after the machine's first call" >&2; exit 2; }
site=${DEVICE_JOB_SITE:-/tmp/site}      # where the carried wheels install (a test points it elsewhere)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
  || { echo "the wheels did not install: carry .whl (bash tools/device_job.sh prepare)" >&2; exit 1; }
export PYTHONPATH=$site:$PWD PYTHONUNBUFFERED=1
[ -d .gpu/unimals_100 ] && export MJX_MORPH_UNIMALS=$PWD/.gpu/unimals_100
# JAX's compilation cache: a fresh machine starts from the programs an earlier lease brought back (DEVICE_JOB_SAVE_XLA=1
# packs them into $OUT/xla-cache.tar.gz; copy it to .gpu/ here), which serve where the GPU model and code are the same
# (--continue calls too where this machine has not unpacked it yet: the first training call after `place` calls is
# one, and `place .xla` may have made the cache already)
if [ -f .gpu/xla-cache.tar.gz ] && { [ $continuing = 0 ] || [ ! -f "$MJX_MORPH_XLA_CACHE.gpu-unpacked" ]; }; then
  python3 tools/xla_cache.py unpack .gpu/xla-cache.tar.gz "$MJX_MORPH_XLA_CACHE" &&
    touch "$MJX_MORPH_XLA_CACHE.gpu-unpacked"
fi
if [ -d .gpu/pairs ]; then      # the searches `prepare` made (read only if selfcontact.py has not changed since)
  export MJX_MORPH_PAIR_CACHE=$PWD/.gpu/pairs
  echo "[device_job] $(ls .gpu/pairs | wc -l) self-collision pair searches kept in .gpu/pairs"
fi
nvidia-smi --query-gpu=index,name,memory.used --format=csv,noheader
# the device tool kills a call at its limit (600 s) and nothing comes back from a killed call: interrupt the command
# first (Ctrl-C: a run saves a checkpoint, a study waits for its workers to), leaving time to bring the artefacts home
left=$(( limit - SECONDS ))
held=$(( $(date +%s) - $(cat .lease-start) ))
echo "[device_job] $name: the machine's first call began $held s ago" | tee "$OUT/$name.log"
stop="after $limit s of the call (DEVICE_JOB_LIMIT_S)"
if [ -n "$until_s" ] && [ $(( until_s - held )) -lt $left ]; then
  left=$(( until_s - held )); stop="$until_s s after the machine's first call (DEVICE_JOB_UNTIL_S)"
fi
if [ $left -gt 0 ]; then      # (`timeout 0` would never stop it)
  timeout -s INT -k 20 $left "$@" 2>&1 | grep -v --line-buffered "^[WI]0000 " | tee -a "$OUT/$name.log"
  rc=${PIPESTATUS[0]}
else
  echo "[device_job] $name: no time left before $stop: the command was not run" | tee -a "$OUT/$name.log"; rc=124
fi
[ $rc -eq 124 ] && [ $left -gt 0 ] && echo "[device_job] $name: interrupted $stop"
ended=$SECONDS      # what follows (the runs' artefacts, the cache, a move's parts) is timed: it must end by 600 s
dirs=$(ls -d runs/studies/* runs/* 2>/dev/null | grep -vx runs/studies | paste -sd, -)   # a study's runs: <study>/<run>
[ -n "$dirs" ] && python3 -m experiments.collect "runs=[$dirs]" out="$OUT/$name-runs.tar.gz" 2>&1 | tail -1
[ "${DEVICE_JOB_SAVE_XLA:-0}" = 1 ] && python3 tools/xla_cache.py pack "$MJX_MORPH_XLA_CACHE" "$OUT/xla-cache.tar.gz"
for run in ${DEVICE_JOB_MOVE_OUT:-}; do   # an unfinished run to move (above): its newest checkpoint in 15-MiB parts
  move=$(python3 tools/move_runs.py name "$run") &&
    python3 -m experiments.collect "runs=[$run]" out="outgoing/$move" checkpoint=true part_mb=15 2>&1 | tail -1
done
[ -n "${DEVICE_JOB_MOVE_OUT:-}" ] && python3 tools/move_runs.py send outgoing "$OUT"   # the rest: `send` calls
echo "[device_job] $name: exit status $rc; packed in $(( SECONDS - ended )) s, $SECONDS s into the call" |
  tee -a "$OUT/$name.log"
exit $rc
