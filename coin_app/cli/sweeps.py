"""``sweep``, ``generalize``, ``archive`` and ``report``: Tune sweeps of the paper's experiments and the report made from them."""

from __future__ import annotations

import argparse
from pathlib import Path

from coin_app.cli.flags import overrides_of
from coin_app.evaluation.archive import STATUS_FILE, archive_sweep, archive_table
from coin_app.evaluation.arena_report import PAGE as ARENA_PAGE
from coin_app.evaluation.arena_report import is_arena_eval, load_arena_eval, write_arena_html
from coin_app.evaluation.episode_cache import DEFAULT_DIR as CACHE_DIR
from coin_app.evaluation.outputs import OutputLock, check_dir_output, staged_outputs, write_text_atomic
from coin_app.evaluation.report import ReportOptions, build_report, gather
from coin_app.evaluation.sweep_results import sweep_dirs
from tuning.sweep import run_sweep, write_generalization


def sweep_scale(scale: str | None, smoke: bool) -> str:
    """The scale asked for by ``--scale`` and ``--smoke`` (default paper); a ValueError when they disagree."""
    if smoke and scale not in (None, "smoke"):
        raise ValueError(f"--smoke with --scale {scale}; allowed: one of them (--smoke is --scale smoke)")
    return "smoke" if smoke else scale or "paper"


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run or resume a Tune sweep of one paper experiment; print where results went and each trial's figures."""

    summary = run_sweep(
        args.experiment,
        scenario=args.scenario,
        scale=sweep_scale(args.scale, args.smoke),
        methods=tuple(args.algos) if args.algos else None,
        seeds=tuple(args.seeds) if args.seeds else None,
        steps=args.steps,
        overrides=overrides_of(args.set),
        storage=args.storage,
        name=args.name,
        address=args.address,
        max_concurrent=args.max_concurrent,
        resume=args.resume,
        restart=tuple(args.restart),
        num_cpus=args.num_cpus,
        command=getattr(args, "command_line", None),
        wandb_project=args.wandb,
        mlflow_uri=args.mlflow,
        accept_changes=args.accept_changes,
        connect_timeout=args.connect_timeout,
    )
    print(f"\nsweep summary: {summary['experiment_dir']} ({summary['wall_s']:.0f} s, {summary['errors']} errored trials)")
    for t in summary.get("trials", []):
        state = "done" if t["finished"] else "UNFINISHED"
        print(
            f"  {t['name']:<28} {state:<10} env steps {t['env_steps']:>9}  train success {t['train_success_rate']:.3f}  "
            f"eval success {t['eval_success_rate']:.3f}  {t['checkpoint']}"
        )
    if "generalization_csv" in summary:
        print(f"  generalization table: {summary['generalization_csv']}")
    unfinished = [t["name"] for t in summary.get("trials", []) if not t["finished"]]
    if summary["errors"] or unfinished:
        print(f"  not finished: {', '.join(unfinished) or summary['errors']}; continue with --resume")
        return 1
    return 0


def cmd_generalize(args: argparse.Namespace) -> int:
    """Evaluate every final checkpoint of a sweep at each agent count; write the tidy generalization CSV."""

    out = write_generalization(Path(args.experiment_dir), counts=args.counts, test_seeds=args.test_seeds)
    print(f"generalization table: {out}")
    return 0


def cmd_archive(args: argparse.Namespace) -> int:
    """Archive every finished trial of the sweeps given under ``--out``; print what was added and what was left out."""
    out = Path(args.out)
    sweeps = [d for p in args.sweeps for d in sweep_dirs(Path(p))]  # every path checked before any write
    check_dir_output(out, sweeps, what="a sweep it archives")
    with OutputLock(out, getattr(args, "command_line", None), "the archive directory"):
        records = [archive_sweep(d, out, args.validation_episodes, tuple(args.modules)) for d in sweeps]
        write_text_atomic(out / STATUS_FILE, archive_table(out))
    added = sum(len(r["added"]) for r in records)
    print(f"\narchive summary: {added} trial(s) added to {out}, {sum(len(r['trials']) for r in records)} archived in all")
    print(f"  every archived trial's cost and validation scores: {out / STATUS_FILE}")
    for r in records:
        print(f"  {r['path']}: {len(r['trials'])} trial(s), {r['bytes'] / 1e6:.1f} MB; not yet: {', '.join(r['left_out']) or 'none'}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Evaluate sweeps (or read results) and write the paper's tables, tests, figures and report.html."""

    options = ReportOptions(
        method=args.method,
        counts=tuple(args.counts) if args.counts else None,
        test_seeds=args.test_seeds,
        workers=args.workers,
        alpha=args.alpha,
        tsne_samples=args.tsne_samples,
        tsne_episodes=args.tsne_episodes,
        transfer=args.transfer,
        transfer_test_seeds=args.transfer_test_seeds,
        select=args.select,
        validation_episodes=args.validation_episodes,
        reference_actors=args.reference_actors,
        cache=None if args.no_cache else str(args.cache or Path(args.out) / CACHE_DIR),
        command=getattr(args, "command_line", None),
    )
    arena = [Path(p) for p in args.sources if is_arena_eval(p)]  # evaluate-arena outputs: the arena page
    sweeps = [Path(p) for p in args.sources if not is_arena_eval(p)]
    out = Path(args.out)
    options.check()
    check_dir_output(out, [p for p in map(Path, args.sources) if p.is_dir()], what="a sweep it reads")
    sources = gather(sweeps) if sweeps else None  # a bad source is refused before anything is written
    # one writer; the old report's files stay whole until the new ones are complete (other files in --out stay)
    with OutputLock(out, options.command, "the report directory") as lock, staged_outputs(out) as stage:
        if lock.stale_note():
            print(lock.stale_note())
        if arena:
            page = write_arena_html(stage / ARENA_PAGE, [load_arena_eval(p) for p in arena], options.command)
            print(f"arena report: {len(arena)} evaluate-arena run(s) -> {out / page.name}")
        summary = build_report(sources, stage, options, shown_as=out) if sources else None
    if summary is None:
        return 0
    print(f"\nreport summary: {summary['episodes']} test episodes of {summary['models']} models in {summary['wall_s']:.0f} s -> {out}")
    for key, value in summary["success"].items():
        print(f"  success {key:<40} {100 * value:6.2f} %")
    drawn = [k for k, v in summary["figures"].items() if not v.startswith("not drawn")]
    print(f"  figures: {len(drawn)} of {len(summary['figures'])} drawn; page: {out / 'report.html'}")
    for name, value in summary["figures"].items():
        if value.startswith("not drawn"):
            print(f"    {name}: {value}")
    for f in summary["failures"]:
        where = f" on {f['backend']}" if f.get("backend") else ""
        print(f"  NOT EVALUATED{where} {f.get('trial') or f.get('checkpoint')}: {f['error']}")
    for f in summary.get("unreadable", []):
        print(f"  UNREADABLE {f['path']}: {f['error']} (left out of the learning curves)")
    return 1 if summary["failures"] or summary.get("unreadable") else 0
