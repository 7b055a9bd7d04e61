# The dense comparison, continued wherever it stands (docs/results/intersection-30/README.md):
#   bash docs/results/intersection-30/continue.sh            # from the repository root; runs until stopped
# Two lanes, one per core: the TD3 family's methods in turn, and the PPO family's. Each method is one sweep
# (`sweep seeds --scale dense --algos METHOD`) of the seeds not yet archived, run by the code of $CODE (every trial of the
# comparison by the same code: the archive refuses another), resumed with --resume where its directory exists. Every
# 10 minutes the finished trials are archived into trials/ (python -m coin_app archive), which is what gets committed.
set -uo pipefail
cd "$(dirname "$0")/../../.."
CODE=${CODE:-ba6517f}                      # the commit every trial runs (the one the first trials ran)
RUNS=${RUNS:-../runs}                      # sweeps, logs: outside git
WORKTREE=${WORKTREE:-../wt-dense}          # a checkout of $CODE
ARCHIVE=docs/results/intersection-30/trials
PY=${PY:-$PWD/.venv/bin/python}
mkdir -p "$RUNS/sweeps"
RUNS=$(cd "$RUNS" && pwd)
[ -d "$WORKTREE" ] || git worktree add --detach "$WORKTREE" "$CODE"
WORKTREE=$(cd "$WORKTREE" && pwd)

remaining() {  # the seeds 0..4 of method $1 not archived yet
  "$PY" - "$ARCHIVE/dense-$1/coin_archive.json" "$1" <<'PY'
import json, sys
from pathlib import Path
path, algo = Path(sys.argv[1]), sys.argv[2]
done = json.loads(path.read_text())["trials"] if path.is_file() else {}
print(" ".join(str(s) for s in range(5) if f"{algo}-s{s}" not in done))
PY
}

lane() {  # the methods of one lane, one after another
  for algo in "$@"; do
    seeds=$(remaining "$algo")
    [ -z "$seeds" ] && continue
    dir="$RUNS/sweeps/dense-$algo"
    if [ -f "$dir/coin_sweep.json" ]; then args=(--resume); else args=(--seeds $seeds); fi
    (cd "$WORKTREE" && PYTHONPATH="$WORKTREE" PYTHONHASHSEED=0 OMP_NUM_THREADS=1 nice -n 10 "$PY" -m coin_app sweep seeds \
      --scale dense --algos "$algo" --name "dense-$algo" --storage "$RUNS/sweeps" --max-concurrent 1 --num-cpus 1 "${args[@]}")
  done
}

lane cig_td3 itd3 traco >> "$RUNS/dense-td3.log" 2>&1 &
sleep 20
lane ippo cppo mfpo copo >> "$RUNS/dense-ppo.log" 2>&1 &
while true; do
  sleep 600
  OMP_NUM_THREADS=1 nice -n 5 "$PY" -m coin_app archive "$RUNS/sweeps" --out "$ARCHIVE" >> "$RUNS/archive.log" 2>&1
done
