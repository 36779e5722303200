"""The schema declares each key's constraint once (field metadata, one validator) and
docs/config.md's tables of keys are generated from it (diffuser_lab/cli/config_docs.py)."""
import dataclasses
import typing

import pytest
from conftest import ROOT

from diffuser_lab import config
from diffuser_lab.cli import config_docs


def _keys(cls, prefix=""):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}.{f.name}" if prefix else f.name
        sub = config_docs._section_type(hints[f.name])
        if sub is not None:
            yield from _keys(sub, key)
        else:
            yield key, f


def test_config_md_tables_are_generated_from_the_schema():
    text = (ROOT / "docs" / "config.md").read_text()
    assert config_docs.BEGIN in text and config_docs.END in text
    assert config_docs.render(text) == text, "docs/config.md is stale: python -m diffuser_lab.cli.config_docs"
    for key, _ in _keys(config.Config):
        assert f"| `{key}` |" in text, key


def test_one_validator_reads_the_declared_checks():
    """Every declared check is what the error line says; a section built directly is validated too."""
    from diffuser_lab.data.sources import SOURCES

    keys = [*_keys(config.Config), *(kf for e in SOURCES.values() for kf in _keys(e.options, "scene.options"))]
    checked = [(key, f.metadata["check"]) for key, f in keys if "check" in f.metadata]
    assert len(checked) > 120
    assert dict(checked)["graph.k"].expected == ">= 1 (paper: 24)"
    with pytest.raises(config.ConfigError, match=r"^graph\.k=0: expected >= 1 \(paper: 24\)$"):
        config.GraphConfig(k=0)
    from diffuser_lab.data.sources.demo import DemoOptions

    with pytest.raises(config.ConfigError, match=r"^scene\.options\.fov_deg=200\.0: expected in \[10, 150\]$"):
        DemoOptions(fov_deg=200.0)
    # registry names are strings the resolve step checks, not enums of the schema
    named = {key for key, f in _keys(config.Config) if "registry" in f.metadata}
    assert named == {"scene.source", "taxonomy.name", "predictions.source", "method.name", "protocol.name"}
