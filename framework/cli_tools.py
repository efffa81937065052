"""Commands beside the main job: ``pose`` (6-DoF poses), ``convert``, ``batch``, ``compare``, ``score``, ``video``.

Registered on :data:`photonpano.cli_base.app` (the ``photonpano`` command, see
:mod:`photonpano.cli`); expected failures print one line and exit 1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .cli_base import (
    ForceOption,
    OutOption,
    ResumeOption,
    SetOption,
    _capture_spec,
    _fail,
    _host,
    _observed,
    app,
    one_line_errors,
)
from .errors import PhotonpanoError

__all__ = ["execute_pose", "pose", "convert", "batch", "compare", "score", "video"]


def execute_pose(spec: Any, out: Path, force: bool, host: Any, resume: bool = False) -> None:
    """Run a spec with a ``pose_estimator`` into ``out`` (``resume``: continue it) and print its summary."""
    from .pose_run import run_pose

    with _observed(host):
        summary = run_pose(spec, out, host, force=force, resume=resume)[0]
    _report_pose(summary, out)


def _report_pose(summary: dict[str, Any], out: Path) -> None:
    last = summary["levels"][-1]
    typer.echo(f"poses for {summary['frames_with_pose']} of {summary['source']['frames']} binary frames "
               f"written to {out} (level {last['level']}: {last['registered']}/{last['exposures']} "
               "virtual exposures "
               f"registered, {summary['timings_s']['estimate']:.1f} s)")
    for warning in summary.get("warnings", []):
        typer.secho(f"warning: {warning}", fg=typer.colors.YELLOW, err=True)
    gt = summary.get("ground_truth")
    if gt and "rpe" in gt:
        typer.echo(f"vs ground truth: ATE {1e3 * gt['ate_m']:.2f} mm, RPE over {gt['rpe_gap_frames']} frames "
                   f"{1e3 * gt['rpe']['translation_m']:.2f} mm ({gt['rpe']['percent']:.1f} % of the true "
                   "motion)")


@app.command()
@one_line_errors
def pose(input: Annotated[str, typer.Argument(
             help="A capture (.npy photon cube, SwissSPAD folder, ...) or 'simulate3d' (a simulated room "
                  "with ground-truth poses).")],
         output: OutOption,
         intrinsics: Annotated[Optional[Path], typer.Option(
             help="JSON file with fx, fy, cx, cy in pixels (OpenCV convention); omitted: "
                  "self-calibration.")] = None,
         set_: SetOption = None, force: ForceOption = False, resume: ResumeOption = False) -> None:
    """Experimental: estimate a 6-DoF camera pose for every binary frame (pycolmap-sfm)."""
    from .pose import Intrinsics
    from .spec import apply_overrides, validate_spec

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
    execute_pose(parsed, output, force, host, resume)


@app.command()
@one_line_errors
def convert(inputs: Annotated[list[Path], typer.Argument(help="A folder of SwissSPAD2 .bin readout files, or "
                                                         ".bin files in frame order; or one .npy or .zarr cube.")],
            output: Annotated[Path, typer.Option("--output", "-o", help="The .npy (or, from a .npy cube, .zarr) "
                                                 "cube to write (must not exist).")],
            layout: Annotated[str, typer.Option(help="Readout layout: half (512 frames of 256x512 per file) or "
                                                "full (256 frames of 512x512).")] = "half",
            check_layout: Annotated[bool, typer.Option(help="Refuse a layout the data does not fit.")] = True,
            resume: Annotated[bool, typer.Option(
                "--resume", help="Restart a conversion that was interrupted (killed): the <output>.part it "
                                 "left is removed and the conversion runs again from the start.")] = False) -> None:
    """Convert SwissSPAD2 raw readouts to a bit-packed .npy photon cube, or a cube between .npy and .zarr, streaming.

    From readouts the cube holds the raw frames, (T, 256, 64) or (T, 512, 64) uint8 packed
    MSB first; read it with `photonpano pano cube.npy --set source.fix=colorspad` (or
    grayspad). A .npy cube converts to a chunked, compressed zarr array (source
    zarr-cube) and back, keeping its shape and dtype. The output appears only when complete
    (it is written as <output>.part and renamed).
    """
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

        try:
            if cube_to_cube:
                from photonpano.plugins.sources.zarr_cube import convert_npy_to_zarr, convert_zarr_to_npy

                to_zarr = kinds[1] == ".zarr"
                frames = (convert_npy_to_zarr if to_zarr else convert_zarr_to_npy)(inputs[0], output,
                                                                                    progress=progress, restart=resume)
            else:
                from photonpano.plugins.sources.swissspad import convert_bin_to_npy

                frames, notes = convert_bin_to_npy(inputs, output, layout, check_layout=check_layout,
                                                   progress=progress, restart=resume)
        except OSError as exc:  # reading an input failed (writes fail as OutputError naming the output)
            raise PhotonpanoError(f"convert: cannot read {exc.filename or 'an input'}: "
                                  f"{exc.strerror or exc}") from None
    for note in notes:
        typer.secho(f"warning: {note}", fg=typer.colors.YELLOW, err=True)
    typer.echo(f"wrote {output}: {frames} " + ("frames" if cube_to_cube else f"{layout}-array frames"))


@app.command()
@one_line_errors
def batch(inputs: Annotated[list[str], typer.Argument(
              help="Captures (anything `pano` reads), spec files (.yaml) or source keys such as 'simulate'.")],
          output: Annotated[Path, typer.Option("--output", "-o", help="Folder receiving one output folder per "
                                               "input, named after the input's stem.")],
          set_: SetOption = None, force: ForceOption = False,
          resume: Annotated[bool, typer.Option(
              "--resume", help="Continue an interrupted batch: finished captures are reused, interrupted ones "
                               "continue from their last finished level, the others run.")] = False) -> None:
    """Reconstruct several captures concurrently (processes, or Dask with --set executor=dask).

    Prints one progress bar over the captures and a summary table; exits 1 if any capture
    failed (the others still run). See docs/scaling.md.
    """
    from .batch import main as batch_main
    from .cli_base import _state

    code = batch_main(inputs, output, set_ or [], force, _state["quiet"], _host(), resume=resume)
    if code:
        raise typer.Exit(code)


@app.command()
@one_line_errors
def compare(input: Annotated[str, typer.Argument(help="A spec (.yaml), a capture (.npy, ...) or 'simulate' "
                                                  "(the demo's simulated capture, with ground truth).")],
            output: OutOption,
            locators: Annotated[str, typer.Option(
                "--locators", "-l",
                help="Comma-separated locator keys, each optionally key:field=value[:field=value].")],
            set_: SetOption = None, force: ForceOption = False,
            refine: Annotated[bool, typer.Option(
                "--refine", help="Keep the spec's level_schemes (compare whole pipelines as `run` executes "
                                 "them); default: each locator registers pairs at every level.")
            ] = False,
            resume: Annotated[bool, typer.Option(
                "--resume", help="Continue the interrupted comparison in the output folder: locators that "
                                 "finished are reused, the others run (same command).")] = False) -> None:
    """Run the same pipeline with each locator; write a table and a plot of error and time.

    Writes compare.md, compare.png, <locator>/homographies.npy and, last, compare.json into
    OUTPUT (atomically, with a manifest: see docs/locators.md).
    """
    from .compare import COMPARE_JSON, compare_locators, markdown_table, write_comparison
    from .outputs import RunFolder
    from .spec import apply_overrides

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
    if force and resume:
        raise PhotonpanoError("compare: --force and --resume exclude each other")
    inputs = [path] if input != "simulate" and path.exists() else []
    with RunFolder(output, force=force, resume=resume, inputs=inputs, final=COMPARE_JSON) as folder:
        with _observed(host) as bars:
            log = bars.bars.console.print if bars is not None else typer.echo  # above the bars, not glued to them
            rows = compare_locators(data, keys, host, folder, origin=input, log=log, refine=refine)
        write_comparison(rows, folder, data)
    typer.echo(markdown_table(rows))
    if not any(row["status"] == "ok" for row in rows):
        _fail("no locator completed (see the table)")


@app.command()
@one_line_errors
def score(panorama: Annotated[Path, typer.Argument(help="A reconstruction (PNG, TIFF, JPEG or .npy in [0, 1]), or "
                                                    "a folder of them.")],
          reference: Annotated[Path, typer.Argument(help="The reference image, or a folder of references (each "
                                                    "paired with the image at the same relative path).")],
          json_: Annotated[bool, typer.Option("--json", help="Print the scores as JSON (summary and per image) "
                                              "instead of the table.")] = False) -> None:
    """Score reconstructions against references with the Single Photon Challenge's metrics.

    PSNR (peak 1) and MS-SSIM (5 scales, 11x11 Gaussian window, sigma 1.5) per image; the
    table gives their mean and the 5 % and 1 % quantiles over the images (the challenge's
    worst-case lows). See photonpano.score.
    """
    import json

    from .score import format_table, score_paths, summarize

    scores = score_paths(panorama, reference)
    summary = summarize(scores)
    if json_:
        def number(v: float) -> float | str:
            return v if v == v and abs(v) != float("inf") else str(v)

        summary = {k: ({m: number(x) for m, x in v.items()} if isinstance(v, dict) else v) for k, v in summary.items()}
        summary["per_image"] = [{"name": s.name, "psnr_db": number(s.psnr_db), "ms_ssim": number(s.ms_ssim)}
                                for s in scores]
        typer.echo(json.dumps(summary, indent=2))
    else:
        typer.echo(format_table(summary))


@app.command()
@one_line_errors
def video(run: Annotated[Path, typer.Argument(help="A finished run folder (run.json, homographies.npy, "
                                              "panorama.npy).")],
          output: Annotated[Path, typer.Option("--output", "-o", help="The .mp4 file to write (must not exist "
                                               "unless --force).")],
          mode: Annotated[str, typer.Option(help="stabilised: virtual exposures warped onto the panorama "
                                            "canvas; flythrough: the panorama as the camera saw it along the "
                                            "estimated path; levels: each level's merged frames (a run with "
                                            "outputs.merged_frames).")] = "stabilised",
          exposure: Annotated[Optional[int], typer.Option(help="Binary frames per virtual exposure "
                                                          "(stabilised); default: the run's level-1 group "
                                                          "size.")] = None,
          fps: Annotated[float, typer.Option(help="Playback frames per second.")] = 30.0,
          frames: Annotated[Optional[int], typer.Option(help="Video frames, spread evenly over the capture; "
                                                        "default: one per exposure (at most 1000), every "
                                                        "merged frame for levels.")] = None,
          width: Annotated[Optional[int], typer.Option(help="Output width in pixels (the height keeps the "
                                                       "aspect); default: the frames' own size.")] = None,
          force: Annotated[bool, typer.Option("--force", help="Replace an existing output file.")] = False) -> None:
    """Render a finished run as an H.264 video (PyAV, the video extra). See docs/outputs.md."""
    from .cli_base import _state
    from .progress import RichProgress
    from .video import render_video

    bars = None if _state["quiet"] else RichProgress()
    task: dict[str, Any] = {}

    def start(total: int) -> None:
        if bars is not None:
            bars.bars.start()
            task["id"] = bars.bars.add_task(f"video ({mode})", total=total)

    def advance(n: int) -> None:
        if bars is not None and "id" in task:
            bars.bars.advance(task["id"], n)

    try:
        info = render_video(run, output, mode=mode, exposure=exposure, fps=fps, frames=frames, width=width,
                            force=force, advance=advance, start=start)
    finally:
        if bars is not None and task:
            bars.stop()
    for note in info.notes:
        typer.secho(f"note: {note}", fg=typer.colors.YELLOW, err=True)
    typer.echo(f"wrote {output}: {info.frames} frames of {info.width}x{info.height} at {fps:g} fps ({info.codec})")
