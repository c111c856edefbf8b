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


@pytest.mark.parametrize("text, key", [("123: 4\n", "123"), ("on: true\n", "on"), ("carve:\n  1.5: 2\n", "1.5"),
                                       ("null: 3\n", "null"), ("yes:\n  resolution: 4\n", "yes")])
def test_a_key_that_is_not_text_is_named(tmp_path, text, key):
    """``123: 4`` or ``on: true`` (YAML 1.1 reads ``on`` as True) was an AttributeError traceback, in a
    --config file and in a run's saved config.yaml (export): one ConfigError naming the key as written."""
    from carvi_torch.config import read_run_config

    p = tmp_path / "c.yaml"
    p.write_text(text)
    for read in (load_config, read_run_config):
        with pytest.raises(ConfigError, match=f"^{p}: config key '{key}' at line [12] is not a setting name") as e:
            read(p)
        assert "\n" not in str(e.value)


def test_a_key_that_is_not_text_is_named_in_a_mapping_too():
    with pytest.raises(ConfigError, match="^config key 123 is not a setting name"):
        Config().override({123: 4})
    with pytest.raises(ConfigError, match="^config key True is not a setting name"):
        Config().override({"carve": {True: 4}})


def test_a_misspelt_section_is_suggested(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("carv: {resolution: 16}\n")
    with pytest.raises(ConfigError, match=r"^unknown config key 'carv'; did you mean 'carve'\?"):
        load_config(p)
    with pytest.raises(ConfigError, match=r"did you mean 'viewpoints' or "):
        Config().override({"viewpoint": {"refine": False}})


@pytest.mark.parametrize("item, value", [
    ("out=007", "007"), ("out=no", "no"), ("out=1.50", "1.50"), ("out=[a, b]", "[a, b]"), ("out=on", "on"),
    ("out=runs/2024-01-01", "runs/2024-01-01"), ("out=a: b", "a: b"), ("out=x #1", "x #1"),
    ("out='007'", "007"), ('out="null"', "null"), ("device=cuda:1", "cuda:1"), ("references=test", "test"),
    ("data=1e3", "1e3"), ("gt=true", "true"), ("ray_address=10.0.0.1:6379", "10.0.0.1:6379"),
])
def test_text_settings_keep_the_text_as_typed(item, value):
    """``out=007`` was the folder '7', ``out=no`` 'False', ``out=1.50`` '1.5', ``out=[a, b]`` "['a', 'b']": a
    text setting takes the text as typed (quotes around all of it removed)."""
    key, _ = item.split("=", 1)
    cfg = Config().override([item])
    assert getattr(cfg, key) == value


@pytest.mark.parametrize("text, value", [
    ("out: 007\n", "007"), ("out: 1.50\n", "1.50"), ("out: 2024-01-01\n", "2024-01-01"), ("out: '007'\n", "007"),
    ("out: 1_000\n", "1_000"), ("data: 0x1F\n", "0x1F"), ("device: cpu\n", "cpu"),
])
def test_text_settings_of_a_file_keep_numbers_as_written(tmp_path, text, value):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    key = text.split(":")[0]
    assert getattr(load_config(p), key) == value


@pytest.mark.parametrize("text, key", [
    ("out: no\n", "out"), ("out: [a, b]\n", "out"), ("out: {a: 1}\n", "out"), ("data: yes\n", "data"),
    ("gt: on\n", "gt"), ("references: [test]\n", "references"), ("classes: [car, [a]]\n", "classes"),
    ("classes: [car, true]\n", "classes"),
])
def test_text_settings_of_a_file_refuse_lists_mappings_and_booleans(tmp_path, text, key):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=f"^{key}: expected text, got .*quote it") as e:
        load_config(p)
    assert "\n" not in str(e.value)


def test_text_settings_refuse_other_python_values():
    assert Config().override({"out": Path("runs") / "x"}).out == str(Path("runs") / "x")
    for value in (7, 1.5, True, ["a"]):
        with pytest.raises(ConfigError, match="^out: expected text"):
            Config().override({"out": value})


@pytest.mark.parametrize("items, key, value", [
    (["classes=[car,chair]"], "classes", ["car", "chair"]), (["classes=car,chair"], "classes", ["car", "chair"]),
    (["classes=car, chair"], "classes", ["car", "chair"]), (["classes=[car, 007]"], "classes", ["car", "007"]),
    (["classes=007"], "classes", ["007"]), ({"classes": "car"}, "classes", ["car"]),
    ({"classes": ["car", "chair"]}, "classes", ["car", "chair"]),
    (["stage=cameras"], "stage", "cameras"), (["frame=symmetry+up"], "viewpoints.frame", "symmetry+up"),
    (["sfm_polish=alternate"], "viewpoints.sfm_polish", "alternate"), (["mesh_format=obj"], "mesh.format", "obj"),
    ([" stage = cameras "], "stage", "cameras"), (["silhouette_weight=1e-3"], "viewpoints.silhouette_weight", 1e-3),
    (["resolution=40.0"], "carve.resolution", 40), (["resolution=1_000"], "carve.resolution", 1000),
])
def test_enums_lists_and_numbers_still_parse(items, key, value):
    from carvi_torch.config import _get

    assert _get(Config().override(items), key) == value


def test_lists_and_enums_of_a_file(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("classes: [car, 007]\nstage: cameras\nmesh: {format: obj}\n")
    cfg = load_config(p)
    assert cfg.classes == ["car", "007"] and cfg.stage == "cameras" and cfg.mesh.format == "obj"


@pytest.mark.parametrize("item", ["data=null", "gt=null", "classes=null", "ray_address=null", "data=~", "data=",
                                  "classes=NULL"])
def test_null_unsets_an_optional_setting(item):
    key = item.split("=")[0]
    cfg = Config().override(["data=a.json", "gt=g.json", "classes=car", "ray_address=auto"]).override([item])
    assert getattr(cfg, key) is None


@pytest.mark.parametrize("item", ["out=null", "out=", "seed=null", "stage=null"])
def test_null_is_refused_where_a_setting_needs_a_value(item):
    with pytest.raises(ConfigError, match="cannot be empty"):
        Config().override([item])


def test_a_key_given_twice_in_a_file_is_refused(tmp_path):
    """A duplicate key silently took the last value."""
    p = tmp_path / "c.yaml"
    p.write_text("resolution: 16\nproposals: 3\nresolution: 20\n")
    with pytest.raises(ConfigError, match=f"^{p}: config key 'resolution' is given twice \\(lines 1 and 3\\)"):
        load_config(p)
    p.write_text("carve:\n  resolution: 16\n  resolution: 20\n")
    with pytest.raises(ConfigError, match="config key 'resolution' is given twice"):
        load_config(p)
    p.write_text("resolution: 16\ncarve:\n  resolution: 20\n")
    with pytest.raises(ConfigError, match=r"^carve\.resolution is given twice \('resolution' and "
                                          r"'carve\.resolution'\)"):
        load_config(p)


def test_a_merge_key_may_be_overridden(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("carve:\n  <<: {resolution: 16, imprint: false}\n  resolution: 20\n")
    cfg = load_config(p)
    assert cfg.carve.resolution == 20 and cfg.carve.imprint is False


def test_a_key_given_twice_on_the_command_line_takes_the_last():
    assert Config().override(["resolution=16", "carve.resolution=20"]).carve.resolution == 20


def test_integers_are_decimal(tmp_path):
    """``seed=010`` was 8 (YAML 1.1 octal): an integer is read in decimal, leading zeros and all."""
    assert Config().override(["seed=010"]).seed == 10
    p = tmp_path / "c.yaml"
    p.write_text("seed: 010\nresolution: 0040\n")
    cfg = load_config(p)
    assert cfg.seed == 10 and cfg.carve.resolution == 40
    for text in ("seed: 0x10\n", "seed: 1:30\n"):
        p.write_text(text)
        with pytest.raises(ConfigError, match=f"^seed: expected int, got {text[6:-1]}$"):
            load_config(p)


@pytest.mark.parametrize("value, expect", [("1", True), ("0", False), ('"1"', True), ("yes", True), ("Off", False),
                                           ("true", True), ("FALSE", False)])
def test_booleans_read_alike_typed_or_in_a_file(tmp_path, value, expect):
    """``preview=1`` was refused while ``preview="1"`` was true."""
    assert Config().override([f"preview={value}"]).preview is expect
    p = tmp_path / "c.yaml"
    p.write_text(f"preview: {value}\n")
    assert load_config(p).preview is expect


@pytest.mark.parametrize("value", ["2", "-1", "1.0", "maybe", "[1]"])
def test_other_booleans_are_refused(value):
    with pytest.raises(ConfigError, match="^preview: expected bool"):
        Config().override([f"preview={value}"])


def test_a_number_of_a_file_is_a_class_name_as_written(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("classes: 007\n")
    assert load_config(p).classes == ["007"]


def test_other_yaml_readers_are_left_as_they_were():
    """The config files' reader keeps numbers' text on its own loader: PyYAML's safe loader is unchanged."""
    assert yaml.safe_load("a: 010\nb: 2024-01-01\n") == {"a": 8, "b": __import__("datetime").date(2024, 1, 1)}


def test_flattened_settings_are_plain_values(tmp_path):
    """What flatten_settings gives (settings_changed, summary.json's record, the tools) dumps as YAML and JSON."""
    from carvi_torch.config import flatten_settings, read_run_config, read_yaml

    p = tmp_path / "config.yaml"
    p.write_text("out: 007\ncarve: {resolution: 040}\nsilhouette_weight: 1.50\nclasses: [007]\n")
    flat = flatten_settings(read_yaml(p))
    assert yaml.safe_load(yaml.safe_dump(flat)) == flat == {"out": 7, "carve.resolution": 40,
                                                            "viewpoints.silhouette_weight": 1.5, "classes": [7]}
    cfg = read_run_config(p)  # the saved file's text, as load_config reads it
    assert (cfg.out, cfg.carve.resolution, cfg.classes) == ("007", 40, ["007"])


def test_blanks_around_a_typed_text_value_are_dropped_unless_quoted():
    """``device=cpu `` (a blank the shell passed on) was the device ``'cpu '``; a quoted value keeps its blanks."""
    cfg = load_config(None, ["device=cpu ", "references= train", "out=' x '"])
    assert (cfg.device, cfg.references, cfg.out) == ("cpu", "train", " x ")
