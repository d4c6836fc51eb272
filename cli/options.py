"""Options shared by several commands, defined once."""

from __future__ import annotations

from collections.abc import Callable

import click


def config_options(func: Callable) -> Callable:
    """``--config PATH.toml`` and repeatable ``--set section.field=value``."""
    func = click.option(
        "--set",
        "overrides",
        multiple=True,
        metavar="SECTION.FIELD=VALUE",
        help="Override one config field, e.g. --set terrain.control_points_x=15 (repeatable).",
    )(func)
    return click.option(
        "--config", "config_path", type=click.Path(dir_okay=False), default=None, help="TOML config file."
    )(func)
