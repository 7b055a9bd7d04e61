"""The argument parser of every command: names and defaults only, so that parsing imports neither Ray nor torch."""

from __future__ import annotations

import argparse
from typing import Any, NoReturn

from coin_app.algorithms.choices import ALGORITHM_NAMES, ARENA
from coin_app.evaluation.limits import CONNECT_TIMEOUT_S, MAX_EPISODES, MAX_SCENARIOS_PER_CASE, VALIDATION_EPISODES
from coin_app.sim.arena.config import GENERATORS, PROTOCOLS
from coin_app.sim.config import PRESETS
from coin_app.sim.scenes import DRIVING_SCENARIOS as DRIVING
from tuning.experiment import SCALES


class UsageError(ValueError):
    """A command line that does not parse (an unknown option or choice, a missing argument): one line, exit 2."""


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, unless its help already says it or it is a flag (default False)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        empty = action.default is None or action.default is False or action.default == [] or action.default == argparse.SUPPRESS
        if "default" in text or empty or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class DefaultsParser(argparse.ArgumentParser):
    """A command's parser whose --help shows every option's default; a parse error raises :class:`UsageError`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        """Raise the parse error as one line naming the command (``main`` prints it, exit 2)."""
        raise UsageError(f"{self.prog.removeprefix('python -m coin_app').strip() or 'coin_app'}: {message} (see --help)")


def add_set(parser: argparse.ArgumentParser, text: str) -> None:
    """The ``--set KEY=VALUE ...`` option; repeated ``--set`` groups add up (one key with two values is refused later)."""
    parser.add_argument(
        "--set", nargs="*", action="extend", default=[], metavar="KEY=VALUE", help=f"{text}; --set may be repeated (--set a=1 --set b=2)"
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every command."""
    parser = DefaultsParser(
        prog="python -m coin_app",
        description="COIN / CIG-TD3 multi-agent driving on Ray RLlib.",
        epilog="--debug (anywhere on the line): show the traceback of an error instead of its one-line message",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=DefaultsParser)
    sub.required = True

    demo = sub.add_parser(
        "demo", help="drive a scenario with the shipped CIG-TD3 beside the heuristic driver; metrics, GIF, trajectory plot, replay page"
    )
    demo.add_argument(
        "--policy",
        default="auto",
        help="auto (the shipped policy trained on --scenario, else heuristic) | heuristic | a shipped policy's name "
        "(python -m coin_app policies) | an exported policy file",
    )
    demo.add_argument("--compare", default="heuristic", help="a second policy driven on the same seed, beside the first | none")
    demo.add_argument("--scenario", default=None, choices=DRIVING, help="the scenario (default: the policy's; intersection)")
    demo.add_argument("--preset", default=None, choices=tuple(PRESETS), help="scenario settings (default: the policy's; paper)")
    demo.add_argument("--num-agents", type=int, default=None, help="vehicles at reset (default: the policy's training count)")
    demo.add_argument("--steps", type=int, default=300, help="env steps to run (stops earlier if the episode ends)")
    demo.add_argument("--seed", type=int, default=0, help="episode seed")
    demo.add_argument("--out", default="runs/demo", help="output directory")
    demo.add_argument("--gif-every", type=int, default=2, help="render every k-th step into the GIF")
    demo.add_argument("--no-gif", action="store_true", help="skip the animation")
    demo.add_argument(
        "--html", action=argparse.BooleanOptionalAction, default=True, help="write replay.html: the episode to scrub in a browser"
    )
    add_set(demo, "scenario config overrides")
    demo.set_defaults(run="drive.cmd_demo")

    tr = sub.add_parser("train", help=f"train an algorithm ({', '.join(ALGORITHM_NAMES)}) with checkpoints and --resume")
    tr.add_argument("--algo", default="cig_td3", choices=ALGORITHM_NAMES, help=f"the algorithm ({ALGORITHM_NAMES[-1]}: the {ARENA})")
    tr.add_argument("--scenario", default="intersection", choices=(*DRIVING, ARENA), help=f"the scenario ({ARENA}: {ALGORITHM_NAMES[-1]})")
    tr.add_argument("--num-agents", type=int, default=None, help="vehicles (default: the scenario's)")
    tr.add_argument("--backend", default="native", help="native | metadrive (needs requirements-metadrive.txt)")
    tr.add_argument("--steps", type=int, default=1_000_000, help="env steps to train for")
    tr.add_argument("--seed", type=int, default=0, help="training seed, an integer in [0, 90000) (higher ones are evaluation seeds)")
    add_set(tr, "scenario or algorithm overrides (see docs)")
    tr.add_argument("--out", default=None, help="run directory (default runs/<algo>_<scenario>_s<seed>)")
    tr.add_argument("--checkpoint-every", type=int, default=10, help="checkpoint every K training iterations")
    tr.add_argument("--max-minutes", type=float, default=None, help="stop (with a checkpoint) after this much wall time")
    tr.add_argument(
        "--max-cpu-hours",
        type=float,
        default=None,
        help="stop (with a checkpoint) once the run's CPU time, its Ray processes' and a resumed run's earlier segments "
        "included, reaches this many hours (checked between iterations)",
    )
    tr.add_argument("--resume", default=None, help="checkpoint directory to continue from (same algorithm, scenario and network)")
    tr.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out (refused without --resume or this)")
    tr.add_argument(
        "--progress",
        choices=("auto", "always", "never"),
        default="auto",
        help="progress bar over env steps, with the updates inside each iteration (auto: on a terminal only)",
    )
    tr.add_argument(
        "--quick",
        action="store_true",
        help="the algorithm's small settings that show learning within minutes (4 agents, a horizon that fits the scene: 300 "
        "on the intersection; small networks; TD3 family: warm-up 500); --set values override them",
    )
    tr.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads of the training process (1; more only if benchmarks/learner_update.py shows it helps)",
    )
    tr.add_argument("--address", default=None, help="a running Ray cluster (default: a local session over all of this machine's cores)")
    tr.add_argument(
        "--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, help="seconds to wait for the cluster at --address before refusing it"
    )
    tr.set_defaults(run="train.cmd_train")

    ev = sub.add_parser("evaluate", help="evaluate a checkpoint or exported policy on test seeds (deterministic actions)")
    ev.add_argument("policy", help="a checkpoint directory or an exported .npz file")
    ev.add_argument("--scenario", default=None, help="scenario (default: the one the policy was trained on)")
    ev.add_argument("--backend", default=None, help="native | metadrive (default: the training backend)")
    ev.add_argument(
        "--preset",
        default=None,
        help=f"{' | '.join(PRESETS)}: evaluate with this preset's settings in place of the training config's preset and the keys "
        "presets set (e.g. metadrive_compat: lidar_range 40); --set still wins (default: the policy's own training config)",
    )
    add_set(ev, "scenario config overrides")
    ev.add_argument("--episodes", type=int, default=20, help=f"number of test seeds (paper: 20; at most {MAX_EPISODES})")
    ev.add_argument("--seeds", type=int, nargs="*", default=None, help="explicit seeds (default: the fixed test seeds)")
    ev.add_argument("--num-agents", type=int, default=None, help="evaluate at another agent count (generalization)")
    ev.add_argument("--out", default=None, help="write per-episode results to this JSON file")
    ev.add_argument("--replay", default=None, metavar="HTML", help="also write the first seed's episode as a replay page (native backend)")
    ev.set_defaults(run="evaluate.cmd_evaluate")

    er = sub.add_parser(
        "evaluate-reference",
        help="the COIN authors' released actors on every scene, natively and on MetaDrive (their protocol): the reference table",
    )
    er.add_argument(
        "--actors",
        default=None,
        help="directory of the released actors (<scene>/TD3_<scene>_<seed>_best_model_*_actor) or a clone of "
        "github.com/marmotlab/COIN (default: $COIN_OFFICIAL_ACTORS)",
    )
    er.add_argument("--scenes", nargs="+", default=list(DRIVING), choices=DRIVING, help="scenes, each at COIN's vehicle count")
    er.add_argument("--backends", nargs="+", default=["native", "metadrive"], choices=("native", "metadrive"), help="simulators")
    er.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="training seeds of the actors (default: every one found, 1000..8000)"
    )
    er.add_argument(
        "--episodes",
        type=int,
        default=5,
        help="episodes per actor, seeded 1000 + 100 i as coin_eval.py seeds them (it runs 20 per actor; the README table 5)",
    )
    er.add_argument("--workers", type=int, default=1, help="evaluation processes (each MetaDrive episode runs in one)")
    er.add_argument("--out", default="runs/reference", help="output directory; a run there resumes (finished episodes are kept)")
    er.add_argument(
        "--progress", choices=("auto", "always", "never"), default="auto", help="a line per finished task (auto: on a terminal only)"
    )
    er.set_defaults(run="reference.cmd_evaluate_reference")

    pr = sub.add_parser("probe", help="a TD3-family checkpoint's critics at its stopped vehicles: do they prefer braking or driving on?")
    pr.add_argument("checkpoint", help="a CIG-TD3 or ITD3 checkpoint directory (native backend)")
    pr.add_argument("--episodes", type=int, default=10, help="test seeds to run (default 10)")
    pr.add_argument("--speed-below", type=float, default=0.5, help="a vehicle counts as stopped below this speed (m/s)")
    pr.set_defaults(run="train.cmd_probe")

    ex = sub.add_parser("export", help="export a checkpoint's actor for Ray-free inference")
    ex.add_argument("checkpoint", help="a checkpoint directory written by train or a sweep")
    ex.add_argument(
        "--format",
        default="numpy",
        help="numpy (.npz weights, numpy forward pass), torchscript (.pt, needs torch) or onnx (.onnx, needs requirements-onnx.txt)",
    )
    ex.add_argument("--out", required=True, help="output file with the format's suffix: policy.npz, policy.pt or policy.onnx")
    ex.set_defaults(run="evaluate.cmd_export")

    pa = sub.add_parser("pair", help="combine a long- and a short-range arena policy into one switching policy file")
    pa.add_argument("long", help="long-range policy: checkpoint directory or exported .npz")
    pa.add_argument("short", help="short-range (parking) policy: checkpoint directory or exported .npz")
    pa.add_argument("--switch-radius", type=float, default=7.5, help="metres to the target below which the short-range policy acts")
    pa.add_argument("--out", required=True, help="pair file to write (.json)")
    pa.set_defaults(run="evaluate.cmd_pair")

    ea = sub.add_parser("evaluate-arena", help="the seed-2 paper's 24-case arena test suite (Tables I and II) for policies, side by side")
    ea.add_argument(
        "policy",
        nargs="+",
        help="one or more of: heuristic | avoiding | planning (the scripted drivers) | agnn (the A-GNN baseline's released weights) | "
        "a shipped policy's name (nav_ppo-arena) | checkpoint directory | exported .npz | pair .json",
    )
    ea.add_argument("--cases", default="all", help="all (the paper's 24) or e.g. 4x3,20x8")
    ea.add_argument(
        "--scenarios-per-case",
        type=int,
        default=100,
        help=f"fixed test scenarios per case (the paper: 4062; at most {MAX_SCENARIOS_PER_CASE})",
    )
    ea.add_argument(
        "--max-steps", type=int, default=400, help="steps of 0.1 s per scenario (400 = 40 s; agnn: the same time in its 0.2 s steps)"
    )
    ea.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default="arena",
        help="arena: the seed paper's success test (1.25 m, 0.2 rad, 0.05 m/s; vehicles park); "
        "agnn: the A-GNN paper's (final state within 1.25 m and 0.2 rad, no speed test, early stop when all are still)",
    )
    ea.add_argument(
        "--generator",
        choices=GENERATORS,
        default="agnn",
        help="agnn: the paper's suite (the A-GNN test generator); short: the parking stage's starts (1-7.5 m from the target, "
        "any heading) on the same held-out seeds, to score a short-range policy alone (not comparable with the paper's tables)",
    )
    ea.add_argument(
        "--observed-entities",
        type=int,
        default=None,
        help="entities each vehicle observes, closest first: for scripted drivers (default 1, the paper's); "
        "learned policies observe what they were trained on",
    )
    ea.add_argument("--workers", type=int, default=2, help="worker processes (one CPU thread each)")
    ea.add_argument("--out", default="runs/arena_eval", help="output directory")
    ea.add_argument("--plots", type=int, default=0, help="trajectory plots and replay pages of the first K test scenarios of each case")
    ea.set_defaults(run="evaluate.cmd_evaluate_arena")

    sw = sub.add_parser("sweep", help="run (or --resume) a Ray Tune sweep: seeds | ablations | generalization")
    sw.add_argument("experiment", help="seeds, ablations or generalization (tuning/)")
    sw.add_argument("--scenario", default="intersection", choices=DRIVING, help="the scenario")
    sw.add_argument("--algos", nargs="*", default=None, help="methods to sweep (default: the experiment's, cig_td3)")
    sw.add_argument("--seeds", type=int, nargs="*", default=None, help="training seeds (default: the scale's; paper: 0..7)")
    sw.add_argument("--steps", type=int, default=None, help="env steps per trial (default: the scale's; paper: 1,000,000)")
    add_set(sw, "overrides for every trial")
    scales = [f"{name} ({what})" for name, what in SCALES.items()]
    sw.add_argument("--scale", default=None, help=f"{', '.join(scales[:-1])} or {scales[-1]}")
    sw.add_argument("--smoke", action="store_true", help="the same as --scale smoke")
    sw.add_argument("--address", default=None, help="Ray cluster to run on: auto, HOST:PORT or ray://HOST:PORT (default: a local Ray)")
    sw.add_argument("--storage", default=None, help="results root: a path or a URI such as s3://bucket/sweeps (default runs/sweeps)")
    sw.add_argument("--name", default=None, help="experiment directory name (default <experiment>-<scenario>[-<scale>])")
    sw.add_argument("--max-concurrent", type=int, default=None, help="trials running at once (default: as many as fit)")
    sw.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    sw.add_argument(
        "--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, help="seconds to wait for the cluster at --address before refusing it"
    )
    sw.add_argument("--resume", action="store_true", help="continue the named sweep: finished trials stay, others resume")
    sw.add_argument(
        "--accept-changes",
        action="store_true",
        help="with --resume: continue although this code resolves other trial settings than the sweep ran with (recorded)",
    )
    sw.add_argument(
        "--restart",
        nargs="+",
        default=[],
        metavar="METHOD",
        help="with --resume: run these methods' trials again from scratch (after a fix); their old directories move to replaced/",
    )
    sw.add_argument("--wandb", default=None, metavar="PROJECT", help="also log trials to this W&B project (needs wandb)")
    sw.add_argument("--mlflow", default=None, metavar="URI", help="also log trials to this MLflow tracking URI (needs mlflow)")
    sw.set_defaults(run="sweeps.cmd_sweep")

    ge = sub.add_parser("generalize", help="evaluate a sweep's final checkpoints at other agent counts (tidy CSV)")
    ge.add_argument("experiment_dir", help="a sweep's experiment directory")
    ge.add_argument("--counts", type=int, nargs="*", default=None, help="agent counts (default: the sweep's grid)")
    ge.add_argument("--test-seeds", type=int, default=None, help="episodes per checkpoint and count (default: the sweep's, 20)")
    ge.set_defaults(run="sweeps.cmd_generalize")

    ar = sub.add_parser(
        "archive",
        help="copy a sweep's finished trials (results, curves, the final and the validation-selected checkpoints' actors) into "
        "a small directory that report reads as the sweep: a result that outlives the machine",
    )
    ar.add_argument("sweeps", nargs="+", help="sweep directories or directories of sweeps")
    ar.add_argument("--out", required=True, help="archive root: each sweep goes to <out>/<sweep name>/ (run again to add trials)")
    ar.add_argument(
        "--validation-episodes",
        type=int,
        default=VALIDATION_EPISODES,
        help="validation seeds per kept checkpoint: the one best on them is archived beside the final one (report --select's)",
    )
    ar.add_argument(
        "--modules",
        nargs="*",
        default=["cig_td3"],
        metavar="METHOD",
        help="methods whose two checkpoints keep the whole policy module, critics included (the report's CVAE latent figure); "
        "the others keep their actor only",
    )
    ar.set_defaults(run="sweeps.cmd_archive")

    rp = sub.add_parser("report", help="evaluate sweeps on the test seeds; tables, t-tests, figures, marl-eval JSON, report.html")
    rp.add_argument(
        "sources",
        nargs="+",
        help="sweep directories (or their archives), directories of sweeps, results.csv files of earlier reports, or "
        "evaluate-arena output directories",
    )
    rp.add_argument("--out", required=True, help="output directory")
    rp.add_argument("--method", default="cig_td3", help="the method tested against every baseline (default cig_td3)")
    rp.add_argument(
        "--counts", type=int, nargs="*", default=None, help="also evaluate at these agent counts (default: a generalization sweep's)"
    )
    rp.add_argument("--test-seeds", type=int, default=None, help="test episodes per model and cell (default: the sweep's, 20)")
    rp.add_argument("--workers", type=int, default=2, help="evaluation processes")
    rp.add_argument("--alpha", type=float, default=0.01, help="significance level before the Bonferroni correction")
    rp.add_argument("--tsne-samples", type=int, default=500, help="CVAE latent samples per scenario (paper: 1500)")
    rp.add_argument("--tsne-episodes", type=int, default=4, help="test episodes the latents are collected from")
    rp.add_argument("--transfer", default=None, help="also evaluate every model on this backend (metadrive): the native -> MetaDrive gap")
    rp.add_argument("--transfer-test-seeds", type=int, default=5, help="test episodes per model on the --transfer backend")
    rp.add_argument(
        "--select",
        default="final",
        help="the checkpoint of each trial scored on the test seeds: final (default) | validation (the one best on validation seeds)",
    )
    rp.add_argument(
        "--validation-episodes", type=int, default=VALIDATION_EPISODES, help="validation seeds per checkpoint with --select validation"
    )
    rp.add_argument(
        "--reference-actors",
        default=None,
        help="also evaluate the COIN authors' released actors (this directory, see evaluate-reference --actors) on the same test "
        "seeds, for every scene the report has at Table 5.1's density: the reference row 'coin_authors' (not in the t-tests)",
    )
    rp.add_argument(
        "--cache",
        default=None,
        help="evaluated episodes are kept in this directory as each model's evaluation ends and are not evaluated again while "
        "the checkpoint and the simulator's and evaluator's code stay the same: a stopped report, run again, goes on where it "
        "stopped (default: the folder episodes of --out)",
    )
    rp.add_argument("--no-cache", action="store_true", help="evaluate every episode, keep none")
    rp.set_defaults(run="sweeps.cmd_report")

    sb = sub.add_parser("submit", help="submit a coin_app command to a Ray cluster as a job (ray job submit); prints the job id")
    sb.add_argument("--address", default=None, help="job server URL (the dashboard), default http://127.0.0.1:8265")
    sb.add_argument("--install", default="pip", choices=["pip", "none"], help="pip: install requirements.txt's pins in the job env")
    sb.add_argument("--submission-id", default=None, help="job id to use (default: one from Ray)")
    sb.add_argument("--wait", action="store_true", help="follow the job's logs until it ends; exit 0 only if it succeeded")
    sb.add_argument("--timeout", type=float, default=24 * 3600.0, help="seconds --wait follows the job at most")
    sb.add_argument("command", nargs=argparse.REMAINDER, help="-- then the coin_app command, e.g. -- sweep seeds --smoke")
    sb.set_defaults(run="cluster.cmd_submit")

    jb = sub.add_parser("job", help="status, logs or stop of a submitted job")
    jb.add_argument("action", choices=["status", "logs", "stop"])
    jb.add_argument("job_id", help="the id submit printed")
    jb.add_argument("--address", default=None, help="job server URL, default http://127.0.0.1:8265")
    jb.set_defaults(run="cluster.cmd_job")

    cf = sub.add_parser("config", help="print every merged setting of a run (train's or a sweep trial's) with where it came from")
    cf.add_argument("--algo", default="cig_td3", choices=ALGORITHM_NAMES, help="the algorithm")
    cf.add_argument("--scenario", default="intersection", choices=(*DRIVING, ARENA), help="the scenario")
    cf.add_argument("--scale", default=None, choices=tuple(SCALES), help="a sweep trial's settings at this scale (sweep --scale's)")
    cf.add_argument("--experiment", default="seeds", help="the sweep's experiment, with --scale: seeds | ablations | generalization")
    cf.add_argument("--variant", default="default", help="the experiment's variant, with --scale (ablations: e.g. wo_gat)")
    cf.add_argument("--steps", type=int, default=None, help="env steps per trial, with --scale (default: the scale's)")
    cf.add_argument("--quick", action="store_true", help="train --quick's small settings (without --scale)")
    cf.add_argument("--num-agents", type=int, default=None, help="vehicles (default: the scenario's or the scale's)")
    add_set(cf, "overrides, as train and sweep take them")
    cf.set_defaults(run="settings.cmd_config")

    pol = sub.add_parser("policies", help="list the shipped trained policies (load one by name, drive one with demo --policy)")
    pol.set_defaults(run="drive.cmd_policies")

    scen = sub.add_parser("scenarios", help="list scenarios, presets, their config keys and every algorithm's keys with defaults")
    scen.set_defaults(run="catalog.cmd_scenarios")
    return parser
