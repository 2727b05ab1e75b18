"""docs/configuration.md is generated from the config dataclasses' field docs and is current."""

import dataclasses
import inspect
from pathlib import Path

import pytest

from imagine import config
from imagine.config_reference import (
    COMMAND,
    config_classes,
    configuration_markdown,
    field_docs,
)

PAGE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_the_page_is_current():
    assert PAGE.read_text() == configuration_markdown(), (
        f"docs/configuration.md is stale: regenerate it with `{COMMAND}`"
    )


def test_every_agent_field_is_on_the_page_with_its_docstring():
    page = configuration_markdown()
    docs = {
        d.name: d.doc for d in field_docs(config_classes(inspect.getsource(config))["AgentConfig"])
    }
    for field in dataclasses.fields(config.AgentConfig):
        first_words = " ".join(docs[field.name].split()[:6])
        assert f"- **`{field.name}`**: " in page, field.name
        line = next(x for x in page.splitlines() if x.startswith(f"- **`{field.name}`**: "))
        assert first_words in line, field.name


def test_every_config_class_and_preset_table_is_there():
    page = configuration_markdown()
    assert page.index("## AgentConfig") < page.index("## VisionConfig")
    assert "| field | paper (default) | fast baseline | fast augmented | smoke |" in page
    assert "| field | paper (default) | fast | smoke |" in page
    assert COMMAND in page.splitlines()[2]


def test_a_field_without_a_docstring_is_an_error():
    source = '''
@dataclass(frozen=True)
class ToyConfig:
    """A toy."""

    documented: int = 1
    """Has one."""
    undocumented: float = 0.5
    last: str = "x"
    """Has one too."""
'''
    with pytest.raises(ValueError, match=r"ToyConfig\.undocumented has no docstring"):
        field_docs(config_classes(source)["ToyConfig"])


def test_a_last_field_without_a_docstring_is_an_error():
    source = "@dataclass\nclass C:\n    x: int = 1\n"
    with pytest.raises(ValueError, match=r"C\.x has no docstring"):
        field_docs(config_classes(source)["C"])
