"""config.py: defaults, YAML file, key=value overrides, validation, saved config."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from carvi_torch.config import Config, ConfigError, load_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("setting, run_device, objects, expect", [
    ([], "cuda", 48, "cpu"),  # auto: a small class on a GPU run makes its viewpoints on the CPU
    ([], "cuda", 999, "cpu"),
    ([], "cuda", 1000, "cuda"),  # from gpu_min_objects on, the run's device
    ([], "cuda:1", 9087, "cuda:1"),
    ([], "cpu", 48, "cpu"),
    (["viewpoints.gpu_min_objects=0"], "cuda", 1, "cuda"),
    (["viewpoints.gpu_min_objects=50"], "cuda", 49, "cpu"),
    (["viewpoints.device=run"], "cuda", 48, "cuda"),
    (["viewpoints.device=cpu"], "cuda", 9087, "cpu"),
    (["viewpoint_processes=2", "viewpoints.device=run"], "cuda", 9087, "cpu"),  # processes work on the CPU
])
def test_viewpoint_device(setting, run_device, objects, expect):
    import torch

    cfg = Config().override(setting)
    assert cfg.viewpoint_device(torch.device(run_device), objects) == torch.device(expect)


def test_overrides_are_typed():
    cfg = Config().override(["resolution=32", "imprint=false", "silhouette_weight=2", "classes=car,chair",
                             "device=cpu", "data="])
    assert cfg.carve.resolution == 32 and cfg.carve.imprint is False and cfg.viewpoints.silhouette_weight == 2.0
    assert cfg.classes == ["car", "chair"] and cfg.data is None


@pytest.mark.parametrize("item", ["nokey", "resolution=abc", "resolution=1.5", "imprint=maybe", "stage=mesh",
                                  "unknown_key=1", "canvas_margin=0.7", "silhouette_robust=-0.1",
                                  "refine_min_support=1.5", "refine_min_support=-0.1", "resolution=3",
                                  "resolution=2049"])
def test_bad_overrides(item):
    with pytest.raises(ConfigError):
        Config().override([item])


@pytest.mark.parametrize("item, says", [
    ("seed=-1", "seed must be in [0, 9223372036854775807]"),
    ("seed=9223372036854775808", "seed must be in [0, 9223372036854775807]"),
    ("silhouette_weight=-1", "silhouette_weight must be >= 0"),
    ("cluster_widen_step_deg=0", "cluster_widen_step_deg must be > 0"),
    ("cluster_widen_step_deg=-5", "cluster_widen_step_deg must be > 0"),
    ("cluster_max_threshold_deg=10", "cluster_max_threshold_deg must be in [15.0, 45]"),
    ("cluster_max_threshold_deg=0", "cluster_max_threshold_deg must be in [15.0, 45]"),
    ("cluster_max_threshold_deg=60", "cluster_max_threshold_deg must be in [15.0, 45]"),
    ("cluster_threshold_deg=60", "cluster_threshold_deg must be in (0, 45]"),
    ("plane_size=1", "plane_size must be in [2, 1024]"),
    ("viewpoints.gpu_min_objects=-1", "gpu_min_objects must be >= 0"),
    ("viewpoints.device=gpu", "viewpoints.device"),
    ("plane_size=100000", "plane_size must be in [2, 1024]"),
])
def test_settings_the_run_cannot_use_are_refused_up_front(item, says):
    """Each of these failed late (a traceback, or a class failing after its viewpoints) or ran unbounded."""
    with pytest.raises(ConfigError) as e:
        Config().override([item])
    assert says in str(e.value)


def test_settings_at_their_bounds_are_accepted():
    cfg = Config().override(["seed=9223372036854775807", "silhouette_weight=0", "cluster_threshold_deg=45",
                             "cluster_max_threshold_deg=45", "plane_size=2"])
    assert cfg.seed == 2 ** 63 - 1 and cfg.select.plane_size == 2


def test_file_then_cli(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("resolution: 40\nproposals: 5\n")
    cfg = load_config(p, ["proposals=7"])
    assert cfg.carve.resolution == 40 and cfg.surrogates.proposals == 7


def test_bad_file(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("resolution: [1, 2\n")
    with pytest.raises(ConfigError, match="malformed YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_a_malformed_file_is_one_line_with_its_place(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("carve:\n  resolution: [16\n x: :\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{p}: malformed YAML at line 3, column 3: ")
    p.write_bytes(b"resolution: \xe9\n")  # Latin-1, not UTF-8
    with pytest.raises(ConfigError, match=r"c\.yaml: not UTF-8 text"):
        load_config(p)


def test_a_byte_order_mark_is_accepted(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_bytes(b"\xef\xbb\xbfresolution: 40\n")
    assert load_config(p).carve.resolution == 40


def test_default_yaml_matches_dataclass():
    """configs/default.yaml lists every field with the dataclass default, and its comments are the fields'
    docstrings: it is ``Config().to_yaml()`` exactly (regenerate it so when a docstring changes)."""
    text = (ROOT / "configs" / "default.yaml").read_text()
    assert yaml.safe_load(text) == Config().to_dict()
    assert text == Config().to_yaml()


def test_to_yaml_round_trip():
    cfg = Config().override(["resolution=33", "classes=[a, b]"])
    assert yaml.safe_load(cfg.to_yaml()) == cfg.to_dict()
    assert "# Voxel grid steps per axis." in cfg.to_yaml()


@pytest.mark.parametrize("text", ["carve: 5\n", "carve: [resolution, 48]\n", "carve: yes\n"])
def test_a_section_given_a_scalar_is_named_as_a_section(tmp_path, text):
    """``carve: 5`` names a known section the wrong way: the message says so (not 'unknown config key')."""
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"^'carve' is a section of settings, not a setting: .*carve\.resolution="):
        load_config(p)
    with pytest.raises(ConfigError, match="'carve' is a section of settings"):
        Config().override(["carve=5"])


def test_an_empty_section_sets_nothing(tmp_path):
    """A section whose every key is commented out (``carve:`` with nothing under it) keeps the defaults."""
    p = tmp_path / "c.yaml"
    p.write_text("carve:\n#  resolution: 48\nproposals: 5\n")
    cfg = load_config(p)
    assert cfg.carve.resolution == Config().carve.resolution and cfg.surrogates.proposals == 5
