"""The archive's table of trials (``archive_table``): rows and per-method means by hand, and the committed one current."""

import json
from pathlib import Path

import pytest

from coin_app.evaluation.archive import ARCHIVE_FILE, STATUS_FILE, archive_table

DENSE = Path(__file__).resolve().parents[1] / "docs" / "results" / "intersection-30" / "trials"


def _trial(sweep: Path, name: str, scores: list[tuple[str, int, float]], final: str, selected: str, cpu_s: float | None) -> dict:
    (sweep / name).mkdir(parents=True)
    lines = ["method,variant,trained_seed,checkpoint,order,trained_env_steps,validation_success,selected"]
    lines += [f"x,default,0,{c},{i},{steps},{v},{c == selected}" for i, (c, steps, v) in enumerate(scores)]
    (sweep / name / "selection.csv").write_text("\n".join(lines) + "\n")
    return {"final": final, "selected": selected, "env_steps": scores[-1][1], "cpu_s": cpu_s}


def test_rows_in_seed_order_and_means_of_the_selected_checkpoints(tmp_path):
    a, b = tmp_path / "dense-itd3", tmp_path / "dense-cig_td3"
    trials_a = {
        "itd3-s10": _trial(
            a,
            "itd3-s10",
            [("checkpoint_000001", 50, 0.25), ("checkpoint_000002", 100, 0.5)],
            "checkpoint_000002",
            "checkpoint_000002",
            7200.0,
        ),
        "itd3-s2": _trial(
            a,
            "itd3-s2",
            [("checkpoint_000001", 50, 0.75), ("checkpoint_000002", 100, 0.125)],
            "checkpoint_000002",
            "checkpoint_000001",
            1800.0,
        ),
    }
    trials_b = {"cig_td3-s0": _trial(b, "cig_td3-s0", [("checkpoint_000003", 1500, 0.1)], "checkpoint_000003", "checkpoint_000003", None)}
    for sweep, trials in ((a, trials_a), (b, trials_b)):
        (sweep / ARCHIVE_FILE).write_text(json.dumps({"trials": trials, "sources": []}))
    lines = archive_table(tmp_path).splitlines()
    rows = [line for line in lines if line.startswith("| ") and "---" not in line]
    assert rows[1:4] == [
        "| cig_td3-s0 | 1,500 |  | 0.100 | 1,500: 0.100 |",  # sweeps by name: dense-cig_td3 first; no CPU time recorded
        "| itd3-s2 | 100 | 0.500 | 0.125 | 50: 0.750 |",  # seed 2 before seed 10; the selected one is not the final one
        "| itd3-s10 | 100 | 2.000 | 0.500 | 100: 0.500 |",
    ]
    assert rows[5:] == ["| cig_td3 | 1 | 0.100 (0.100–0.100) |", "| itd3 | 2 | 0.625 (0.500–0.750) |"]


def test_the_committed_dense_table_is_the_archives_own():
    """``python -m coin_app archive`` writes it with every run; a hand edit or a stale copy fails here."""
    if not (DENSE / STATUS_FILE).is_file():
        pytest.skip("no dense archive committed")
    assert (DENSE / STATUS_FILE).read_text() == archive_table(DENSE)
