"""The native -> MetaDrive gap table on hand-built episodes: only shared episodes enter, gaps by hand."""

import numpy as np
import pandas as pd
import pytest

from coin_app.evaluation.protocol import read_results
from coin_app.evaluation.transfer import to_markdown, transfer_table


def _rows(backend, method, ckpt, seeds, success, travel):
    return pd.DataFrame(
        {
            "method": method,
            "variant": "default",
            "trained_seed": 0,
            "test_seed": seeds,
            "scenario": "intersection",
            "agent_count": 4,
            "trained_agent_count": 4,
            "backend": backend,
            "success_rate": success,
            "avg_travel_steps": travel,
            "checkpoint": ckpt,
        }
    )


def test_gap_is_over_the_shared_episodes_of_each_model():
    native = pd.concat(
        [
            _rows("native", "cig_td3", "a", [10, 11, 12], [1.0, 0.5, 0.0], [100.0, np.nan, 300.0]),
            _rows("native", "itd3", "b", [10, 11, 12], [0.25, 0.25, 1.0], [200.0, 220.0, 240.0]),
            # another agent count of the same model is not the training count: left out
            _rows("native", "cig_td3", "a", [10, 11], [0.0, 0.0], [1.0, 1.0]).assign(agent_count=8),
        ]
    )
    moved = pd.concat(
        [
            _rows("metadrive", "cig_td3", "a", [10, 11], [0.5, 0.5], [120.0, 150.0]),
            _rows("metadrive", "itd3", "b", [10, 11], [0.0, 0.5], [np.nan, 260.0]),
        ]
    )
    t = transfer_table(native, moved, metrics=("success_rate", "avg_travel_steps")).set_index(["label", "metric"])
    # cig_td3 on seeds 10, 11: native (1 + 0.5) / 2, metadrive (0.5 + 0.5) / 2
    assert t.loc[("cig_td3", "success_rate")][["native", "transfer", "gap", "n"]].tolist() == pytest.approx([0.75, 0.5, -0.25, 2])
    # travel steps: only seed 10 has a value on both sides
    assert t.loc[("cig_td3", "avg_travel_steps")][["native", "transfer", "gap", "n"]].tolist() == pytest.approx([100.0, 120.0, 20.0, 1])
    assert t.loc[("itd3", "success_rate")][["native", "transfer", "gap"]].tolist() == pytest.approx([0.25, 0.25, 0.0])
    assert t.loc[("itd3", "avg_travel_steps")][["native", "transfer", "n"]].tolist() == pytest.approx([220.0, 260.0, 1])
    md = to_markdown(transfer_table(native, moved, metrics=("success_rate",)), "metadrive")
    assert "| cig_td3 | 2 | 75 / 50 (-25) |" in md and "| itd3 | 2 | 25 / 25 (+0) |" in md


def test_results_tables_written_before_the_backend_column_read_as_native(tmp_path):
    old = _rows("native", "cig_td3", "a", [10], [1.0], [100.0]).drop(columns="backend")
    old[["efficiency", "safety"]] = 0.5
    path = tmp_path / "results.csv"
    old.to_csv(path, index=False)
    table = read_results(path)
    assert list(table["backend"]) == ["native"]
    assert list(table.columns).index("backend") == list(table.columns).index("trained_agent_count") + 1


def test_a_transfer_table_is_refused_as_a_source_of_native_results(tmp_path):
    moved = _rows("metadrive", "cig_td3", "a", [10], [1.0], [100.0])
    moved[["efficiency", "safety"]] = 0.5
    path = tmp_path / "transfer_results.csv"
    moved.to_csv(path, index=False)
    with pytest.raises(ValueError, match="holds metadrive episodes \\(a transfer table\\); allowed: a results table of native episodes"):
        read_results(path)


def test_transfer_to_metadrive_without_the_package_is_refused_before_any_work(monkeypatch):
    from coin_app.evaluation import report

    monkeypatch.setattr(report, "metadrive_available", lambda: False)
    with pytest.raises(ValueError, match="--transfer metadrive needs the metadrive-simulator package, which is not installed"):
        report.ReportOptions(transfer="metadrive").check()
    report.ReportOptions().check()  # no transfer: nothing to install
