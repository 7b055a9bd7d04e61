"""Conformance of every driving scenario record (coin_app/sim/scenes.py): its facts hold and its env behaves."""

import importlib.util
import inspect

import pytest

from coin_app.adapters.rllib_env import ENV_IDS
from coin_app.sim.config import DEFAULT_NUM_AGENTS, OBS_LAYOUTS, SPAWN_CAPACITY, make_config
from coin_app.sim.road_map import MAP_DIR, load_map
from coin_app.sim.scenes import DRIVING_SCENARIOS, SCENES, scene

PAPER_COUNTS = {"intersection": 30, "roundabout": 40, "bottleneck": 20}  # COIN Table 5.1, written here independently


def test_the_records_are_the_papers_three_scenes():
    assert {n: s.default_vehicles for n, s in SCENES.items()} == PAPER_COUNTS == DEFAULT_NUM_AGENTS
    with pytest.raises(ValueError, match="unknown scenario 'highway'; allowed: intersection, roundabout, bottleneck"):
        scene("highway")


@pytest.mark.parametrize("name", DRIVING_SCENARIOS)
def test_a_scene_has_its_map_config_env_id_and_grid(name):
    s = scene(name)
    assert (MAP_DIR / s.map_file).is_file() and load_map(name).name == name
    assert make_config(name).num_agents == s.default_vehicles
    assert ENV_IDS[s.env_id] == name
    assert s.default_vehicles in s.generalization_counts and list(s.generalization_counts) == sorted(set(s.generalization_counts))
    assert len(load_map(name).spawn_slot_lane) == SPAWN_CAPACITY >= max(s.generalization_counts)  # the map's spawn slots
    assert s.metadrive_obs_layout in OBS_LAYOUTS and make_config(name).obs_layout == "standard"  # native: the paper's 91
    if importlib.util.find_spec("metadrive") is not None:  # the optional backend: the class it rebuilds exists there
        import metadrive

        cls = getattr(metadrive, s.metadrive_class)
        # MetaDrive's reward flips the progress sign on negative roads where the scene's env inherits it (its bottleneck
        # overrides reward_function without the flip); its observation is 96 numbers where it adds the two detectors
        flips = "is_negative_road()" in inspect.getsource(inspect.unwrap(cls.reward_function))
        assert flips == s.progress_sign_flip
        assert cls.default_config()["vehicle_config"]["side_detector"]["num_lasers"] == (
            4 if s.metadrive_obs_layout == "bottleneck96" else 0
        )
