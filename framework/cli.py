"""The ``photonpano`` command line.

``run`` a spec, ``pano`` an input with the paper's default spec, ``demo`` on the bundled
photograph, list ``plugins``, ``validate`` a spec and print its JSON ``schema``.
Expected failures (bad input, bad spec, broken plugin) print one line and exit 1.
"""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from . import __version__
from .errors import PhotonpanoError

app = typer.Typer(add_completion=True, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Motion estimation and panoramas from single-photon cameras "
                       "(stratified temporal re-sampling, Jungerman et al., ICCV 2023).")

SetOption = Annotated[Optional[list[str]], typer.Option(
    "--set", "-s", help="Override a spec field: stage.field=value (value parsed as YAML). Repeatable.")]
OutOption = Annotated[Path, typer.Option("--output", "-o", help="Output folder (must be empty unless --force).")]
ForceOption = Annotated[bool, typer.Option("--force", help="Replace the previous run's outputs in the output "
                                           "folder (the files its manifest lists; other files are kept).")]
ResumeOption = Annotated[bool, typer.Option("--resume", help="Continue the interrupted run in the output "
                                            "folder from its last finished level (same spec).")]


_state: dict[str, Any] = {"debug": False, "quiet": False}
"""Global options of the command line (set by :func:`_global_options`)."""


def _version(value: bool) -> None:
    if value:
        typer.echo(f"photonpano {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Print debug messages.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print only warnings, errors and the result; "
                                                             "no progress bars.")] = False,
    log_file: Annotated[Optional[Path], typer.Option(
        "--log-file", help="Append a detailed log (debug level, with timestamps, tracebacks of plugin "
                           "failures) to this file.")] = None,
    debug: Annotated[bool, typer.Option(
        "--debug", help="Show the full traceback of unexpected errors (plugin bugs) instead of one line.")] = False,
) -> None:
    """Motion estimation and panoramas from single-photon cameras."""
    import logging

    _state.update(quiet=quiet, debug=debug)
    logger = logging.getLogger("photonpano")
    logger.setLevel(logging.DEBUG)
    for handler in list(logger.handlers):  # one set of handlers per invocation (tests call main repeatedly)
        if getattr(handler, "_photonpano_cli", False):
            logger.removeHandler(handler)
            handler.close()
    console = logging.StreamHandler(sys.stderr)
    # the progress display already prints each level's line: the console log adds only
    # warnings, or everything with --verbose
    console.setLevel(logging.DEBUG if verbose else logging.WARNING)
    console.setFormatter(logging.Formatter("%(message)s"))
    handlers: list[logging.Handler] = [console]
    if log_file is not None:
        try:
            file_handler = logging.FileHandler(log_file, encoding="utf-8")
        except OSError as exc:
            _fail(f"--log-file {log_file}: {exc.strerror or exc}")
        file_handler.setLevel(logging.DEBUG)
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handlers.append(file_handler)
    for handler in handlers:
        handler._photonpano_cli = True  # type: ignore[attr-defined]
        logger.addHandler(handler)
    logger.propagate = False


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(1)


def _host():
    from .host import PluginHost

    return PluginHost()


@contextmanager
def _observed(host):
    """Register the log observer and, unless ``--quiet``, progress bars on ``host`` for a block."""
    from .progress import LogObserver, RichProgress, reporting

    observers = {"cli-log": LogObserver()}
    bars = None
    if not _state["quiet"]:
        from rich.console import Console

        bars = observers["cli-progress"] = RichProgress(Console(stderr=True))
    for name, observer in observers.items():
        host.register(observer, name=name)
    try:
        with reporting(host):
            yield
    finally:
        if bars is not None:
            bars.stop()
        for name in observers:
            host.unregister(name)


def _execute(spec, out: Path, force: bool, host, resume: bool = False) -> dict[str, Any]:
    import warnings

    from .pipeline import run_pipeline

    for note in host.collisions:  # a third party offering a key or name already taken
        warnings.warn(note, stacklevel=1)
    with _observed(host):
        try:
            return run_pipeline(spec, out, host, force=force, resume=resume).summary
        except Exception as exc:  # plugin code raising anything: one line naming it
            if isinstance(exc, PhotonpanoError) or _state["debug"]:
                raise
            raise _plugin_failure(exc, host, spec) from exc


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
        set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False) -> None:
    """Run the pipeline described by a YAML spec."""
    from .spec import load_spec

    try:
        host = _host()
        parsed = load_spec(spec, host, set_ or [])
        if getattr(parsed, "pose_estimator", None) is not None:  # experimental: camera poses
            _report_pose(_execute_pose(parsed, output, force, host), output)
            return
        _report(_execute(parsed, output, force, host, resume), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def pano(input: Annotated[Path, typer.Argument(help="A capture: a .npy photon cube, a folder of SwissSPAD .bin "
                                                 "files, a video, an image folder or a Photron .mraw.")],
         output: OutOption,
         set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False) -> None:
    """Reconstruct a panorama from INPUT with the paper's default settings."""
    from .spec import apply_overrides, validate_spec

    try:
        host = _host()
        data = apply_overrides(_capture_spec(input, host), set_ or [])
        parsed = validate_spec(data, host, origin="pano")
        _report(_execute(parsed, output, force, host, resume), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


def _plugin_failure(exc: Exception, host, spec=None):
    """One-line :class:`PluginError` for a plugin's bug; the traceback goes to the log (file)."""
    import logging

    from .faults import plugin_failure

    logging.getLogger("photonpano").debug("unexpected exception in plugin code", exc_info=exc)
    return plugin_failure(exc, host, spec)


def _capture_spec(path: Path, host) -> dict[str, Any]:
    """:func:`photonpano.presets.spec_for_capture`, with a plugin's bug reported as one line."""
    from .presets import spec_for_capture

    try:
        return spec_for_capture(path, host)
    except PhotonpanoError:
        raise
    except Exception as exc:  # a plugin's bug: one line naming it
        if _state["debug"]:
            raise
        raise _plugin_failure(exc, host) from exc


def _execute_pose(spec, out: Path, force: bool, host) -> dict[str, Any]:
    from .pose_run import run_pose

    with _observed(host):
        return run_pose(spec, out, host, force=force)[0]


def _report_pose(summary: dict[str, Any], out: Path) -> None:
    last = summary["levels"][-1]
    typer.echo(f"poses for {summary['frames_with_pose']} of {summary['source']['frames']} binary frames "
               f"written to {out} (level {last['level']}: {last['registered']}/{last['exposures']} "
               "virtual exposures "
               f"registered, {summary['timings_s']['estimate']:.1f} s)")
    gt = summary.get("ground_truth")
    if gt and "rpe" in gt:
        typer.echo(f"vs ground truth: ATE {1e3 * gt['ate_m']:.2f} mm, RPE over {gt['rpe_gap_frames']} frames "
                   f"{1e3 * gt['rpe']['translation_m']:.2f} mm ({gt['rpe']['percent']:.1f} % of the true "
                   "motion)")


@app.command()
def pose(input: Annotated[str, typer.Argument(
             help="A capture (.npy photon cube, SwissSPAD folder, ...) or 'simulate3d' (a simulated room "
                  "with ground-truth poses).")],
         output: OutOption,
         intrinsics: Annotated[Optional[Path], typer.Option(
             help="JSON file with fx, fy, cx, cy in pixels (OpenCV convention); omitted: "
                  "self-calibration.")] = None,
         set_: SetOption = None, force: ForceOption = False) -> None:
    """Experimental: estimate a 6-DoF camera pose for every binary frame (pycolmap-sfm)."""
    from .pose import Intrinsics
    from .spec import apply_overrides, validate_spec

    try:
        host = _host()
        if intrinsics is not None:
            Intrinsics.load(intrinsics)  # a bad file fails before any work
        if input == "simulate3d":
            source = {"plugin": "simulate3d"}
        else:
            source = _capture_spec(Path(input), host)["source"]
        data = {"source": source, "pose_estimator": {"plugin": "pycolmap-sfm"}}
        if intrinsics is not None:
            data["pose_estimator"]["intrinsics"] = str(intrinsics)
        parsed = validate_spec(apply_overrides(data, set_ or []), host, origin="pose")
        _report_pose(_execute_pose(parsed, output, force, host), output)
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def convert(inputs: Annotated[list[Path], typer.Argument(help="A folder of SwissSPAD2 .bin readout files, or "
                                                         ".bin files in frame order; or one .npy or .zarr cube.")],
            output: Annotated[Path, typer.Option("--output", "-o", help="The .npy (or, from a .npy cube, .zarr) "
                                                 "cube to write (must not exist).")],
            layout: Annotated[str, typer.Option(help="Readout layout: half (512 frames of 256x512 per file) or "
                                                "full (256 frames of 512x512).")] = "half",
            check_layout: Annotated[bool, typer.Option(help="Refuse a layout the data does not fit.")] = True) -> None:
    """Convert SwissSPAD2 raw readouts to a bit-packed .npy photon cube, or a cube between .npy and .zarr, streaming.

    From readouts the cube holds the raw frames, (T, 256, 64) or (T, 512, 64) uint8 packed
    MSB first; read it with `photonpano pano cube.npy --set source.fix=colorspad` (or
    grayspad). A .npy cube converts to a chunked, compressed zarr array (source
    zarr-cube) and back, keeping its shape and dtype.
    """
    try:
        for path in inputs:
            if not path.exists():
                raise PhotonpanoError(f"input {path} does not exist")
        kinds = (inputs[0].suffix.lower(), output.suffix.lower())
        cube_to_cube = len(inputs) == 1 and kinds in ((".npy", ".zarr"), (".zarr", ".npy"))
        if not cube_to_cube and kinds[1] == ".zarr":
            raise PhotonpanoError(f"convert: {output}: a .zarr cube is written from one .npy cube; convert the "
                                  "readouts to .npy first")
        if not cube_to_cube and layout not in ("half", "full"):
            raise PhotonpanoError(f"convert: --layout must be half or full, got {layout!r}")
        from .progress import RichProgress

        notes: list[str] = []
        bars = RichProgress()
        with bars.bars as bar:
            task = bar.add_task("convert", total=None)

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            if cube_to_cube:
                from photonpano.plugins.sources.zarr_cube import convert_npy_to_zarr, convert_zarr_to_npy

                to_zarr = kinds[1] == ".zarr"
                frames = (convert_npy_to_zarr if to_zarr else convert_zarr_to_npy)(inputs[0], output,
                                                                                   progress=progress)
            else:
                from photonpano.plugins.sources.swissspad import convert_bin_to_npy

                frames, notes = convert_bin_to_npy(inputs, output, layout, check_layout=check_layout,
                                                   progress=progress)
        for note in notes:
            typer.secho(f"warning: {note}", fg=typer.colors.YELLOW, err=True)
        typer.echo(f"wrote {output}: {frames} " + ("frames" if cube_to_cube else f"{layout}-array frames"))
    except PhotonpanoError as exc:
        _fail(str(exc))


@app.command()
def batch(inputs: Annotated[list[str], typer.Argument(
              help="Captures (anything `pano` reads), spec files (.yaml) or source keys such as 'simulate'.")],
          output: Annotated[Path, typer.Option("--output", "-o", help="Folder receiving one output folder per "
                                               "input, named after the input's stem.")],
          set_: SetOption = None, force: ForceOption = False) -> None:
    """Reconstruct several captures concurrently (processes, or Dask with --set executor=dask).

    Prints one progress bar over the captures and a summary table; exits 1 if any capture
    failed (the others still run). See docs/scaling.md.
    """
    from .batch import main as batch_main

    try:
        code = batch_main(inputs, output, set_ or [], force, _state["quiet"], _host())
    except PhotonpanoError as exc:
        _fail(str(exc))
    if code:
        raise typer.Exit(code)


@app.command()
def demo(output: OutOption, set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False,
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
        _report(_execute(parsed, output, force, host, resume), output)
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
            from .spec import read_spec_file

            if not path.exists():
                raise PhotonpanoError(f"spec {input} does not exist")
            data = read_spec_file(path)[0] or {}
        else:
            data = _capture_spec(path, host)
        data = apply_overrides(data, set_ or [])
        keys = [k.strip() for k in locators.split(",") if k.strip()]
        if not keys:
            raise PhotonpanoError("--locators: give at least one locator key")
        prepare_output(output, force)
        with _observed(host):
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
    from rich.markup import escape
    from rich.table import Table

    table = Table("key", "stage", "module", "distribution", "version", "status")
    for info in _host().plugin_infos():
        # escape: rich would read "photonpano[kornia]" in an install hint as markup and drop it
        table.add_row(*(escape(str(v)) for v in (info.key, info.stage, info.module, info.distribution,
                                                 info.version, info.status)))
    Console(width=200).print(table)


@app.command()
def validate(spec: Annotated[Path, typer.Argument(help="Pipeline spec (YAML).")], set_: SetOption = None) -> None:
    """Validate a spec without reading any data."""
    from .spec import check_available, dump_spec, load_spec

    try:
        parsed = load_spec(spec, _host(), set_ or [])
        check_available(parsed)
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
