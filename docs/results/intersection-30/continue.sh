# The dense comparisons, continued wherever they stand (docs/results/intersection-30/README.md):
#   bash docs/results/intersection-30/continue.sh            # from the repository root; runs until stopped
# The scenes in turn (the intersection, then the roundabout and the bottleneck: issue 57's item 6). Two lanes, one per
# core, each taking the next method no lane is running (a lock per sweep). Each method of a scene is one sweep
# (`sweep seeds --scale dense --scenario SCENE --algos METHOD`) of the seeds not yet archived, run by the code of the
# scene's commit (every trial of a comparison by the same code: the archive refuses another), resumed with --resume
# where its directory exists. Every 10 minutes the finished trials are archived into each scene's trials/ (python -m
# coin_app archive), which is what gets committed.
set -uo pipefail
cd "$(dirname "$0")/../../.."
SCENES=(${SCENES:-intersection roundabout bottleneck})
RUNS=${RUNS:-../runs}                      # sweeps, logs: outside git
PY=${PY:-$PWD/.venv/bin/python}
# Ray starts its workers (the trials) 15 nicer than their driver, i.e. at 19 under the lanes' nice 10, level with the
# report's evaluation (README, "The report, across sessions"); 0 keeps them at the lanes' 10, ahead of it
export RAY_worker_niceness=${RAY_worker_niceness:-0}
METHODS=(cig_td3 itd3 traco ippo cppo mfpo copo)
mkdir -p "$RUNS"
RUNS=$(cd "$RUNS" && pwd)

code() {  # the commit every trial of scene $1 runs (the one its first trials ran)
  case $1 in
    intersection) echo "${CODE_INTERSECTION:-ba6517f}" ;;
    *) echo "${CODE_SCENES:-d15ca9b}" ;;  # the native fixes of 2026-12-03 and every learner's fused gradient step (2026-12-04)
  esac
}
archive() {  # where scene $1's finished trials are committed
  case $1 in
    intersection) echo docs/results/intersection-30/trials ;;
    roundabout) echo docs/results/roundabout-40/trials ;;
    bottleneck) echo docs/results/bottleneck-20/trials ;;
  esac
}
storage() { [ "$1" = intersection ] && echo "$RUNS/sweeps" || echo "$RUNS/sweeps-$1"; }
sweep_name() { [ "$1" = intersection ] && echo "dense-$2" || echo "dense-$1-$2"; }
worktree() {  # a checkout of scene $1's commit
  local rev dir
  rev=$(git rev-parse --short "$(code "$1")")
  dir=${WORKTREE_ROOT:-..}/wt-dense-$rev
  [ "$1" = intersection ] && [ -z "${WORKTREE_ROOT:-}" ] && dir=../wt-dense
  [ -d "$dir" ] || git worktree add --detach "$dir" "$rev" >&2
  (cd "$dir" && pwd)
}

remaining() {  # the seeds 0..4 of sweep $2 not archived yet in $1
  "$PY" - "$1/$2/coin_archive.json" "$3" <<'PY'
import json, sys
from pathlib import Path
path, algo = Path(sys.argv[1]), sys.argv[2]
done = json.loads(path.read_text())["trials"] if path.is_file() else {}
print(" ".join(str(s) for s in range(5) if f"{algo}-s{s}" not in done))
PY
}

lane() {  # every scene's methods one after another, skipping any another lane holds
  for scene in "${SCENES[@]}"; do
    wt=$(worktree "$scene")
    store=$(storage "$scene")
    mkdir -p "$store"
    for algo in "$@"; do
      name=$(sweep_name "$scene" "$algo")
      seeds=$(remaining "$(archive "$scene")" "$name" "$algo")
      [ -z "$seeds" ] && continue
      if [ -f "$store/$name/coin_sweep.json" ]; then args=(--resume); else args=(--seeds $seeds); fi
      (cd "$wt" && PYTHONPATH="$wt" PYTHONHASHSEED=0 OMP_NUM_THREADS=1 flock -n -E 75 "$RUNS/.lock-$name" \
        nice -n 10 "$PY" -m coin_app sweep seeds --scale dense --scenario "$scene" \
        --algos "$algo" --name "$name" --storage "$store" --max-concurrent 1 --num-cpus 1 "${args[@]}")
    done
  done
}

lane "${METHODS[@]}" >> "$RUNS/dense-lane1.log" 2>&1 &
sleep 20
lane ippo "${METHODS[@]}" >> "$RUNS/dense-lane2.log" 2>&1 &
while true; do
  sleep 600
  for scene in "${SCENES[@]}"; do
    store=$(storage "$scene")
    [ -d "$store" ] || continue
    OMP_NUM_THREADS=1 nice -n 5 "$PY" -m coin_app archive "$store" --out "$(archive "$scene")" >> "$RUNS/archive.log" 2>&1
  done
done
