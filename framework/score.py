"""Image quality scores of the Single Photon Challenge: PSNR and MS-SSIM, mean and worst-case quantiles.

``photonpano score PANORAMA REFERENCE`` compares reconstructions with reference images as
the challenge's evaluation server does (``wision-lab/spcwebsite``,
``eval/management/commands/evaluate_submissions.py``, with torchmetrics'
``PeakSignalNoiseRatio(data_range=(0, 1))`` and
``MultiScaleStructuralSimilarityIndexMeasure(data_range=(0, 1))``):

- images are read as floats in ``[0, 1]`` (8-bit codes / 255, 16-bit codes / 65535; float
  images must already lie in ``[0, 1]``), an alpha channel dropped, RGB channel order;
- **PSNR** (:func:`psnr`): ``10 log10(1 / MSE)`` in dB, the mean squared error over all
  pixels and channels of one image pair (peak 1, no gain fit: unlike
  :func:`photonpano.metrics.psnr`, which scores linear flux against simulated truth);
- **MS-SSIM** (:func:`ms_ssim`): Wang, Simoncelli and Bovik, "Multiscale structural
  similarity for image quality assessment", Asilomar 2003: 5 scales, exponents
  ``(0.0448, 0.2856, 0.3001, 0.2363, 0.1333)``, an 11x11 Gaussian window of sigma 1.5,
  ``K1 = 0.01``, ``K2 = 0.03``, dynamic range 1; at each scale the contrast-structure term
  (scales 1-4) or the SSIM (scale 5) is averaged over the positions where the window lies
  inside the image and over the channels, negative averages are clipped to 0 (torchmetrics'
  default ``normalize="relu"``), and the image is halved by 2x2 averaging between scales;
- **worst-case quantiles**: over the image pairs scored together (a folder), the 5 % and
  1 % quantiles of the per-image values (``np.quantile``, linear interpolation; the low
  tail, as both scores grow with quality), the challenge's "5% Low" and "1% Low". For a
  single pair they equal its value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import PhotonpanoError

__all__ = ["MS_SSIM_WEIGHTS", "IMAGE_SUFFIXES", "ImageScore", "load_image", "psnr", "ms_ssim", "score_images",
           "score_paths", "summarize", "format_table"]

MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
"""Exponents of the five MS-SSIM scales, finest first (Wang et al. 2003)."""

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".npy")
"""File types ``score`` reads (images through OpenCV or tifffile, arrays through NumPy)."""

QUANTILES = (0.05, 0.01)
"""The worst-case quantiles reported (the challenge's 5 % and 1 % lows)."""


@dataclass(frozen=True)
class ImageScore:
    """Scores of one image pair.

    Attributes:
        name: the pair's name (the path relative to the folders, or the file name).
        psnr_db: PSNR in dB (``inf`` for identical images).
        ms_ssim: MS-SSIM in ``[0, 1]`` (1: identical).
    """

    name: str
    psnr_db: float
    ms_ssim: float


def load_image(path: Path, what: str = "score") -> NDArray[np.float64]:
    """Read an image as float64 values in ``[0, 1]``.

    Args:
        path: a PNG/JPEG/TIFF (OpenCV; TIFF pages beyond the first, e.g. the validity mask
            of ``panorama.tif``, are ignored) or an ``.npy`` array, (H, W) grey or (H, W, 3|4)
            colour; an alpha channel is dropped.
        what: how messages name the caller.

    Returns:
        (H, W) or (H, W, 3) float64 in ``[0, 1]``, colour in RGB order: uint8 codes / 255,
        uint16 codes / 65535, bool as 0/1, float values as stored.

    Raises:
        PhotonpanoError: a missing or unreadable file, an unsupported shape or dtype, or
            float values outside ``[0, 1]`` or not finite (e.g. ``panorama.npy``, linear
            flux in photons/s: score the tone-mapped ``panorama.png`` instead); one line
            naming the file.
    """
    if not path.is_file():
        raise PhotonpanoError(f"{what}: {path} does not exist or is not a file")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        from .npy_header import load_npy

        image = load_npy(path, what)
    elif suffix in (".tif", ".tiff"):
        import tifffile

        try:
            image = tifffile.imread(path, key=0)
        except Exception as exc:  # tifffile raises many types for a bad file
            raise PhotonpanoError(f"{what}: {path} is not a readable TIFF ({' '.join(str(exc).split())[:120]})") \
                from None
    else:
        import cv2

        decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if decoded is None:
            raise PhotonpanoError(f"{what}: {path} is not an image OpenCV can decode")
        image = decoded
        if image.ndim == 3:
            image = image[..., 2::-1] if image.shape[2] >= 3 else image  # BGR(A) -> RGB
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise PhotonpanoError(f"{what}: {path} has shape {image.shape}; expected an (H, W) grey or (H, W, 3) "
                              "colour image")
    if image.dtype == np.uint8:
        return image.astype(np.float64) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float64) / 65535.0
    if image.dtype == np.bool_:
        return image.astype(np.float64)
    if image.dtype.kind != "f":
        raise PhotonpanoError(f"{what}: {path} holds {image.dtype}; expected uint8, uint16 or float values in "
                              "[0, 1]")
    image = image.astype(np.float64)
    if not np.isfinite(image).all() or image.min(initial=0.0) < 0.0 or image.max(initial=0.0) > 1.0:
        raise PhotonpanoError(f"{what}: {path} holds float values outside [0, 1] (or NaN); expected an image "
                              "in [0, 1] (for a photonpano run, score panorama.png, not the linear flux)")
    return image


def psnr(estimate: NDArray, reference: NDArray) -> float:
    """PSNR of an image against its reference, peak value 1.

    Args:
        estimate: (H, W) or (H, W, C) float values in ``[0, 1]`` (clipped to it).
        reference: the same shape.

    Returns:
        ``10 log10(1 / MSE)`` in dB over all pixels and channels; ``inf`` if identical.

    Raises:
        ValueError: if the shapes differ.
    """
    e, r = _pair(estimate, reference)
    mse = float(np.mean((e - r) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def _pair(estimate: NDArray, reference: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    e = np.clip(np.asarray(estimate, np.float64), 0.0, 1.0)
    r = np.clip(np.asarray(reference, np.float64), 0.0, 1.0)
    if e.shape != r.shape:
        raise ValueError(f"images of different shapes {e.shape} and {r.shape}")
    return e, r


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> NDArray[np.float64]:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _ssim_terms(x: NDArray[np.float64], y: NDArray[np.float64], window: NDArray[np.float64],
                c1: float, c2: float) -> tuple[float, float]:
    """Mean SSIM and mean contrast-structure term of (H, W, C) images over the valid window positions."""
    from scipy.ndimage import correlate1d

    half = len(window) // 2

    def blur(a: NDArray[np.float64]) -> NDArray[np.float64]:
        a = correlate1d(correlate1d(a, window, axis=0, mode="nearest"), window, axis=1, mode="nearest")
        return a[half:a.shape[0] - half, half:a.shape[1] - half]  # only positions whose window lies inside

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x ** 2
    var_y = blur(y * y) - mu_y ** 2
    cov = blur(x * y) - mu_x * mu_y
    cs = (2 * cov + c2) / (var_x + var_y + c2)
    luminance = (2 * mu_x * mu_y + c1) / (mu_x ** 2 + mu_y ** 2 + c1)
    return float(np.mean(luminance * cs)), float(np.mean(cs))


def ms_ssim(estimate: NDArray, reference: NDArray, weights: tuple[float, ...] = MS_SSIM_WEIGHTS) -> float:
    """Multi-scale SSIM (Wang, Simoncelli, Bovik 2003) of an image against its reference, dynamic range 1.

    Args:
        estimate: (H, W) or (H, W, C) float values in ``[0, 1]`` (clipped to it).
        reference: the same shape.
        weights: exponents of the scales, finest first (default: the paper's five).

    Returns:
        ``prod_j cs_j ** w_j`` (scales 1..M-1) times ``ssim_M ** w_M``, each term the mean over
        valid window positions and channels, clipped at 0; in ``[0, 1]``, 1 for identical images.

    Raises:
        ValueError: if the shapes differ or the image is too small for the scales: each side
            must exceed ``10 * 16 = 160`` pixels for 5 scales (the coarsest scale must hold an
            11x11 window), as torchmetrics requires.
    """
    e, r = _pair(estimate, reference)
    if e.ndim == 2:
        e, r = e[..., None], r[..., None]
    window = _gaussian_window()
    levels = len(weights)
    div = max(1, levels - 1) ** 2
    if min(e.shape[:2]) // div <= len(window) - 1:
        raise ValueError(f"images of {e.shape[0]}x{e.shape[1]} are too small for {levels}-scale MS-SSIM; each "
                         f"side must exceed {(len(window) - 1) * div} pixels")
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    terms = []
    for level in range(levels):
        sim, cs = _ssim_terms(e, r, window, c1, c2)
        terms.append(max(sim if level == levels - 1 else cs, 0.0))
        if level < levels - 1:
            h, w = e.shape[0] // 2 * 2, e.shape[1] // 2 * 2
            e = e[:h, :w].reshape(h // 2, 2, w // 2, 2, -1).mean(axis=(1, 3))
            r = r[:h, :w].reshape(h // 2, 2, w // 2, 2, -1).mean(axis=(1, 3))
    return float(np.prod([t ** wgt for t, wgt in zip(terms, weights)]))


def score_images(estimate: NDArray, reference: NDArray, name: str = "") -> ImageScore:
    """Score one image pair; a grey image against a colour one is compared as three equal channels.

    Args:
        estimate: (H, W) or (H, W, 3) float in ``[0, 1]``.
        reference: (H, W) or (H, W, 3) float in ``[0, 1]``, the same H and W.
        name: the pair's name.

    Returns:
        The pair's :class:`ImageScore`.

    Raises:
        ValueError: different sizes, or images too small for MS-SSIM.
    """
    if estimate.ndim != reference.ndim:
        estimate, reference = (np.repeat(a[..., None], 3, axis=2) if a.ndim == 2 else a
                               for a in (estimate, reference))
    if estimate.shape != reference.shape:
        raise ValueError(f"the image is {estimate.shape[1]}x{estimate.shape[0]}, the reference "
                         f"{reference.shape[1]}x{reference.shape[0]}")
    return ImageScore(name, psnr(estimate, reference), ms_ssim(estimate, reference))


def _pairs(panorama: Path, reference: Path) -> list[tuple[str, Path, Path]]:
    for path in (panorama, reference):
        if not path.exists():
            raise PhotonpanoError(f"score: {path} does not exist")
    if reference.is_dir() != panorama.is_dir():
        raise PhotonpanoError(f"score: {panorama} and {reference} must both be image files or both folders")
    if not reference.is_dir():
        return [(panorama.name, panorama, reference)]
    refs = sorted(p for p in reference.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not refs:
        raise PhotonpanoError(f"score: no reference images ({', '.join(IMAGE_SUFFIXES)}) in {reference}")
    found = {p.relative_to(panorama).with_suffix("").as_posix(): p for p in panorama.rglob("*")
             if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()}
    pairs, missing = [], []
    for ref in refs:
        key = ref.relative_to(reference).with_suffix("").as_posix()
        if key in found:
            pairs.append((key, found[key], ref))
        else:
            missing.append(key)
    if missing:
        raise PhotonpanoError(f"score: {panorama} has no image for {len(missing)} of the {len(refs)} references "
                              f"in {reference}, e.g. {missing[0]} (images pair by relative path, any suffix)")
    return pairs


def score_paths(panorama: Path, reference: Path) -> list[ImageScore]:
    """Score an image against a reference image, or every reference in a folder against its counterpart.

    Args:
        panorama: an image, or a folder of images.
        reference: an image, or a folder; each reference image pairs with the image of
            ``panorama`` at the same relative path (any of :data:`IMAGE_SUFFIXES`), e.g. the
            challenge's ``<SCENE-NAME>/<FRAME-IDX>.png``; images of ``panorama`` without a
            reference are not scored.

    Returns:
        One :class:`ImageScore` per reference image, in the references' sorted order.

    Raises:
        PhotonpanoError: a file and a folder, a reference without its image, unreadable
            images (see :func:`load_image`), different sizes, or images too small for
            MS-SSIM; one line naming the files.
    """
    scores = []
    for name, image_path, ref_path in _pairs(panorama, reference):
        image, ref = load_image(image_path), load_image(ref_path)
        try:
            scores.append(score_images(image, ref, name))
        except ValueError as exc:
            raise PhotonpanoError(f"score: {image_path} against {ref_path}: {exc}") from None
    return scores


def summarize(scores: list[ImageScore]) -> dict[str, Any]:
    """Return the mean and worst-case quantiles of per-image scores.

    Args:
        scores: at least one :class:`ImageScore`.

    Returns:
        ``{"images": n, "psnr_db": {"mean", "low_5pct", "low_1pct"}, "ms_ssim": {...}}``:
        the mean and the 5 % and 1 % quantiles (``np.quantile``, linear) of the
        per-image values; PSNR values are ``inf`` for identical images.
    """
    out: dict[str, Any] = {"images": len(scores)}
    for key in ("psnr_db", "ms_ssim"):
        values = np.array([getattr(s, key) for s in scores], dtype=np.float64)
        # identical images score PSNR inf; interpolating towards inf gives inf (numpy would give NaN at weight 0)
        capped = np.where(np.isinf(values), _INF_STAND_IN, values)
        top = float(np.max(values[np.isfinite(values)], initial=-math.inf))
        lows = [float(v) if v <= top else math.inf for v in np.quantile(capped, QUANTILES)]
        out[key] = {"mean": float(np.mean(values)), "low_5pct": lows[0], "low_1pct": lows[1]}
    return out


_INF_STAND_IN = 1e12
"""Stands in for an infinite PSNR while interpolating quantiles."""


def format_table(summary: dict[str, Any]) -> str:
    """Return the summary as a short plain-text table (one row per metric)."""
    rows = [f"{'metric':<10}{'mean':>10}{'5 % low':>10}{'1 % low':>10}   ({summary['images']} image"
            f"{'s' if summary['images'] != 1 else ''})"]
    for key, label, fmt in (("psnr_db", "PSNR (dB)", "{:10.3f}"), ("ms_ssim", "MS-SSIM", "{:10.4f}")):
        s = summary[key]
        rows.append(f"{label:<10}" + "".join(fmt.format(s[k]) for k in ("mean", "low_5pct", "low_1pct")))
    return "\n".join(rows)
