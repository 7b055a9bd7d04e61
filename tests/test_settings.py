"""One declaration per setting: the settings classes, their presets and what derives from them."""

import subprocess
import sys
from dataclasses import FrozenInstanceError, dataclass

import pytest

from coin_app.algorithms import registry
from coin_app.algorithms.checks import positive, unit
from coin_app.algorithms.settings import SAME, Settings, redeclare, setting

SPECS_WITH_SETTINGS = sorted(name for name, spec in registry.ALGORITHMS.items() if spec.settings is not None)


@dataclass(frozen=True)
class Parent(Settings):
    rate: float = setting(0.5, unit(), "a rate", reads="the test")
    width: int = setting(8, positive("int"), "a width", reads="the test", official=16)


@dataclass(frozen=True)
class Child(Parent):
    rate: float = redeclare(Parent, "rate", 0.25)
    depth: int = setting(2, positive("int"), "a depth", reads="the child")


def test_a_declaration_carries_default_rule_meaning_reader_and_official_value():
    decl = Parent.declarations()
    assert list(decl) == ["rate", "width"] and decl["rate"].default == 0.5 and decl["rate"].reads == "the test"
    assert decl["width"].official == 16 and decl["width"].differs_from_official() and decl["rate"].official is SAME
    assert Parent.hyperparameters() == {"rate": (0.5, "a rate"), "width": (8, "a width")}


def test_a_child_redeclares_a_default_keeps_the_rule_and_field_order_and_adds_its_own():
    decl = Child.declarations()
    assert list(decl) == ["rate", "width", "depth"]  # an inherited field keeps its place
    assert decl["rate"].default == 0.25 and decl["rate"].rule == unit() and decl["rate"].meaning == "a rate"
    # a parent's preset as a value of the child: its changes over the child's defaults (the redeclared rate stays the child's)
    assert Child.lift(Parent(width=3)) == Child(rate=0.25, width=3, depth=2)
    assert Child.lift(Parent(rate=0.1)) == Child(rate=0.1) and Child.lift(Parent()) == Child()


def test_of_refuses_unknown_keys_and_bad_values_in_one_line():
    assert Parent.of({"width": 4}) == Parent(width=4)
    assert Parent.of({"rate": 0.1}, base=Parent(width=4)) == Parent(rate=0.1, width=4)
    with pytest.raises(ValueError) as err:
        Parent.of({"width": 0})
    assert str(err.value) == "bad value for 'width': 0; allowed: an integer >= 1"
    with pytest.raises(ValueError) as err:
        Parent.of({"widht": 4})
    assert str(err.value) == "unknown Parent key(s) ['widht']; allowed: rate, width"


def test_a_default_its_rule_refuses_is_refused_at_declaration():
    with pytest.raises(ValueError, match="default 2.0 refused by its own rule"):
        setting(2.0, unit(), "a rate", reads="nobody")


def test_values_are_frozen_and_changes_are_the_differences_from_the_defaults():
    p = Parent(width=3)
    with pytest.raises(FrozenInstanceError):
        p.width = 4  # type: ignore[misc]
    assert p.changes() == {"width": 3} and Parent().changes() == {} and p.changes(base=Parent(width=3, rate=0.1)) == {"rate": 0.5}
    assert Parent(rate=1).changes() == {"rate": 1}  # 1 is not the float 1.0's type: shown as a change


@pytest.mark.parametrize("name", SPECS_WITH_SETTINGS)
def test_a_spec_derives_its_keys_quick_and_tiny_from_its_settings_and_presets(name):
    spec = registry.get(name)
    assert spec.keys() == spec.settings.keys()
    assert all(isinstance(p, spec.settings) for p in spec.presets.values())
    assert spec.quick == spec.presets["quick"].changes() and spec.tiny == spec.presets["tiny"].changes()
    for key, d in spec.settings.declarations().items():
        assert d.meaning and d.reads, f"{name}'s {key} has no meaning or reader"
        assert spec.rule(key) is d.rule


def test_the_ppo_family_presets_are_those_of_the_protocols():
    from coin_app.algorithms.ppo_family.settings import PRESETS, PpoSettings

    assert PRESETS["paper"].changes() == {"num_env_runners": 4}  # CoPO's four sampling workers
    assert PRESETS["reduced"].changes() == PRESETS["quick"].changes() == {"hidden": 64}
    smoke = PRESETS["smoke"]
    assert smoke.train_batch_size_per_learner % smoke.rollout_fragment_length == 0  # whole chunks per batch
    assert isinstance(PRESETS["tiny"], PpoSettings) and registry.get("copo").presets["smoke"].hidden == 64


def test_settings_modules_import_neither_ray_nor_torch():
    modules = [registry.get(n).settings.__module__ for n in SPECS_WITH_SETTINGS]
    code = f"import sys\nfor m in {modules!r}: __import__(m)\nprint(sorted({{m.split('.')[0] for m in sys.modules}} & {{'ray', 'torch'}}))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
