"""The photographs of the evaluation suite's outside check, written into a folder for ``suite.py --photos``.

Defaults are chosen on the suite's own photographs (``benchmarks/photos``), so they are
checked again on photographs they were not chosen on: scikit-image's sample images
(bundled with the ``scikit-image`` package of the ``test`` extra, no download). Besides
photographs (cells, coins, a stained tissue, the moon, a printed page, a retina, a
rocket, a motorbike, a clock, text on a wall) the set holds scenes of flat regions and
hard edges that no suite photograph is like: a horse's silhouette, a logo, the
Shepp-Logan phantom and a checkerboard (docs/accuracy.md, "Flat scenes of hard edges").

Usage::

    python benchmarks/outside_photos.py /tmp/outside
    python benchmarks/suite.py --photos /tmp/outside --json outside.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

IMAGES = {
    "cell": "cell", "checkerboard": "checkerboard", "clock_motion": None, "coins": "coins", "horse": "horse",
    "immunohistochemistry": "immunohistochemistry", "logo": "logo", "microaneurysms": "microaneurysms",
    "moon": "moon", "motorcycle": "stereo_motorcycle", "page": "page", "phantom": "shepp_logan_phantom",
    "retina": "retina", "rocket": "rocket", "text": "text",
}
"""Written file stem -> ``skimage.data`` function (None: a file of ``skimage/data`` read directly)."""


def as_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) uint8 of a ``skimage.data`` image: booleans to 0/255, alpha dropped, floats scaled.

    Raises:
        ValueError: if the image is neither 2-D nor 3-D with 3 or 4 channels.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = image[..., :3]
    elif image.ndim != 2:
        raise ValueError(f"expected a grey or colour image, got shape {image.shape}")
    if image.dtype == bool:
        return image.astype(np.uint8) * 255
    if image.dtype != np.uint8:
        from skimage import img_as_ubyte

        return img_as_ubyte(image)
    return image


def load(stem: str) -> np.ndarray:
    """The uint8 image written as ``stem``.png (see :data:`IMAGES`)."""
    import skimage.data
    import skimage.io

    name = IMAGES[stem]
    if name is None:
        return as_uint8(skimage.io.imread(Path(skimage.data.__file__).parent / f"{stem}.png"))
    image = getattr(skimage.data, name)()
    if isinstance(image, tuple):  # the stereo pair: its left view
        image = image[0]
    return as_uint8(image)


def write(folder: Path, stems: list[str] | None = None) -> list[Path]:
    """Write the images (all of :data:`IMAGES` by default) into ``folder`` as PNG; returns their paths.

    Raises:
        FileExistsError: if a file of that name is already there (nothing is overwritten).
    """
    import skimage.io

    folder.mkdir(parents=True, exist_ok=True)
    stems = stems or list(IMAGES)
    existing = [folder / f"{s}.png" for s in stems if (folder / f"{s}.png").exists()]
    if existing:
        raise FileExistsError(f"{existing[0]} exists: choose an empty folder")
    paths = []
    for stem in stems:
        path = folder / f"{stem}.png"
        skimage.io.imsave(path, load(stem), check_contrast=False)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    """Write the outside check's photographs into the given folder."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--only", default="", help="comma-separated stems (default: all)")
    args = parser.parse_args(argv)
    stems = [s for s in args.only.split(",") if s] or None
    unknown = sorted(set(stems or []) - set(IMAGES))
    if unknown:
        parser.error(f"unknown stems {unknown}; known: {', '.join(IMAGES)}")
    try:
        paths = write(args.folder, stems)
    except FileExistsError as exc:
        print(f"outside_photos: {exc}", file=sys.stderr)
        return 1
    print(f"{len(paths)} photographs in {args.folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
