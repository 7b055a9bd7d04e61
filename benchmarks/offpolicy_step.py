"""Where the TD3 family's training step spends its time, per env step: CIG-TD3, ITD3 and TraCo at 4 and 30 vehicles.

Usage: python benchmarks/offpolicy_step.py [--tree PATH] [--algos cig_td3 itd3 traco] [--agents 4 30] [--dense]
                                           [--steps4 40] [--steps30 5] [--precision auto|fp32|bf16]
                                           [--fragment K] [--other-fragment K] [--envs N] [--other-envs N]

Each case builds the algorithm as training does (``coin_app.training.build_config``): at 4 vehicles
the reduced protocol's trial (``sweep seeds --scale reduced``, seed 0), at 30 the intersection at
the paper's density with the algorithm's defaults (``--dense``: the dense protocol's trial, ``--scale dense``);
``--precision`` overrides the learner precision
of both (default: the settings' own; the table names the precision it resolved to), ``--fragment``
the env steps per training step (``rollout_fragment_length``, K) of this tree and ``--other-fragment``
of the ``--tree`` one (default 1 each), ``--envs`` / ``--other-envs`` the envs each env runner steps together
(``num_envs_per_env_runner``; default 1 each: the reduced protocol's; an env step is one env's step, so N envs
sample N env steps per runner step). The warm-up is cut to what fills one batch, so the updates
start at once (the time of a step after the warm-up does not depend on its length). After the
first update it times blocks of ``algo.training_step()`` calls, the loop ``algo.train()`` runs
(the iteration's end, one per 500 env steps, is not timed), and attributes every second to one
piece by wrapping the functions that do it (time inside a nested wrapped call goes to the inner
piece only):

* simulator: ``DrivingSimulator.step`` / ``reset_envs``;
* actor forward: the env runner's action computation (``BatchedEnvRunner._actions``);
* episode building: the rest of the env runner's ``sample`` (step arrays, infos, ``MultiAgentEpisode`` chunks)
  and of the vector env's step;
* replay add: ``episodes_to_transitions`` and the replay buffer's ``add``;
* replay sample + connector: the buffer's ``sample``, ``SampleBatch`` construction, the learner's
  batch preparation (``_make_batch_if_necessary``, RLlib's and the learner's own: learner connector
  pipeline, numpy -> torch) and any ``ConnectorV2`` piece's call (the TD3 family's ``JointState``);
* update: the learner's gradient step (``Learner._update``, ``before/after_gradient_based_update``);
* weight sync: the algorithm's ``_sync_actor`` (RLlib's ``sync_weights`` where it has none);
* metrics: ``MetricsLogger`` calls and the learner's step-count metrics;
* RLlib calls: the rest of ``synchronous_parallel_sample``, ``LearnerGroup.update`` and ``Learner.update``;
* other: the rest of ``training_step``.

With ``--tree PATH`` every case also runs on that checkout (e.g. a worktree of an older commit), in
a worker of its own (``benchmarks/trees.py``), the two trees' blocks alternating, and the table shows
both side by side. Pieces a tree does not have are reported absent. RLlib's own timers of the result
dict (mean ms per call) are printed under each case as a cross-check. The summary gives, per case,
ms per env step, the update's share and the time outside the update (issue 55's targets: outside
<= 10 % of a training step at 4 vehicles, <= 10 ms per env step at 30).
"""

from __future__ import annotations

import argparse
import functools
import gc
import importlib
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

from trees import THIS_TREE, TreeWorker, serve, tree_path

PIECES = (
    "simulator",
    "actor forward",
    "episode building",
    "replay add",
    "replay sample + connector",
    "update",
    "weight sync",
    "metrics",
    "RLlib calls",
    "other",
)
ALGOS = ("cig_td3", "itd3", "traco")
REDUCED_AGENTS = 4  # the reduced protocol's intersection
CLOCKS = ("wall", "cpu")
RLLIB_TIMERS = {
    "env_runner_sampling_timer": "sampling",
    "replay_buffer_add_data_timer": "replay add",
    "replay_buffer_sampling_timer": "replay sample",
    "learner_update_timer": "learner update",
    "synch_weights": "weight sync",
}


# ---------------------------------------------------------------- worker side: exclusive timing by wrappers
class Clock:
    """Seconds per piece, exclusive (a wrapped call's time minus the time of the wrapped calls nested in it), on two clocks.

    ``wall``: elapsed time; ``cpu``: the calling thread's CPU time (``time.thread_time``), which
    leaves out the time the process waits for a core on a loaded machine (the training step runs
    in one thread: the env runner and the learner live in the algorithm's process).
    """

    def __init__(self) -> None:
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)  # by function name
        self.stack: list[list[Any]] = []  # [piece, wall and cpu time of the nested wrapped calls]
        self.thread = threading.get_ident()  # calls from other threads pass untimed (they are not the training step's)
        self.foreign_calls = 0
        self.gc_seconds = 0.0
        gc.callbacks.append(self.gc_callback)

    def wrap(self, fn: Callable[..., Any], piece: str) -> Callable[..., Any]:
        """``fn`` timed into ``piece``."""

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if threading.get_ident() != self.thread:
                self.foreign_calls += 1
                return fn(*args, **kwargs)
            wall0, cpu0 = time.perf_counter(), time.thread_time()
            self.stack.append([piece, 0.0, 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, nested_wall, nested_cpu = self.stack.pop()
                wall, cpu = time.perf_counter() - wall0, time.thread_time() - cpu0
                self.wall[piece] += wall - nested_wall
                self.cpu[piece] += cpu - nested_cpu
                self.calls[fn.__name__] += 1
                if self.stack:
                    self.stack[-1][1] += wall
                    self.stack[-1][2] += cpu

        timed.__wrapped_by_clock__ = True  # type: ignore[attr-defined]
        return timed

    def patch(self, owner: Any, name: str, piece: str) -> bool:
        """Wrap ``owner.name`` (a class's method or a module's function) once; False if ``owner`` has no such attribute."""
        fn = owner.__dict__.get(name) if isinstance(owner, type) else getattr(owner, name, None)
        if fn is None or getattr(fn, "__wrapped_by_clock__", False):
            return fn is not None
        if isinstance(fn, staticmethod | classmethod):
            return False
        setattr(owner, name, self.wrap(fn, piece))
        return True

    def reset(self) -> None:
        """Forget the totals so far."""
        self.wall.clear()
        self.cpu.clear()
        self.calls.clear()
        self.foreign_calls = 0
        self.gc_seconds = 0.0

    def gc_callback(self, phase: str, info: dict[str, Any]) -> None:
        """Sum the time of Python's garbage collections (a ``gc.callbacks`` entry); it is inside whichever piece they interrupt."""
        if phase == "start":
            self._gc_start = time.perf_counter()
        elif hasattr(self, "_gc_start"):
            self.gc_seconds += time.perf_counter() - self._gc_start

    def cost_per_call(self, calls: int = 20_000) -> float:
        """Seconds one wrapper adds to a call (measured on a no-op, outside any piece)."""

        def noop() -> None:
            return None

        timed = Clock().wrap(noop, "calibration")
        t0 = time.perf_counter()
        for _ in range(calls):
            noop()
        t1 = time.perf_counter()
        for _ in range(calls):
            timed()
        return max(0.0, (time.perf_counter() - t1) - (t1 - t0)) / calls


def _defining_class(cls: type, name: str) -> type | None:
    """The class in ``cls``'s MRO whose own dict defines ``name``."""
    return next((k for k in cls.__mro__ if name in k.__dict__), None)


def instrument(clock: Clock, algo: Any) -> list[str]:
    """Wrap the pieces of ``algo``'s training step (see module doc); the names of the ones found."""
    from ray.rllib.connectors.connector_v2 import ConnectorV2  # noqa: I001  (imported by the worker only: its tree's Ray)
    from ray.rllib.core.learner.learner import Learner
    from ray.rllib.core.learner.learner_group import LearnerGroup
    from ray.rllib.execution import rollout_ops
    from ray.rllib.policy.sample_batch import SampleBatch
    from ray.rllib.utils.metrics.metrics_logger import MetricsLogger

    found: list[str] = []

    def patch(owner: Any, name: str, piece: str) -> None:
        if owner is None:
            return
        where = _defining_class(owner, name) if isinstance(owner, type) else owner
        if where is not None and clock.patch(where, name, piece):
            found.append(f"{getattr(where, '__qualname__', getattr(where, '__name__', where))}.{name}")

    runner = algo.env_runner
    venv = getattr(runner, "vector_env", None)
    patch(type(getattr(venv, "sim", None)) if venv is not None else None, "step", "simulator")
    patch(type(getattr(venv, "sim", None)) if venv is not None else None, "reset_envs", "simulator")
    patch(type(venv) if venv is not None else None, "step", "episode building")
    patch(type(runner), "_actions", "actor forward")
    for name in ("sample", "_chunk", "_episodes"):
        patch(type(runner), name, "episode building")
    # the replay: the buffer object's class and the algorithm module's transitions function
    replay = getattr(algo, "replay", None) or getattr(algo, "local_replay_buffer", None)
    patch(type(replay) if replay is not None else None, "add", "replay add")
    patch(type(replay) if replay is not None else None, "sample", "replay sample + connector")
    step_module = importlib.import_module(_defining_class(type(algo), "training_step").__module__)
    patch(step_module, "episodes_to_transitions", "replay add")
    patch(SampleBatch, "__init__", "replay sample + connector")
    learner = getattr(algo.learner_group, "_learner", None)
    patch(Learner, "_make_batch_if_necessary", "replay sample + connector")
    patch(type(learner) if learner is not None else None, "_make_batch_if_necessary", "replay sample + connector")  # a tree's own
    for cls in _subclasses(ConnectorV2):
        if "__call__" in cls.__dict__:
            patch(cls, "__call__", "replay sample + connector")
    for name in ("_update", "before_gradient_based_update", "after_gradient_based_update"):
        patch(type(learner) if learner is not None else Learner, name, "update")
    if not patch_sync(algo, patch):
        patch(type(algo.env_runner_group), "sync_weights", "weight sync")
    for name in ("log_value", "log_dict", "aggregate", "reduce", "peek", "log_time"):
        patch(MetricsLogger, name, "metrics")
    for name in ("_log_steps_trained_metrics", "_log_metrics"):
        patch(Learner, name, "metrics")
    patch(rollout_ops, "synchronous_parallel_sample", "RLlib calls")
    step_globals = vars(step_module)
    if "synchronous_parallel_sample" in step_globals:  # the name the training step calls
        patch(step_module, "synchronous_parallel_sample", "RLlib calls")
    patch(LearnerGroup, "update", "RLlib calls")
    patch(Learner, "update", "RLlib calls")
    patch(type(algo), "training_step", "other")
    return found


def patch_sync(algo: Any, patch: Callable[[Any, str, str], None]) -> bool:
    """Wrap the algorithm's own actor sync if it has one."""
    if _defining_class(type(algo), "_sync_actor") is None:
        return False
    patch(type(algo), "_sync_actor", "weight sync")
    return True


def _subclasses(cls: type) -> list[type]:
    out, todo = [], [cls]
    while todo:
        for sub in todo.pop().__subclasses__():
            out.append(sub)
            todo.append(sub)
    return out


class Worker:
    """One algorithm at a time, instrumented, in one tree."""

    def __init__(self) -> None:
        self.algo: Any = None
        self.clock = Clock()

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        """Answer one request: build, time or stop (see the methods)."""
        import ray  # noqa: I001  (imported by the worker only: its tree decides which coin_app these are)
        import torch

        torch.set_num_threads(1)
        if not ray.is_initialized():
            ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
        if req["op"] == "build":
            return self.build(
                req["algo"], req["agents"], req.get("precision"), req.get("fragment", 1), req.get("envs", 1), req.get("dense", False)
            )
        if req["op"] == "time":
            return self.time(req["steps"])
        if req["op"] == "stop":
            self.algo.stop()
            self.algo = None
            gc.collect()  # the next case starts without this one's garbage
            return {}
        raise ValueError(f"unknown op {req['op']!r}")

    def build(
        self, algo_name: str, agents: int, precision: str | None, fragment: int, envs: int = 1, dense: bool = False
    ) -> dict[str, Any]:
        """Build and instrument the case's algorithm and run it until its first update; what was found and the settings."""
        from coin_app.training import build_config  # noqa: I001  (the worker's tree)

        overrides: dict[str, Any] = {"eval_every": 0}
        if agents == REDUCED_AGENTS or dense:
            from tuning import get_experiment
            from tuning.experiment import expand_grid
            from tuning.trainable import trial_overrides

            scale = "reduced" if agents == REDUCED_AGENTS else "dense"
            (trial,) = expand_grid(get_experiment("seeds").param_space("intersection", scale, (algo_name,), (0,)))
            overrides.update(trial_overrides(trial) | {"eval_every": 0})
        else:
            overrides["num_agents"] = agents
        if precision is not None:
            overrides["precision"] = precision
        if fragment != 1:
            overrides["rollout_fragment_length"] = fragment
        if envs != 1:
            overrides["num_envs_per_env_runner"] = envs
        probe = build_config(algo_name, "intersection", overrides, 0)
        batch = probe.train_batch_size_per_learner
        overrides["warmup_steps"] = 2 * -(-batch // max(1, agents - 1)) + 10  # a batch of sampleable transitions, then updates
        cfg = build_config(algo_name, "intersection", overrides, 0)
        self.algo = cfg.build_algo()
        found = instrument(self.clock, self.algo)
        self.clock.reset()  # the wrappers stay on the classes from case to case; their counts do not
        t0 = time.perf_counter()
        while self.clock.calls["_update"] == 0:  # warm-up: until the first gradient step has run
            self.algo.training_step()
        precision = getattr(cfg, "precision", "fp32")
        try:  # the precision "auto" resolves to on the learner's device (a tree without it has no "auto")
            from coin_app.algorithms.td3.learner import resolve_precision  # noqa: I001  (the worker's tree)

            learner = self.algo.learner_group._learner
            precision = resolve_precision(precision, next(learner.module["shared"].parameters()).device)
        except (ImportError, AttributeError, ValueError):
            pass
        return {
            "found": found,
            "warmup_s": time.perf_counter() - t0,
            "precision": precision,
            "fragment": fragment,
            "envs": envs,
            "batch": batch,
            "num_agents": cfg.scenario_config().num_agents,
        }

    def time(self, steps: int) -> dict[str, Any]:
        """Run training steps until ``steps`` env steps were sampled; the wall time, the pieces' seconds and RLlib's timers."""
        from ray.rllib.utils.metrics import TIMERS  # noqa: I001  (the worker's tree's Ray)

        algo, runner = self.algo, self.algo.env_runner
        env0 = runner.num_env_steps_sampled_lifetime  # read without the metrics logger (its calls are timed)
        self.clock.reset()
        wall0, cpu0 = time.perf_counter(), time.thread_time()
        while runner.num_env_steps_sampled_lifetime - env0 < steps:
            algo.training_step()
        wall, cpu = time.perf_counter() - wall0, time.thread_time() - cpu0
        timers = {name: algo.metrics.peek((TIMERS, name), default=float("nan")) for name in RLLIB_TIMERS}
        return {
            "wall": wall,
            "cpu": cpu,
            "env_steps": int(runner.num_env_steps_sampled_lifetime - env0),
            "pieces": {"wall": dict(self.clock.wall), "cpu": dict(self.clock.cpu)},
            "updates": self.clock.calls["_update"],
            "wrapped_calls": sum(self.clock.calls.values()),
            "foreign_calls": self.clock.foreign_calls,
            "gc_seconds": self.clock.gc_seconds,
            "cost_per_call": self.clock.cost_per_call(),
            "timers": {k: float(v) for k, v in timers.items() if v == v},  # NaN: no such timer
        }


# ---------------------------------------------------------------- parent side
def main() -> None:
    """Run every case on every tree and print the breakdowns and the summary."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", help="another checkout to measure beside this one (e.g. a worktree of an older commit)")
    ap.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    ap.add_argument("--agents", nargs="+", type=int, choices=(REDUCED_AGENTS, 30), default=[REDUCED_AGENTS, 30])
    ap.add_argument("--steps4", type=int, default=40, help="timed env steps per tree at 4 vehicles (default 40)")
    ap.add_argument(
        "--steps30",
        type=int,
        help="timed env steps per tree at 30 vehicles (default 5: one policy-delay cycle; with --dense 40: 10 updates)",
    )
    ap.add_argument("--blocks", type=int, default=1, help="timed blocks per tree, the trees alternating (default 1)")
    ap.add_argument("--dense", action="store_true", help="at 30 vehicles, the dense protocol's trial (sweep seeds --scale dense)")
    ap.add_argument("--precision", choices=("auto", "fp32", "bf16"), help="learner precision of every case (default: the settings' own)")
    ap.add_argument("--fragment", type=int, default=1, help="env steps per training step (K) in this tree (default 1)")
    ap.add_argument("--other-fragment", type=int, default=1, help="env steps per training step (K) in the --tree one (default 1)")
    ap.add_argument("--envs", type=int, default=1, help="envs per env runner in this tree (default 1)")
    ap.add_argument("--other-envs", type=int, default=1, help="envs per env runner in the --tree one (default 1)")
    args = ap.parse_args()
    if args.steps30 is None:
        args.steps30 = 40 if args.dense else 5
    for name in ("steps4", "steps30", "blocks", "fragment", "other_fragment", "envs", "other_envs"):
        if getattr(args, name) < 1:
            raise SystemExit(f"bad --{name} {getattr(args, name)}; allowed: an integer >= 1")
    trees = {"this": THIS_TREE}
    if args.tree:
        trees["other"] = tree_path(args.tree)
    t_start = time.perf_counter()
    workers = {name: TreeWorker(__file__, path, name) for name, path in trees.items()}
    summary = []
    try:
        for agents in args.agents:
            for algo in args.algos:
                steps = args.steps4 if agents == REDUCED_AGENTS else args.steps30
                fragments = {"this": args.fragment, "other": args.other_fragment}
                envs = {"this": args.envs, "other": args.other_envs}
                built = {
                    n: w.call(
                        op="build",
                        algo=algo,
                        agents=agents,
                        precision=args.precision,
                        fragment=fragments[n],
                        envs=envs[n],
                        dense=args.dense,
                    )
                    for n, w in workers.items()
                }
                runs: dict[str, list[dict[str, Any]]] = {n: [] for n in workers}
                for block in range(args.blocks):
                    for n, w in list(workers.items())[:: 1 if block % 2 == 0 else -1]:  # each tree first in every other block
                        runs[n].append(w.call(op="time", steps=steps))
                for w in workers.values():
                    w.call(op="stop")
                summary.append(report(algo, agents, built, runs, args.dense))
    finally:
        for w in workers.values():
            w.close()
    clock = "cpu"
    print(f"\nsummary ({clock} ms per env step; outside = everything but the update; the issue's targets: outside <= 10 % at 4 vehicles,")
    print("<= 10 ms per env step at 30)")
    print(f"{'case':<24}" + "".join(f"{n + ' total':>12}{n + ' update':>13}{n + ' outside':>14}{'outside %':>10}" for n in trees))
    for case, per_tree in summary:
        cells = [(per_tree[n][f"{clock} total"], per_tree[n][f"{clock} update"]) for n in trees]
        print(f"{case:<24}" + "".join(f"{t:>12.1f}{u:>13.1f}{t - u:>14.1f}{100 * (t - u) / t:>9.0f}%" for t, u in cells))
    if "other" in trees:
        print(
            "\nthis / other, per case (cpu): "
            + "; ".join(f"{case} {t['this']['cpu total'] / t['other']['cpu total']:.2f}" for case, t in summary)
        )
    print(f"\n({time.perf_counter() - t_start:.0f} s in all)")


def report(
    algo: str, agents: int, built: dict[str, dict], runs: dict[str, list[dict]], dense: bool = False
) -> tuple[str, dict[str, dict[str, float]]]:
    """Print one case's breakdown (ms per env step, wall and CPU, per tree); return per tree the wall and CPU totals and updates."""
    first = next(iter(built.values()))
    scale = "reduced protocol" if agents == REDUCED_AGENTS else "dense protocol" if dense else "paper density"
    how = "; ".join(f"{n}: precision {b['precision']}, K={b.get('fragment', 1)}, envs {b.get('envs', 1)}" for n, b in built.items())
    print(f"\n{algo}, intersection, {first['num_agents']} vehicles ({scale}), B={first['batch']}, {how}")
    per_step: dict[tuple[str, str], dict[str, float]] = {}  # (tree, clock) -> piece -> ms per env step
    for n, blocks in runs.items():
        env_steps = sum(b["env_steps"] for b in blocks)
        for clock in CLOCKS:
            pieces: dict[str, float] = defaultdict(float)
            for b in blocks:
                for k, v in b["pieces"][clock].items():
                    pieces[k] += v
            total = sum(b[clock] for b in blocks)
            pieces["other"] += total - sum(pieces.values())  # time outside every wrapped call (the loop itself)
            per_step[n, clock] = {k: 1000 * v / env_steps for k, v in pieces.items()} | {"total": 1000 * total / env_steps}
        print(f"  {n} tree: {env_steps} env steps, {sum(b['updates'] for b in blocks)} updates, warm-up {built[n]['warmup_s']:.0f} s")
    cols = [(n, c) for n in runs for c in CLOCKS]
    ratio = "other" in runs
    print(f"  {'ms per env step':<28}" + "".join(f"{n + ' ' + c:>12}" for n, c in cols) + ("   this/other (cpu)" if ratio else ""))
    for piece in (*PIECES, "total"):
        cells = [per_step[key].get(piece) for key in cols]
        line = f"  {piece:<28}" + "".join(f"{'absent':>12}" if v is None else f"{v:>12.2f}" for v in cells)
        mine, theirs = per_step["this", "cpu"].get(piece), per_step.get(("other", "cpu"), {}).get(piece)
        if ratio and mine is not None and theirs:
            line += f"   {mine / theirs:.2f}"
        print(line)
    for n, blocks in runs.items():
        steps = sum(b["env_steps"] for b in blocks)
        calls = sum(b["wrapped_calls"] for b in blocks) / steps
        cost = 1000 * calls * blocks[-1]["cost_per_call"]
        foreign = sum(b["foreign_calls"] for b in blocks)
        gc_ms = 1000 * sum(b["gc_seconds"] for b in blocks) / steps
        print(
            f"  instrumentation, {n} tree: {calls:.0f} wrapped calls per env step, about {cost:.2f} ms per env step (inside the pieces)"
            + (f"; {foreign} calls from other threads, not timed" if foreign else "")
            + f"; Python's garbage collections {gc_ms:.2f} ms per env step (inside the pieces they interrupt)"
        )
        timers = blocks[-1]["timers"]
        if timers:
            print(
                f"  RLlib timers, {n} tree (mean ms per call): " + ", ".join(f"{RLLIB_TIMERS[k]} {v * 1000:.2f}" for k, v in timers.items())
            )
    out = {n: {f"{c} {k}": per_step[n, c].get(k, 0.0) for c in CLOCKS for k in ("total", "update")} for n in runs}
    return f"{algo}, {agents} vehicles", out


if __name__ == "__main__":
    if sys.argv[1:] == ["--worker"]:
        serve(Worker().handle)
    else:
        main()
