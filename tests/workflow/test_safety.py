"""Safety: models load from safetensors only, remote code only on request, `mlflow ui` on 127.0.0.1."""

from __future__ import annotations


import pytest
from conftest import ROOT

from pipeline.lm.model_settings import ModelSettings
from jobs import toy_config



def test_models_load_from_safetensors_only_and_remote_code_only_on_request():
    import inspect

    from pipeline.lm import models as modeling

    source = inspect.getsource(modeling.load_model)
    assert "use_safetensors=True" in source and "trust_remote_code=trust_remote_code" in source
    assert inspect.signature(modeling.load_model).parameters["trust_remote_code"].default is False
    assert inspect.signature(modeling.load_tokenizer).parameters["trust_remote_code"].default is False
    assert ModelSettings().trust_remote_code is False   # the base every model preset starts from
    for option in sorted((ROOT / "conf" / "model").glob("*.yaml")):
        assert toy_config(ROOT / "outputs", f"model={option.stem}", "model.path=x").model.trust_remote_code is False, option.name


def _readme_commands(text: str) -> list[str]:
    """Shell commands in a Markdown text: the lines of fenced blocks and the inline code spans."""
    import re

    fenced = re.findall(r"```[^\n]*\n(.*?)```", text, flags=re.S)
    lines = [line for block in fenced for line in block.replace("\\\n", " ").splitlines()]
    inline = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    return [command.strip().lstrip("$ ") for command in lines + inline]


def test_the_readme_binds_mlflow_ui_to_localhost():
    readme = ROOT / "README.md"
    if not readme.exists():
        pytest.skip("README.md not written yet")
    commands = [c for c in _readme_commands(readme.read_text()) if c.startswith(("mlflow ui", "mlflow server"))]
    assert commands, "the README should say how to open the MLflow UI"
    for command in commands:
        assert "--host 127.0.0.1" in command or "-h 127.0.0.1" in command, command
