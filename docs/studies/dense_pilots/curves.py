"""The dense pilots' figures: each run's TensorBoard events as the study's CSV, and their curves in one plot.

    python docs/studies/dense_pilots/curves.py csv ../pilots/P1h --out docs/studies/dense_pilots/P1h.csv
    python docs/studies/dense_pilots/curves.py plot docs/studies/dense_pilots/P1h.csv docs/studies/dense_pilots/P2.csv \
        --out docs/studies/dense_pilots/P1h_P2.png --budget 0.8

A CSV row is one training iteration (its env steps), with the run's CPU and wall seconds, the iteration's
training figures and, at the iterations that had one, the periodic validation evaluation's (``eval/*``), as
``train`` wrote them to TensorBoard (``tensorboard/events.out.tfevents.*`` in the run directory; several files,
one per resumed segment, are read in order, a later value of a step replacing an earlier one).
"""

from __future__ import annotations

import argparse
import csv
import struct
from pathlib import Path

COLUMNS = (
    "env_steps",
    "cpu_s",
    "wall_s",
    "eval/success_rate",
    "eval/collision_rate",
    "eval/out_of_road_rate",
    "eval/cpu_s",
    "train_success_rate",
    "train_collision_rate",
    "agents_finished",
    "mean_speed",
)


def read_events(run: Path) -> dict[int, dict[str, float]]:
    """Every scalar of ``run``'s TensorBoard event files by step (env steps): {step: {tag: value}}."""
    from tensorboardX.proto import event_pb2  # optional: tensorboardX comes with Ray; only reading needs it

    rows: dict[int, dict[str, float]] = {}
    files = sorted((run / "tensorboard").glob("events.out.tfevents.*"))
    if not files:
        raise SystemExit(f"no TensorBoard events under {run / 'tensorboard'}; allowed: a train --out directory")
    for path in files:
        data = path.read_bytes()
        i = 0
        while i + 12 <= len(data):  # TFRecord: length (8 bytes), its CRC (4), the record, the record's CRC (4)
            (n,) = struct.unpack_from("<Q", data, i)
            event = event_pb2.Event()
            event.ParseFromString(data[i + 12 : i + 12 + n])
            i += 12 + n + 4
            for v in event.summary.value:
                rows.setdefault(int(event.step), {})[v.tag] = float(v.simple_value)
    return rows


def write_csv(run: Path, out: Path) -> int:
    """Write ``run``'s iterations as the study's CSV; the number of rows written."""
    rows = read_events(run)
    with out.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for step in sorted(rows):
            r = rows[step]
            if "cpu_s" not in r:  # an iteration's figures come together; a lone tag (e.g. the first step's) is skipped
                continue
            w.writerow([step, *(f"{r[c]:.6g}" if c in r else "" for c in COLUMNS[1:])])
    return sum(1 for s in rows if "cpu_s" in rows[s])


def plot(csvs: list[Path], out: Path, budget: float | None) -> None:
    """Validation success against CPU hours and against env steps, one line per CSV (its file name)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for path in csvs:
        with path.open() as f:
            ev = [r for r in csv.DictReader(f) if r["eval/success_rate"]]
        steps = [int(r["env_steps"]) for r in ev]
        hours = [float(r["cpu_s"]) / 3600 for r in ev]
        success = [float(r["eval/success_rate"]) for r in ev]
        axes[0].plot(hours, success, marker="o", label=path.stem)
        axes[1].plot(steps, success, marker="o", label=path.stem)
    if budget:
        axes[0].axvline(budget, color="grey", ls="--", lw=1, label=f"budget {budget} CPU h")
    axes[0].set_xlabel("CPU hours (the run's process tree)")
    axes[1].set_xlabel("env steps")
    axes[0].set_ylabel("validation success (5 seeds, deterministic)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main() -> None:
    """The two commands of the module's doc."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("csv", help="a run's TensorBoard events as the study's CSV")
    c.add_argument("run", type=Path)
    c.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("plot", help="validation success against CPU hours and env steps")
    p.add_argument("csvs", type=Path, nargs="+")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--budget", type=float, help="CPU hours to mark")
    args = ap.parse_args()
    if args.cmd == "csv":
        print(f"{write_csv(args.run, args.out)} rows -> {args.out}")
    else:
        plot(args.csvs, args.out, args.budget)
        print(f"plot -> {args.out}")


if __name__ == "__main__":
    main()
