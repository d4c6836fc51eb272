"""``terrainmap eval``: evaluations that reproduce and extend the paper's."""

from __future__ import annotations

import csv
import io
import json
import math

import click

from terrainmap.config import load_config
from terrainmap.errors import ConfigError

from .options import (
    PLOT_SUFFIXES,
    Finite,
    check_outputs,
    config_options,
    output_file,
    write_text,
    writing,
)
from .source_options import open_options


def _numbers(*, positive: bool = True, whole: bool = False, count: int | None = None):
    """A click callback parsing a comma-separated list of finite numbers (positive, whole,
    exactly ``count`` of them, as asked)."""

    def parse(ctx: click.Context, param: click.Parameter, text: str) -> list[float]:
        try:
            values = [float(v) for v in text.split(",")]  # an empty entry ("1,,2") is no number either
        except ValueError:
            raise click.BadParameter(f"expected comma-separated numbers, got {text!r}") from None
        if not values or not all(
            math.isfinite(v) and (v > 0 or not positive) and (v == int(v) or not whole) for v in values
        ):
            kind = [w for w, on in (("finite", True), ("positive", positive), ("whole", whole)) if on]
            raise click.BadParameter(f"expected {' '.join(['comma-separated', *kind, 'numbers'])}, got {text!r}")
        if count is not None and len(values) != count:
            raise click.BadParameter(f"expected {count} numbers, got {text!r}")
        return values

    return parse


_FIELD_OPTIONS = {"terrain.control_points": "--nets", "terrain.degree": "--degree", "grid.length_m": "--length/--cell",
                  "grid.width_m": "--width/--cell", "grid.cell_size_m": "--cell"}
"""The artificial-obstacle option behind each config field it sets (errors name both)."""


@click.group("eval", short_help="Evaluate: the paper's Fig. 6, robustness, accuracy, stereo.")
def eval_group() -> None:
    """Evaluate terrain estimation: the paper's Fig. 6, robustness, accuracy vs ground truth,
    stereo disparity vs ground truth."""


@eval_group.command("artificial-obstacle")
@click.option("--length", "length_m", type=Finite(min=0, min_open=True), default=22.0, show_default=True,
              help="Area length along x, m.")
@click.option("--width", "width_m", type=Finite(min=0, min_open=True), default=22.0, show_default=True,
              help="Area width along y, m.")
@click.option("--cell", "cell_m", type=Finite(min=0, min_open=True), default=0.5, show_default=True, help="Cell size, m.")
@click.option("--degree", type=int, default=None, help="Spline degree (default: terrain.degree of the config, 3).")
@click.option("--nets", default="5,25", show_default=True, callback=_numbers(whole=True),
              help="Control points per axis, comma-separated.")
@click.option("--widths", default="0.8,2,4,6,8,10,12", show_default=True, callback=_numbers(), help="Obstacle widths, m.")
@click.option("--heights", default="0.5,1,1.5,2,2.5,3", show_default=True, callback=_numbers(), help="Obstacle heights, m.")
@click.option("--position", default="11.0,0.0", show_default=True, callback=_numbers(positive=False, count=2),
              help="Obstacle centre x,y in the area, m.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(".json"), help="Write results as JSON.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False), callback=output_file(".csv"), help="Write results as CSV.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), callback=output_file(*PLOT_SUFFIXES),
              help="Draw Fig. 6 to this image (.png, .pdf or .svg).")
@click.option("--base", "base_log", type=click.Path(exists=True), help="Take the base scene from a frame of this log "
              "or folder (its stereo points, vehicle frame) instead of a flat plane; the area is then the config's grid.")
@click.option("--frame", "frame_index", type=click.IntRange(min=0), default=0, show_default=True,
              help="With --base: which stereo pair of the log (0 = first).")
@open_options
@config_options
def artificial_obstacle(
    length_m, width_m, cell_m, degree, nets, widths, heights, position, json_path, csv_path, plot_path,
    base_log, frame_index, source_opts, config_path, overrides,
):
    """Max surface deviation caused by a w×w×h box, in % of h (paper Fig. 6).

    By default a flat scene over an area starting at the vehicle (x from 0, y centred), sampled
    like the grid, with and without the box; with --base, the points of a real or simulated frame,
    with and without the points inside the box footprint raised by h. Terrain settings other than
    the net come from --config/--set.
    """
    from terrainmap.config import GridConfig
    from terrainmap.evaluation import artificial_obstacle as ao

    check_outputs({"--json": json_path, "--csv": csv_path, "--plot": plot_path},
                              [base_log, config_path, source_opts.calibration])
    if frame_index and not base_log:
        raise click.UsageError("--frame picks a stereo pair of the --base log; give --base too")
    ctx = click.get_current_context()
    given = [f"--{name}" for name in ("length", "width", "cell")
             if ctx.get_parameter_source(f"{name}_m") is click.core.ParameterSource.COMMANDLINE]
    if base_log and given:
        raise click.UsageError(f"{', '.join(given)} set the flat scene's area; with --base the area is the config's "
                               "grid (--set grid.length_m=... and the like)")
    source_opts.require(base_log, "--base")
    config = load_config(config_path, overrides)
    if base_log:
        grid, (base_points, camera) = config.grid, ao.points_from_log(base_log, config, frame_index,
                                                                      **source_opts.open_kwargs())
    else:
        grid = GridConfig(x_min_m=0.0, length_m=length_m, width_m=width_m, y_center_m=0.0, cell_size_m=cell_m)
        base_points = camera = None
    terrain = config.terrain
    if degree is not None:
        terrain.degree = degree
    net_list = [int(n) for n in nets]
    terrain.start_control_points = min([terrain.start_control_points, *net_list])
    scenarios = ao.grid_of_scenarios(net_list, widths, heights)
    try:
        grid.validate()
        results = ao.run(scenarios, grid=grid, terrain=terrain, position_xy=tuple(position), base_points=base_points,
                         camera=camera)
    except ConfigError as exc:  # name the option the user gave, not only the config field it set
        field = str(exc).split(":", 1)[0]
        option = next((o for f, o in _FIELD_OPTIONS.items() if field.startswith(f)), "--set" if base_log else None)
        raise ConfigError(f"{option} ({exc})" if option else str(exc)) from exc
    _print_table(results)
    scene = f"{base_log}, stereo pair {frame_index}" if base_log else "flat"  # which base the rows are of
    rows = [{"scene": scene, **r.to_dict()} for r in results]
    if json_path:
        write_text(json_path, json.dumps(rows, indent=2) + "\n")
    if csv_path:
        table = io.StringIO(newline="")
        writer = csv.DictWriter(table, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        write_text(csv_path, table.getvalue())
    if plot_path:
        with writing(plot_path) as partial:
            ao.plot(results, str(partial))


def _print_table(results) -> None:
    heights = sorted({r.height_m for r in results})
    for i, net in enumerate(sorted({r.control_points for r in results})):
        if i:
            click.echo()
        click.echo(f"max deviation [% of obstacle height], {net}×{net} control points")
        click.echo("width m | " + " ".join(f"h={h:<5g}" for h in heights))
        for w in sorted({r.width_m for r in results}):
            cells = {r.height_m: r.max_deviation_pct for r in results if r.control_points == net and r.width_m == w}
            click.echo(f"{w:7g} | " + " ".join(f"{cells[h]:7.1f}" for h in heights))


@eval_group.command("robustness")
@click.option("--noise", "noise_m", type=Finite(0, 10), default=0.03, show_default=True, help="Sample noise σ, m.")
@click.option("--outliers", "outlier_fraction", type=Finite(0, 1), default=0.1, show_default=True,
              help="Fraction of samples raised by a gross error.")
@click.option("--outlier-max", "outlier_max_m", type=Finite(0, 100), default=2.0, show_default=True,
              help="Largest gross error above the ground, m.")
@click.option("--empty", "empty_fraction", type=Finite(0, 0.95), default=0.3, show_default=True,
              help="Fraction of empty cells.")
@click.option("--seeds", type=click.IntRange(1, 1000), default=5, show_default=True,
              help="Random samples to average over (seeds 0..N-1).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(".json"),
              help="Write {iterative_rmse_m, single_fit_rmse_m, ratio} and the scene's settings here.")
@config_options
def robustness(noise_m, outlier_fraction, outlier_max_m, empty_fraction, seeds, json_path, config_path, overrides):
    """Surface RMSE vs truth on synthetic rolling terrain: iterative estimator vs one plain fit."""
    from terrainmap.evaluation import robustness as lib

    check_outputs({"--json": json_path}, [config_path])
    config = load_config(config_path, overrides)
    scene = {"noise_m": noise_m, "outlier_fraction": outlier_fraction, "outlier_max_m": outlier_max_m,
             "empty_fraction": empty_fraction}
    r = lib.run(config, seeds=range(seeds), **scene)
    click.echo(f"iterative (Algorithm V-B.1) RMSE {100 * r['iterative_rmse_m']:.2f} cm; "
               f"single unweighted fit RMSE {100 * r['single_fit_rmse_m']:.2f} cm ({r['ratio']:.1f}× the iterative's)")
    if json_path:
        write_text(json_path, json.dumps({**r, **scene, "seeds": seeds}, indent=2) + "\n")


from .eval_accuracy import accuracy  # noqa: E402 (the commands live in their own modules)
from .eval_stereo import stereo  # noqa: E402

eval_group.add_command(accuracy)
eval_group.add_command(stereo)
