"""``report.html``: one self-contained page per run (images inlined, no external resources).

The page shows the status and warnings of the confidence report, the panorama (click to
zoom, with zoom buttons), the trajectory with its predicted-error band, per-level
figures, the timings, the source, the resolved spec and the versions. Everything comes
from ``run.json`` (the summary), the panorama and the homographies, so a finished run
folder can be reported at any time (:func:`report_html`); the run writes it next to
``run.json`` (``outputs: {report: true}``, the default). :func:`summary_html` is the
compact form a notebook shows for a :class:`~photonpano.pipeline.RunResult`.
"""

from __future__ import annotations

import base64
import html
import io
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["png_data_uri", "panorama_png", "trajectory_png", "report_html", "summary_html", "show"]

MAX_PANORAMA_SIDE = 8192
"""A panorama with a longer side is inlined scaled down to this many pixels."""

_STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:1.5em auto;max-width:1100px;padding:0 1em;
color:#222}
h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.9em}td,th{border:1px solid #ddd;padding:.2em .5em;text-align:right}
th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.status{display:inline-block;padding:.15em .6em;border-radius:.3em;color:#fff;font-weight:bold}
.ok{background:#2a7d2a}.degraded{background:#c07000}.unknown{background:#777}
.warn{color:#8a4b00}pre{background:#f6f6f6;padding:.7em;overflow:auto;font-size:.85em}
.pano{overflow:auto;max-height:80vh;border:1px solid #ddd;background:repeating-conic-gradient(#eee 0 25%,#fff 0 50%)
 0 0/16px 16px}
.pano img{display:block;width:100%;cursor:zoom-in}.pano img.zoomed{width:auto;cursor:zoom-out;image-rendering:pixelated}
button{margin-right:.3em}
"""

_ZOOM = """
<script>
(function(){var img=document.getElementById('panorama'),zoom=0;
function fit(){zoom=0;img.classList.remove('zoomed');img.style.width='';}
function set(z){zoom=Math.max(0.125,Math.min(16,z));img.classList.add('zoomed');
img.style.width=(img.naturalWidth*zoom)+'px';}
img.addEventListener('click',function(){zoom?fit():set(1);});
document.getElementById('zoom-in').onclick=function(){set((zoom||img.width/img.naturalWidth)*2);};
document.getElementById('zoom-out').onclick=function(){set((zoom||img.width/img.naturalWidth)/2);};
document.getElementById('zoom-1').onclick=function(){set(1);};
document.getElementById('zoom-fit').onclick=fit;})();
</script>
"""


def png_data_uri(png: bytes) -> str:
    """``data:image/png;base64,...`` for PNG bytes (to inline in an ``<img src>``)."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def panorama_png(flux: NDArray, max_side: int | None = None) -> bytes:
    """The panorama as an 8-bit grey PNG with alpha, tone-mapped as ``panorama.png``.

    Args:
        flux: (Hc, Wc) float linear flux in photons/s, NaN where unobserved (transparent);
            (Hc, Wc, C) colour flux is shown by its channel mean.
        max_side: a longer side is scaled down to this many pixels (area average);
            None: :data:`MAX_PANORAMA_SIDE`.

    Returns:
        PNG bytes of an (Hc, Wc) image (or scaled), 2 channels grey + alpha encoded as
        4-channel BGRA.

    Raises:
        ValueError: ``flux`` is empty or not 2-D (or 3-D colour).
    """
    import cv2

    from .photons import tone_map

    flux = np.asarray(flux, np.float32)
    if flux.ndim == 3:
        flux = flux.mean(axis=2)
    if flux.ndim != 2 or not flux.size:
        raise ValueError(f"panorama_png: expected an (H, W) flux image, got shape {flux.shape}")
    grey = tone_map(flux)
    alpha = np.where(np.isfinite(flux), np.uint8(255), np.uint8(0))
    image = np.dstack([grey, grey, grey, alpha])
    side, max_side = max(flux.shape), max_side or MAX_PANORAMA_SIDE
    if side > max_side:
        size = (max(1, round(flux.shape[1] * max_side / side)), max(1, round(flux.shape[0] * max_side / side)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("panorama_png: OpenCV could not encode the panorama")
    return data.tobytes()


def trajectory_png(summary: dict[str, Any], to_canvas: NDArray[np.float64],
                   uncertainty: NDArray[np.float64] | None = None) -> bytes:
    """The trajectory figure (:func:`photonpano.metrics.trajectory_figure`) as PNG bytes, 80 dpi.

    Args:
        summary: ``run.json`` content (its ``source``: ``width``, ``height``, ``frame_rate_hz``).
        to_canvas: (T, 3, 3) float64 frame-to-canvas homographies.
        uncertainty: (T,) float64 predicted 1-sigma error per frame in pixels (drawn as a
            band from 0 to 2 sigma), or None.
    """
    import matplotlib.pyplot as plt

    from .metrics import trajectory_figure

    info = summary.get("source", {})
    source = SimpleNamespace(width=int(info.get("width", 1)), height=int(info.get("height", 1)),
                             frame_rate_hz=float(info.get("frame_rate_hz", 1.0)), ground_truth=None)
    fig = trajectory_figure(to_canvas, to_canvas, source, None, uncertainty)
    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, format="png", dpi=80)
    finally:
        plt.close(fig)
    return buffer.getvalue()


def _e(value: Any) -> str:
    return html.escape(str(value))


def _number(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return _e("-" if value is None else value)
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1e4 else f"{value:.0f}"
    return _e(value)


def _status(summary: dict[str, Any]) -> str:
    status = str(summary.get("status", "unknown"))
    kind = status if status in ("ok", "degraded") else "unknown"
    return f'<span class="status {kind}" id="status">{_e(status)}</span>'


def _list(items: list[Any], css: str, element_id: str) -> str:
    if not items:
        return f'<p id="{element_id}">none</p>'
    rows = "\n".join(f'<li class="{css}">{_e(item)}</li>' for item in items)
    return f'<ul id="{element_id}">{rows}</ul>'


def _table(headers: list[str], rows: list[list[Any]], element_id: str = "") -> str:
    ident = f' id="{element_id}"' if element_id else ""
    head = "".join(f"<th>{_e(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{_number(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table{ident}><tr>{head}</tr>{body}</table>"


def _level_rows(levels: list[dict[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    headers = ["level", "scheme", "groups", "pairs", "failed pairs", "median inliers", "photons/px/group",
               "failed fraction", "residual / correction (px)", "time (s)"]
    has_rmse = any("trajectory_rmse_px" in level for level in levels)
    if has_rmse:
        headers.append("RMSE vs truth (px)")
    rows = []
    for level in levels:
        quality = level.get("quality", {}) or {}
        residual = quality.get("pose_graph_residual_px", quality.get("median_correction_px"))
        row = [level.get("level"), level.get("scheme", ""), level.get("groups"), level.get("pairs"),
               level.get("failed_pairs"), level.get("median_inliers"), quality.get("photons_per_pixel_per_group"),
               quality.get("failed_fraction"), residual, sum((level.get("timings_s") or {}).values())]
        if has_rmse:
            row.append(level.get("trajectory_rmse_px"))
        rows.append(row)
    return headers, rows


def _yaml(data: Any) -> str:
    import yaml

    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


def report_html(summary: dict[str, Any], panorama: NDArray, to_canvas: NDArray[np.float64],
                uncertainty: NDArray[np.float64] | None = None, *, trajectory: bytes | None = None,
                title: str = "photonpano run") -> str:
    """The self-contained HTML report of a run (``report.html``).

    Args:
        summary: the ``run.json`` content (status, warnings, notes, levels, timings,
            source, spec, versions, plugins, ground truth if any).
        panorama: (Hc, Wc) float32 flux in photons/s, NaN where unobserved.
        to_canvas: (T, 3, 3) float64 frame-to-canvas homographies.
        uncertainty: (T,) float64 per-frame 1-sigma error in pixels, or None.
        trajectory: PNG bytes of the trajectory figure (e.g. ``trajectory.png``, with
            the ground truth drawn); None: drawn here from ``to_canvas`` and ``uncertainty``.
        title: the page title.

    Returns:
        The page: HTML5, UTF-8, every image a base64 ``data:`` URI, no external URL.
    """
    trajectory = trajectory if trajectory is not None else trajectory_png(summary, to_canvas, uncertainty)
    pano = summary.get("panorama", {})
    source = summary.get("source", {})
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{_e(title)}</title>",
             f"<style>{_STYLE}</style></head><body>",
             f"<h1>{_e(title)}</h1><p>status: {_status(summary)} &nbsp; {_e(source.get('name', ''))}: "
             f"{_e(source.get('frames', '?'))} frames of {_e(source.get('width', '?'))}x"
             f"{_e(source.get('height', '?'))} at {_number(source.get('frame_rate_hz'))} Hz</p>",
             "<h2>Warnings</h2>", _list(list(summary.get("warnings") or []), "warn", "warnings")]
    if summary.get("notes"):
        parts += ["<h2>Notes</h2>", _list(list(summary["notes"]), "note", "notes")]
    parts += [f"<h2>Panorama</h2><p>{_e(pano.get('width', panorama.shape[1]))}x"
              f"{_e(pano.get('height', panorama.shape[0]))} canvas pixels, "
              f"{100 * float(pano.get('observed_fraction', np.isfinite(panorama).mean())):.1f} % observed; "
              "tone-mapped as panorama.png. Click the image to toggle 1:1.</p>",
              '<p><button id="zoom-fit">fit</button><button id="zoom-1">1:1</button>'
              '<button id="zoom-in">+</button><button id="zoom-out">&minus;</button></p>',
              f'<div class="pano"><img id="panorama" alt="panorama" src="{png_data_uri(panorama_png(panorama))}">'
              "</div>", _ZOOM,
              "<h2>Trajectory</h2>",
              f'<img id="trajectory" alt="trajectory" style="max-width:100%" src="{png_data_uri(trajectory)}">']
    unc = summary.get("uncertainty")
    if unc:
        parts.append(f"<p>predicted per-frame error ({_e(unc.get('evidence', ''))}): median "
                     f"{_number(unc.get('median_px'))} px, 95th percentile {_number(unc.get('p95_px'))} px, max "
                     f"{_number(unc.get('max_px'))} px (limit {_number(unc.get('limit_px'))} px)</p>")
    headers, rows = _level_rows(list(summary.get("levels") or []))
    parts += ["<h2>Levels</h2>", _table(headers, rows, "levels")]
    truth = summary.get("ground_truth")
    if truth:
        flat = [[key, value] for key, value in truth.items() if isinstance(value, (int, float))]
        parts += ["<h2>Ground truth</h2>", _table(["figure", "value"], flat, "ground-truth")]
    timings = summary.get("timings_s") or {}
    parts += ["<h2>Timings</h2>", _table(["stage", "seconds"], [[k, v] for k, v in timings.items()], "timings")]
    group = summary.get("group_size")
    if group:
        parts.append(f"<p>group size {_e(group.get('group_size'))}: {_e(group.get('reason', ''))}</p>")
    parts += ["<h2>Spec</h2>", f'<pre id="spec">{_e(_yaml(summary.get("spec", {})))}</pre>',
              "<h2>Versions</h2>",
              _table(["library", "version"], [["photonpano", summary.get("photonpano", "?")],
                                              ["python", summary.get("python", "?")],
                                              *[[k, v] for k, v in (summary.get("versions") or {}).items()]],
                     "versions")]
    plugins = summary.get("plugins") or {}
    if plugins:
        parts.append(f'<pre id="plugins">{_e(_yaml(plugins))}</pre>')
    parts.append("</body></html>\n")
    return "".join(parts)


def summary_html(summary: dict[str, Any], panorama: NDArray, thumbnail_px: int = 320) -> str:
    """A compact HTML summary (a notebook's view of a :class:`~photonpano.pipeline.RunResult`).

    Args:
        summary: the ``run.json`` content.
        panorama: (Hc, Wc) float32 flux, NaN where unobserved.
        thumbnail_px: the thumbnail's longest side in pixels.

    Returns:
        An HTML fragment: status, warnings count, panorama size, frames, levels, RMSE
        against the truth if known, the total time and a small panorama.
    """
    source = summary.get("source", {})
    pano = summary.get("panorama", {"width": panorama.shape[1], "height": panorama.shape[0]})
    rows: list[list[object]] = [
        ["frames", f"{source.get('frames', '?')} of {source.get('width', '?')}x{source.get('height', '?')}"],
        ["panorama", f"{pano.get('width')}x{pano.get('height')} px"],
        ["levels", len(summary.get("levels") or [])],
        ["warnings", len(summary.get("warnings") or [])],
        ["time (s)", f"{sum((summary.get('timings_s') or {}).values()):.1f}"]]
    truth = summary.get("ground_truth") or {}
    if "trajectory_rmse_px" in truth:
        rows.append(["RMSE vs truth (px)", f"{truth['trajectory_rmse_px']:.3f}"])
    table = "".join(f"<tr><td style='text-align:left'>{_e(k)}</td><td style='text-align:left'>{_e(v)}</td></tr>"
                    for k, v in rows)
    thumb = png_data_uri(panorama_png(panorama, max_side=thumbnail_px))
    return (f"<div><b>photonpano RunResult</b> &nbsp; status: {_status(summary)}"
            f"<style>.status{{padding:0 .4em;border-radius:.3em;color:#fff}}.ok{{background:#2a7d2a}}"
            f".degraded{{background:#c07000}}.unknown{{background:#777}}</style>"
            f"<table>{table}</table><img alt='panorama' src='{thumb}'></div>")


def show(result: Any) -> None:
    """Show a run: its full report in a notebook (IPython), else the panorama in a matplotlib window.

    Args:
        result: a :class:`~photonpano.pipeline.RunResult` (``summary``, ``panorama``,
            ``homographies``, ``uncertainty``).
    """
    try:
        from IPython import get_ipython
        from IPython.display import HTML, display
    except ImportError:
        get_ipython = None
    if get_ipython is not None and get_ipython() is not None:
        display(HTML(report_html(result.summary, result.panorama, result.homographies, result.uncertainty)))
        return
    import matplotlib.pyplot as plt

    from .photons import tone_map

    fig, axis = plt.subplots(figsize=(10, 10 * result.panorama.shape[0] / max(result.panorama.shape[1], 1) + 0.6))
    axis.imshow(tone_map(result.panorama), cmap="gray", vmin=0, vmax=255)
    axis.set_title(f"status: {result.summary.get('status', 'unknown')}, "
                   f"{len(result.summary.get('warnings') or [])} warning(s)")
    axis.set_axis_off()
    plt.show()
