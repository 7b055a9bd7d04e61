"""The map extractor (coin_app/backends/map_extract.py) regenerates the committed maps from MetaDrive, byte for byte."""

import json
import subprocess
import sys

import numpy as np
import pytest

from coin_app.backends.map_extract import main
from coin_app.backends.metadrive import metadrive_available
from coin_app.sim.road_map import MAP_DIR, SOLID_LINE_TYPES, load_map
from coin_app.sim.scenes import DRIVING_SCENARIOS, scene


@pytest.mark.skipif(not metadrive_available(), reason="needs the MetaDrive extra (requirements-metadrive.txt)")
def test_the_extractor_regenerates_every_committed_map(tmp_path):
    # its own process: MetaDrive runs one engine per process
    run = subprocess.run([sys.executable, "-m", "coin_app.backends.map_extract", "--out", str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    for name in DRIVING_SCENARIOS:
        file = scene(name).map_file
        # every value exactly (parsed: a zero's sign, which MetaDrive's trigonometry leaves CPU-dependent, is no geometry)
        built, committed = (json.loads(p.read_text()) for p in (tmp_path / file, MAP_DIR / file))
        assert built == committed, f"{file} differs from what MetaDrive builds"


@pytest.mark.skipif(not metadrive_available(), reason="needs the MetaDrive extra (requirements-metadrive.txt)")
def test_the_native_solid_center_line_is_the_bottleneck_coins_patched_metadrive_builds(tmp_path):
    args = ["--scenario", "bottleneck", "--solid-center-line", "--out", str(tmp_path)]
    run = subprocess.run([sys.executable, "-m", "coin_app.backends.map_extract", *args], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    built = json.loads((tmp_path / "bottleneck.json").read_text())["line_segments_physical"]
    assert not [s for s in built if s["type"] == "ROAD_LINE_BROKEN_SINGLE_YELLOW"]
    native = load_map("bottleneck", solid_center_line=True)

    def boxes(p1, p2):  # each box once, its end points in a fixed order, sorted
        ends = np.sort(np.stack([p1, p2], 1).round(4).view("f8,f8"), axis=1).view(float).reshape(-1, 4)
        return ends[np.lexsort(ends.T[::-1])]

    solid = [s for s in built if s["type"] in SOLID_LINE_TYPES]
    got = boxes(np.array([s["p1"] for s in solid]), np.array([s["p2"] for s in solid]))
    assert got.shape == boxes(native.solid_p1, native.solid_p2).shape
    assert np.abs(got - boxes(native.solid_p1, native.solid_p2)).max() < 1e-4  # float32 read-back of MetaDrive's boxes
    assert len(native.line_p1) == len(built)


def test_an_unknown_scene_is_refused_before_metadrive_starts(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--scenario", "highway"])
    assert stop.value.code == 2 and "invalid choice: 'highway'" in capsys.readouterr().err
