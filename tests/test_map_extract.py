"""The map extractor (coin_app/backends/map_extract.py) regenerates the committed maps from MetaDrive, byte for byte."""

import subprocess
import sys

import pytest

from coin_app.backends.map_extract import main
from coin_app.backends.metadrive import metadrive_available
from coin_app.sim.road_map import MAP_DIR
from coin_app.sim.scenes import DRIVING_SCENARIOS, scene


@pytest.mark.skipif(not metadrive_available(), reason="needs the MetaDrive extra (requirements-metadrive.txt)")
def test_the_extractor_regenerates_every_committed_map(tmp_path):
    # its own process: MetaDrive runs one engine per process
    run = subprocess.run([sys.executable, "-m", "coin_app.backends.map_extract", "--out", str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    for name in DRIVING_SCENARIOS:
        file = scene(name).map_file
        assert (tmp_path / file).read_text() == (MAP_DIR / file).read_text(), f"{file} differs from what MetaDrive builds"


def test_an_unknown_scene_is_refused_before_metadrive_starts(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--scenario", "highway"])
    assert stop.value.code == 2 and "invalid choice: 'highway'" in capsys.readouterr().err
