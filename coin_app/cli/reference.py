"""``evaluate-reference``: the COIN authors' released actors by their evaluation protocol, natively and on MetaDrive."""

from __future__ import annotations

import argparse
import shlex
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
    settings = {
        "command": _command(getattr(args, "command_line", "")),
        "scenes": list(args.scenes),
        "backends": list(args.backends),
        "episode_seeds": episode_seeds(args.episodes),
    }
    say = (lambda line: print(line, file=sys.stderr, flush=True)) if progress else None
    results = run_reference(tasks, out, args.workers, say, settings)
    paths = write_tables(results, out, settings)
    print(to_markdown(summary_table(results)))
    print("wrote " + ", ".join(str(p) for p in paths) + f" and {out / 'results.csv'} (one row per episode)")
    return 0


def _command(line: str) -> str:
    """The command line without the options that do not change the results (``--workers``, ``--progress``)."""
    words = shlex.split(line)
    kept = [
        w
        for k, w in enumerate(words)
        if w not in ("--workers", "--progress") and (k == 0 or words[k - 1] not in ("--workers", "--progress"))
    ]
    return shlex.join(kept)


__all__ = ["BACKENDS", "cmd_evaluate_reference"]
