"""``terrainmap config``: print the effective configuration as TOML."""

from __future__ import annotations

import click

from terrainmap.config import load_config

from .options import config_options


@click.command()
@config_options
def config(config_path: str | None, overrides: tuple[str, ...]) -> None:
    """Print the effective config (defaults < --config TOML < --set) as TOML."""
    click.echo(load_config(config_path, overrides).to_toml(), nl=False)
