"""The README's promises: its two set-up commands exist and CI runs the test one, every command it
shows is a command of the CLI, and every config field it names exists; the last two hold for the
text moved from it to docs/*.md too. (The commands themselves run in the CLI, process and
evaluation tests.)"""

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from terrainmap.cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
DOCS = {path.relative_to(ROOT).as_posix(): path.read_text() for path in sorted((ROOT / "docs").glob("*.md"))}
TEXTS = {"README.md": README, **DOCS}


def test_the_docs_the_readme_links_to_are_there():
    assert {"docs/design.md", "docs/accuracy.md", "docs/speed.md"} <= set(DOCS)


def test_two_setup_commands_come_first_and_ci_runs_the_test_one():
    setup = README.split("## Usage")[0]
    assert "make demo" in setup and "make test" in setup
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^demo:", makefile, re.M) and re.search(r"^test:", makefile, re.M)
    assert "make test" in (ROOT / ".ci" / "run").read_text()


@pytest.mark.parametrize(
    "command",
    sorted({c for text in TEXTS.values() for c in re.findall(r"^terrainmap ((?:eval )?[a-z-]+)", text, re.M)}),
)
def test_every_command_in_the_readme_exists(command):
    result = CliRunner().invoke(cli, [*command.split(), "--help"])
    assert result.exit_code == 0, result.output


def test_every_config_field_the_readme_names_exists():
    from terrainmap.config import Config

    config = Config().to_dict()
    for name, text in TEXTS.items():
        for section, field in re.findall(r"`([a-z]+)\.([a-z_]+)(?:=[^`]*)?`", text):
            if section in config:
                assert field in config[section], f"{name} names {section}.{field}"


def test_the_library_example_runs(monkeypatch):
    """The README's Python block runs as written, from the repository's root (the bundled log)."""
    from terrainmap.types import FrameResult

    block = re.search(r"^### Library\n.*?```python\n(.*?)```", README, re.M | re.S).group(1)
    monkeypatch.chdir(ROOT)
    namespace = {}
    exec(compile(block, "README.md", "exec"), namespace)
    assert isinstance(namespace["result"], FrameResult) and namespace["frame"].index == 4  # frames 2 and 4
