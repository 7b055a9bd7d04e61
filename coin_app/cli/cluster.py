"""``submit`` and ``job``: a coin_app command as a Ray job on a cluster."""

from __future__ import annotations

import argparse

from cluster import jobs
from coin_app.cli.parser import UsageError, build_parser
from coin_app.evaluation.limits import check_timeout


def _check_command(command: list[str]) -> None:
    """Refuse a coin_app command that does not parse, before it is sent to a cluster."""
    try:
        build_parser().parse_args(command)
    except (SystemExit, UsageError) as exc:  # SystemExit: --help
        raise ValueError(f"bad coin_app command {' '.join(command)!r} (see python -m coin_app --help)") from exc


def cmd_submit(args: argparse.Namespace) -> int:
    """Submit a coin_app command as a Ray job; print the job id (and follow it with --wait)."""

    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if args.wait:
        check_timeout(args.timeout, "--timeout")  # before the job is sent: a job nobody follows is not started
    address = args.address or jobs.DEFAULT_ADDRESS
    job_id = jobs.submit(command, address, args.install, args.submission_id, check_command=_check_command)
    print(f"submitted job {job_id} to {address}: python -m coin_app {' '.join(command)}")
    print(f"  follow it: python -m coin_app job logs {job_id} --address {address}")
    if not args.wait:
        print(job_id)
        return 0
    try:
        state = jobs.wait(job_id, address, args.timeout)
    except ValueError:  # --wait's time ran out: the job goes on, and that is said
        print(
            f"job {job_id} still runs after --timeout {args.timeout:g} s; stop it: python -m coin_app job stop {job_id} --address {address}"
        )
        raise
    print(f"\njob {job_id} ended: {state}")
    return 0 if state == "SUCCEEDED" else 1


def cmd_job(args: argparse.Namespace) -> int:
    """Status, logs or stop of a submitted job (``ray job status|logs|stop``)."""

    try:
        if args.action == "status":
            print(jobs.status(args.job_id, args.address))
        elif args.action == "logs":
            print(jobs.logs(args.job_id, args.address), end="")
        else:
            print(f"stop requested for {args.job_id}" if jobs.stop(args.job_id, args.address) else f"{args.job_id} was not running")
    except RuntimeError as exc:  # the job server's answer for an unknown id
        raise ValueError(f"job {args.job_id}: {exc}") from exc
    return 0
