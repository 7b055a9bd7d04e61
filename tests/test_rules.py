"""The driving rules (coin_app/sim/rules.py): each rule by hand-computed values, and the simulator's recorded episodes bit for bit."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from coin_app.sim.scenes import DRIVING_SCENARIOS

DATA = Path(__file__).parent / "data"


def _record_module():
    spec = importlib.util.spec_from_file_location("rules_record", DATA / "rules_record.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_long_seeded_episodes_give_the_recorded_rewards_terminations_and_infos_bit_for_bit(scenario):
    record_module = _record_module()
    with np.load(record_module.RECORD) as f:
        want = {k.split("/", 1)[1]: f[k] for k in f.files if k.startswith(f"{scenario}/")}
    got = record_module.episode(scenario)
    assert np.array_equal(got["first_pos"], want["first_pos"]), (
        "the first step's positions differ from the record: the dynamics (or this machine's floating point) changed, not "
        "only the rules; rewrite the record with tests/data/rules_record.py if the change is meant"
    )
    flags = want["flags"].sum(0)
    assert flags[0] > 0 and flags[2] > 0 and want["spawned"].sum() > 0  # the record holds arrivals, exits and respawns
    assert got.keys() == want.keys()
    for key in want:
        assert got[key].dtype == want[key].dtype and np.array_equal(got[key], want[key]), key
