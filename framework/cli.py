"""The ``photonpano`` command line.

``run`` a spec, ``pano`` an input with the paper's default spec, ``demo`` on the bundled
photograph, list ``plugins``, ``validate`` a spec and print its JSON ``schema``.
Expected failures (bad input, bad spec, broken plugin) print one line and exit 1.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from . import hookimpl
from .errors import PhotonpanoError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Motion estimation and panoramas from single-photon cameras "
                       "(stratified temporal re-sampling, Jungerman et al., ICCV 2023).")

SetOption = Annotated[Optional[list[str]], typer.Option(
    "--set", "-s", help="Override a spec field: stage.field=value (value parsed as YAML). Repeatable.")]
OutOption = Annotated[Path, typer.Option("--output", "-o", help="Output folder (must be empty unless --force).")]
ForceOption = Annotated[bool, typer.Option("--force", help="Write into a non-empty output folder.")]


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(1)


def _host():
    from .host import PluginHost

    return PluginHost()


class _RichProgress:
    """Observer plugin drawing progress bars with rich (registered by the CLI only)."""

    def __init__(self) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.bars = Progress(TextColumn("{task.description:<20}"), BarColumn(), MofNCompleteColumn(),
                             TimeElapsedColumn(), transient=False)
        self.tasks: dict[str, Any] = {}

    @hookimpl
    def photonpano_run_start(self, source) -> None:
        typer.echo(f"source: {source.name}: {source.n_frames} frames of {source.height}x{source.width}")
        self.bars.start()

    @hookimpl
    def photonpano_progress(self, task: str, total, advance: int) -> None:
        if task not in self.tasks:
            self.tasks[task] = self.bars.add_task(task, total=total)
        self.bars.advance(self.tasks[task], advance)

    @hookimpl
    def photonpano_level_finished(self, level) -> None:
        s = level.statistics()
        self.bars.console.print(f"level {s['level']}: {s['groups']} groups, median {s['median_inliers']:.0f} "
                                f"inliers, {s['failed_pairs']} failed pairs")

    @hookimpl
    def photonpano_run_finished(self, summary) -> None:
        self.bars.stop()


def _execute(spec, out: Path, force: bool, host) -> dict[str, Any]:
    from .pipeline import run_pipeline

    observer = _RichProgress()
    host.register(observer, name="cli-progress")
    try:
        return run_pipeline(spec, out, host, force=force)
    finally:
        observer.bars.stop()


def _report(summary: dict[str, Any], out: Path) -> None:
    gt = summary.get("ground_truth")
    t = summary["timings_s"]
    typer.echo(f"panorama {summary['panorama']['width']}x{summary['panorama']['height']} written to {out} "
               f"(levels {t['levels']:.1f} s, panorama {t['panorama']:.1f} s)")
    if gt:
        per_level = ", ".join(f"level {row['level']}: {row['trajectory_rmse_px']:.3f}" for row in summary["levels"])
        typer.echo(f"trajectory RMSE vs ground truth (px): {per_level}")
        if "psnr_db" in gt:
            typer.echo(f"panorama PSNR {gt['psnr_db']:.2f} dB; with the true homographies "
                       f"{gt['psnr_true_homographies_db']:.2f} dB (gap {gt['psnr_gap_db']:.2f} dB)")
    for warning in summary.get("warnings", []):
        typer.secho(f"warning: {warning}", fg=typer.colors.YELLOW, err=True)
    if "status" in summary:
        typer.echo(f"status: {summary['status']} (group size {summary['group_size']['group_size']}: "
                   f"{summary['group_size']['reason']})")


@app.command()
def run(spec: Annotated[Path, typer.Argument(help="Pipeline spec (YAML).")], output: OutOption,
        set_: SetOption = None, force: ForceOption = False) -> None:
    """Run the pipeline described by a YAML spec."""
    from .spec import load_spec

    try:
        host = _host()
        parsed = load_spec(spec, host, set_ or [])
        _report(_execute(parsed, output, force, host), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def pano(input: Annotated[Path, typer.Argument(help="A capture: a .npy photon cube, a folder of SwissSPAD .bin "
                                                 "files, a video, an image folder or a Photron .mraw.")],
         output: OutOption,
         set_: SetOption = None, force: ForceOption = False) -> None:
    """Reconstruct a panorama from INPUT with the paper's default settings."""
    from .spec import apply_overrides, validate_spec

    try:
        host = _host()
        data = apply_overrides(_spec_for_capture(input, host), set_ or [])
        parsed = validate_spec(data, host, origin="pano")
        _report(_execute(parsed, output, force, host), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


def _spec_for_capture(path: Path, host) -> dict[str, Any]:
    """Return the spec mapping of a capture file or folder: the source plugin that reads it and its merger.

    Raises:
        PhotonpanoError: if ``path`` does not exist or no source plugin reads it.
    """
    if not path.exists():
        raise PhotonpanoError(f"input {path} does not exist")
    source = host.hook.photonpano_source_for_input(path=path)
    if source is None:
        raise PhotonpanoError(f"no source plugin reads {path} (supported: .npy photon cubes, folders of "
                              ".bin readouts, videos, image folders, .mraw; see `photonpano plugins`)")
    return {"source": source, **_merger_for(source, host)}


def _merger_for(source: dict[str, Any], host) -> dict[str, Any]:
    """Sources of intensity frames (config class ``kind = "intensity"``) get the ``mean`` merger."""
    cls = host.registry("source").get(source.get("plugin"))
    if getattr(cls, "kind", "binary") == "intensity" and "mean" in host.registry("merger"):
        return {"merger": "mean"}
    return {}


@app.command()
def convert(inputs: Annotated[list[Path], typer.Argument(help="A folder of SwissSPAD2 .bin readout files, or "
                                                         ".bin files in frame order.")],
            output: Annotated[Path, typer.Option("--output", "-o", help="The .npy cube to write (must not exist).")],
            layout: Annotated[str, typer.Option(help="Readout layout: half (512 frames of 256x512 per file) or "
                                                "full (256 frames of 512x512).")] = "half",
            check_layout: Annotated[bool, typer.Option(help="Refuse a layout the data does not fit.")] = True) -> None:
    """Convert SwissSPAD2 raw readouts to a bit-packed .npy photon cube, streaming.

    The cube holds the raw frames, (T, 256, 64) or (T, 512, 64) uint8 packed MSB first;
    read it with `photonpano pano cube.npy --set source.fix=colorspad` (or grayspad).
    """
    try:
        if layout not in ("half", "full"):
            raise PhotonpanoError(f"convert: --layout must be half or full, got {layout!r}")
        for path in inputs:
            if not path.exists():
                raise PhotonpanoError(f"input {path} does not exist")
        from rich.progress import Progress

        from photonpano.plugins.sources.swissspad import convert_bin_to_npy

        with Progress(transient=True) as bar:
            task = bar.add_task("convert", total=None)
            frames, notes = convert_bin_to_npy(inputs, output, layout, check_layout=check_layout,
                                               progress=lambda done, total: bar.update(task, completed=done,
                                                                                       total=total))
        for note in notes:
            typer.secho(f"warning: {note}", fg=typer.colors.YELLOW, err=True)
        typer.echo(f"wrote {output}: {frames} {layout}-array frames")
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def demo(output: OutOption, set_: SetOption = None, force: ForceOption = False,
         frames: Annotated[int, typer.Option(help="Binary frames to simulate.")] = 20_000) -> None:
    """Simulate a capture from the bundled real photograph and reconstruct it.

    Prints the trajectory error and the panorama PSNR against ground truth.
    """
    from .spec import apply_overrides, validate_spec

    try:
        host = _host()
        data = apply_overrides({"source": {"plugin": "simulate", "frames": frames}}, set_ or [])
        parsed = validate_spec(data, host, origin="demo")
        typer.echo(f"simulating {parsed.source.frames} binary frames of {parsed.source.height}x"
                   f"{parsed.source.width} at flux {parsed.source.flux} from the bundled photo ...")
        _report(_execute(parsed, output, force, host), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def compare(input: Annotated[str, typer.Argument(help="A spec (.yaml), a capture (.npy, ...) or 'simulate' "
                                                  "(the demo's simulated capture, with ground truth).")],
            output: OutOption,
            locators: Annotated[str, typer.Option(
                "--locators", "-l",
                help="Comma-separated locator keys, each optionally key:field=value[:field=value].")],
            set_: SetOption = None, force: ForceOption = False,
            refine: Annotated[bool, typer.Option(
                "--refine", help="Keep the spec's refine_locator for levels >= 2 (compare whole pipelines "
                                 "as `run` executes them); default: each locator registers pairs at every level.")
            ] = False) -> None:
    """Run the same pipeline with each locator; write a table and a plot of error and time.

    Writes compare.md, compare.json, compare.png and <locator>/homographies.npy into OUTPUT.
    """
    from .compare import compare_locators, markdown_table, write_comparison
    from .pipeline import prepare_output
    from .spec import apply_overrides

    try:
        host = _host()
        path = Path(input)
        if input == "simulate":
            data: dict[str, Any] = {"source": {"plugin": "simulate"}}
        elif path.suffix in (".yaml", ".yml"):
            import yaml

            if not path.exists():
                raise PhotonpanoError(f"spec {input} does not exist")
            data = yaml.safe_load(path.read_text()) or {}
        else:
            data = _spec_for_capture(path, host)
        data = apply_overrides(data, set_ or [])
        keys = [k.strip() for k in locators.split(",") if k.strip()]
        if not keys:
            raise PhotonpanoError("--locators: give at least one locator key")
        prepare_output(output, force)
        rows = compare_locators(data, keys, host, output, origin=input, log=typer.echo,
                                on_row=lambda done: write_comparison(done, output, data), refine=refine)
    except PhotonpanoError as exc:
        _fail(str(exc))
    typer.echo(markdown_table(rows))
    if not any(row["status"] == "ok" for row in rows):
        _fail("no locator completed (see the table)")


@app.command()
def plugins() -> None:
    """List installed plugins: key, stage, module, distribution, version, status."""
    from rich.console import Console
    from rich.table import Table

    table = Table("key", "stage", "module", "distribution", "version", "status")
    for info in _host().plugin_infos():
        table.add_row(info.key, info.stage, info.module, info.distribution, info.version, info.status)
    Console(width=200).print(table)


@app.command()
def validate(spec: Annotated[Path, typer.Argument(help="Pipeline spec (YAML).")], set_: SetOption = None) -> None:
    """Validate a spec without reading any data."""
    from .spec import dump_spec, load_spec

    try:
        parsed = load_spec(spec, _host(), set_ or [])
        for stage in ("source", "resampler", "merger", "locator", "interpolator"):
            type(getattr(parsed, stage)).check_available()
    except PhotonpanoError as exc:
        _fail(str(exc))
    typer.echo(f"{spec}: valid")
    typer.echo(dump_spec(parsed))


@app.command()
def schema() -> None:
    """Print the JSON schema of pipeline specs (for editor completion of YAML specs)."""
    from .spec import spec_model

    try:
        typer.echo(json.dumps(spec_model(_host()).model_json_schema(), indent=2))
    except PhotonpanoError as exc:
        _fail(str(exc))


def main() -> None:
    """Entry point of the ``photonpano`` command."""
    import warnings

    # caveats of a capture (e.g. a truncated last file) print as one line
    warnings.showwarning = lambda message, *args, **kwargs: typer.secho(f"warning: {message}", err=True,
                                                                        fg=typer.colors.YELLOW)
    try:
        app()
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":  # pragma: no cover
    main()
