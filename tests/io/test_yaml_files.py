"""Config YAML reading (``msf_torch.io.yaml_files``) and the loaders built on it.

* YAML 1.2 core-schema scalars: ``1e-4`` is a float (PyYAML's YAML 1.1 resolver leaves it a
  string), ``on`` / ``yes`` stay strings, ``true`` is a bool, integers stay integers;
* what is wrong with the file itself is a ``DataError`` with the line: a syntax error, a key
  given twice (both lines), a folder given for a file;
* an unknown front-end or smoother key names the closest known keys and its line;
* ``load_sequence_config``: the YAML's values win over a dataset's metadata, the metadata
  fills the rest (the trap of ``config_for_sequence(..., explicit=set())``).
"""

from __future__ import annotations

import pytest
import yaml

from msf_torch.backend.window import load_smoother_config
from msf_torch.frontend.config import EskfConfig, load_config, load_sequence_config
from msf_torch.io.errors import DataError
from msf_torch.io.yaml_files import ConfigLoader, did_you_mean, read_yaml


def test_core_schema_scalars() -> None:
    text = "a: 1e-4\nb: 5E+3\nc: .5e-3\nd: 3\ne: on\nf: yes\ng: true\nh: 2.5\ni: -.inf\nj: 1_000\n"
    loaded = yaml.load(text, Loader=ConfigLoader)  # noqa: S506
    assert loaded == {
        "a": 1e-4,
        "b": 5000.0,
        "c": 5e-4,
        "d": 3,
        "e": "on",
        "f": "yes",
        "g": True,
        "h": 2.5,
        "i": float("-inf"),
        "j": 1000,
    }
    assert type(loaded["d"]) is int and type(loaded["a"]) is float
    assert yaml.safe_load("a: 1e-4")["a"] == "1e-4"  # why the loader exists


def test_file_problems_name_the_line(tmp_path) -> None:
    twice = tmp_path / "twice.yaml"
    twice.write_text("zupt: true\ngyro_noise_density: 1e-4\nnested:\n  a: 1\n  a: 2\n")
    with pytest.raises(DataError) as err:
        read_yaml(twice)
    assert (err.value.line, err.value.field) == (5, "nested.a")
    assert "also on line 4" in err.value.problem
    broken = tmp_path / "broken.yaml"
    broken.write_text("zupt: true\nsmoother:\n  window_size: [\n")
    with pytest.raises(DataError, match="not valid YAML"):
        read_yaml(broken)
    with pytest.raises(DataError, match="is a folder"):
        read_yaml(tmp_path)
    with pytest.raises(DataError, match="no such file"):
        read_yaml(tmp_path / "missing.yaml")
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load_config(empty) == EskfConfig()


def test_unknown_keys_suggest_the_closest(tmp_path) -> None:
    typo = tmp_path / "typo.yaml"
    typo.write_text("zupt: true\ngyro_noise_densty: 1e-4\n")
    with pytest.raises(DataError) as err:
        load_config(typo)
    assert err.value.line == 2
    assert "did you mean 'gyro_noise_density'" in str(err.value)
    smoother = tmp_path / "smoother.yaml"
    smoother.write_text("smoother:\n  window_sise: 20\n")
    with pytest.raises(DataError) as err:
        load_smoother_config(smoother)
    assert (err.value.line, err.value.field) == (2, "smoother.window_sise")
    assert "did you mean 'window_size'" in str(err.value)
    assert did_you_mean("qwertyuiop", ["window_size"]) == ""


def test_scientific_notation_and_on_in_a_config(tmp_path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("gyro_noise_density: 1e-4\nnhc: on\n")
    cfg = load_config(path)
    assert cfg.gyro_noise_density == pytest.approx(1e-4) and cfg.nhc == "on"


def test_sequence_config_keeps_the_yaml_over_metadata(tmp_path) -> None:
    meta = {
        "imu_noise": {"gyro_noise_density": 9.9e-5, "accel_noise_density": 2.2e-3},
        "sensor": {"wheel_track_m": 0.55},
    }
    path = tmp_path / "robot.yaml"
    path.write_text("gyro_noise_density: 5.0e-3\nwheel_track_m: 0.9\n")
    cfg = load_sequence_config(meta, path)
    assert (cfg.gyro_noise_density, cfg.wheel_track_m) == (5e-3, 0.9)
    assert cfg.accel_noise_density == 2.2e-3  # not in the YAML: the metadata's
    assert load_sequence_config(meta, None, wheel_track_m=0.7).wheel_track_m == 0.7
    assert load_sequence_config(meta).gyro_noise_density == 9.9e-5
