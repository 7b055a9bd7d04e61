"""``evaluate-reference``: the COIN authors' released actors by their evaluation protocol, natively and on MetaDrive."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from coin_app.evaluation.reference import BACKENDS, episode_seeds, plan, run_reference, summary_table, to_markdown, write_tables
from coin_app.inference.coin_actors import actors_root


def cmd_evaluate_reference(args: argparse.Namespace) -> int:
    """Evaluate the authors' actors (resuming ``--out``), then write and print the reference table."""
    root = actors_root(args.actors)
    tasks = plan(root, args.scenes, args.backends, args.seeds, args.episodes)
    out = Path(args.out)
    progress = args.progress == "always" or (args.progress == "auto" and sys.stderr.isatty())
    results = run_reference(tasks, out, args.workers, (lambda line: print(line, file=sys.stderr, flush=True)) if progress else None)
    settings = {
        "command": getattr(args, "command_line", ""),
        "scenes": list(args.scenes),
        "backends": list(args.backends),
        "episode_seeds": episode_seeds(args.episodes),
    }
    paths = write_tables(results, out, settings)
    print(to_markdown(summary_table(results)))
    print("wrote " + ", ".join(str(p) for p in paths) + f" and {out / 'results.csv'} (one row per episode)")
    return 0


__all__ = ["BACKENDS", "cmd_evaluate_reference"]
