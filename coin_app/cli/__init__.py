"""Command line: ``python -m coin_app <command> ...`` (``--help`` on any command).

Parsing imports neither Ray nor torch: each command's module (``drive``, ``train``, ``evaluate``,
``sweeps``, ``cluster``) is imported when that command runs (``benchmarks/cli_latency.py``).
"""

from coin_app.cli.entry import main, one_line
from coin_app.cli.parser import build_parser

__all__ = ["build_parser", "main", "one_line"]
