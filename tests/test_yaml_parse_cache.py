"""The test session's YAML parse cache (`helpers.cache_yaml_parses`, installed by conftest.py) must not
change what omegaconf loads: every load is a fresh, independent copy, an edited file parses afresh,
and a file that fails to parse is still reported with its name."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf, omegaconf

import helpers


def test_the_cache_is_installed_and_each_load_is_independent(tmp_path):
    assert isinstance(omegaconf.yaml, helpers._ParsedYaml)
    path = tmp_path / "a.yaml"
    path.write_text("a: {b: [1, 2.5e-3]}\nc: x\n")
    first, second = OmegaConf.load(path), OmegaConf.load(path)
    first.a.b.append(3)
    assert OmegaConf.to_container(second) == {"a": {"b": [1, 2.5e-3]}, "c": "x"}
    path.write_text("a: {b: [4]}\nc: y\n")
    assert OmegaConf.to_container(OmegaConf.load(path)) == {"a": {"b": [4]}, "c": "y"}


def test_a_file_that_fails_to_parse_is_still_named(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("a: 1\na: 2\n")  # a duplicate key: omegaconf's loader refuses it
    for _ in range(2):  # (not stored: the second load fails the same way)
        with pytest.raises(Exception, match="duplicate key a") as info:
            OmegaConf.load(path)
        assert "bad.yaml" in str(info.value)
