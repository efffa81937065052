"""Locator ``kornia-sift``: kornia's SIFT, mutual-nearest-neighbour matching, kornia's RANSAC.

A differentiable-vision backend on CPU or a CUDA device: each merged frame is described
once (cached by content) with kornia's SIFT (``kornia.feature.SIFTFeatureScaleSpace`` by
default, ``SIFTFeature`` with ``detector: multires``), pairs are matched with
``kornia.feature.match_smnn`` (mutual nearest neighbours, plus a ratio test unless
``ratio`` is 1, then ``match_mnn``) and the homography is fitted by
``kornia.geometry.RANSAC`` (LO-RANSAC with Levenberg-Marquardt refinement). kornia puts
pixel centres at integers, as photonpano does, so keypoints need no conversion. The
result can be polished by ECC like the OpenCV feature locators.

Needs the optional ``kornia`` extra (``pip install 'photonpano[kornia]'``); torch and
kornia are imported when the locator is built, never at registration.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from photonpano import hookimpl
from photonpano.stages import LocatorConfig
from pydantic import Field

from .common import FeatureLocator, Features, PairResult, PolishConfig, keypoint_mask

__all__ = ["KorniaSiftConfig", "KorniaSiftLocator", "torch_device"]


class KorniaSiftConfig(PolishConfig):
    """kornia SIFTFeature + mutual-nearest-neighbour matching + kornia RANSAC homography."""

    plugin: Literal["kornia-sift"] = "kornia-sift"
    requires: ClassVar[tuple[str, ...]] = ("torch", "kornia")
    install_hint: ClassVar[str] = "pip install 'photonpano[kornia]'"

    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where kornia runs: ``auto`` picks the first CUDA device if torch sees one, else the CPU."""
    detector: Literal["scale-space", "multires"] = "scale-space"
    """kornia's SIFT: ``scale-space`` is ``SIFTFeatureScaleSpace`` (classical DoG
    scale-space extrema with sub-pixel, sub-scale refinement); ``multires`` is
    ``SIFTFeature`` (DoG per pyramid level, no sub-pixel refinement: keypoints of coarse
    levels are off by up to a pixel, which costs accuracy on merged frames)."""
    max_features: Annotated[int, Field(gt=0)] = 2000
    """Keypoints detected per merged frame (kornia's ``num_features``)."""
    upright: bool = False
    """Skip orientation estimation (faster; merged frames of a panning camera barely rotate)."""
    ratio: Annotated[float, Field(gt=0, le=1)] = 0.8
    """Ratio test on descriptor distances on top of the mutual check (1 = plain mutual
    nearest neighbours)."""
    reprojection_px: Annotated[float, Field(gt=0)] = 1.5
    """RANSAC inlier threshold, in pixels."""
    ransac_iterations: Annotated[int, Field(gt=0)] = 20
    """RANSAC iterations (each scores a batch of hypotheses; kornia's ``max_iter``)."""
    min_inliers: Annotated[int, Field(ge=4)] = 12
    """A pair with fewer inliers is flagged as failed (and bridged)."""
    border_px: Annotated[int, Field(ge=0)] = 8
    """Keypoints closer than this (pixels) to untrusted pixels are dropped."""
    seed: Annotated[int, Field(ge=0)] = 0
    """Seed of RANSAC's sampling (runs are repeatable)."""

    def build(self) -> KorniaSiftLocator:
        """Return the locator (imports torch and kornia).

        Raises:
            MissingDependency: if torch or kornia is not installed.
        """
        self.check_available()
        return KorniaSiftLocator(self)


def torch_device(name: str) -> Any:
    """Return the ``torch.device`` for ``auto``, ``cpu`` or ``cuda``.

    Raises:
        photonpano.errors.StageError: for ``cuda`` when torch sees no CUDA device.
    """
    import torch
    from photonpano.errors import StageError

    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise StageError("locator", "kornia", "device 'cuda' requested but torch sees no CUDA device "
                         f"(torch {torch.__version__}); use device: cpu or auto")
    return torch.device(name)


class KorniaSiftLocator(FeatureLocator):
    """Registers pairs with kornia (see :class:`KorniaSiftConfig`).

    Attributes:
        device: the ``torch.device`` kornia runs on.
    """

    thread_safe = False  # one extractor object per locator (torch / COLMAP state)

    def __init__(self, config: KorniaSiftConfig) -> None:
        import kornia.feature as KF
        import torch
        from kornia.geometry import RANSAC

        super().__init__(config)
        self.device = torch_device(config.device)
        self._torch = torch
        self._kf = KF
        detector = KF.SIFTFeatureScaleSpace if config.detector == "scale-space" else KF.SIFTFeature
        self._sift = detector(num_features=config.max_features, upright=config.upright,
                              device=self.device).eval()
        self._ransac = RANSAC("homography", inl_th=config.reprojection_px, max_iter=config.ransac_iterations,
                              confidence=0.9999, seed=config.seed)

    def describe(self, image: NDArray[np.uint8], mask: NDArray[np.bool_],
                 flux: NDArray[np.float32]) -> Features:
        """Detect and describe SIFT keypoints with kornia (see :meth:`FeatureLocator.describe`).

        Returns:
            Features with (K, 2) float64 points and a (K, 128) float32 torch tensor of
            descriptors on :attr:`device`.
        """
        torch = self._torch
        with torch.inference_mode():
            img = torch.from_numpy(np.ascontiguousarray(image)).to(self.device, torch.float32)
            img = img[None, None] / 255.0
            lafs, _, descs = self._sift(img)
            filled = self._kf.laf_is_filled(lafs)[0]
            centres = self._kf.get_laf_center(lafs)[0][filled]
            descs = descs[0][filled]
            points = centres.double().cpu().numpy()
        if len(points):
            allowed = keypoint_mask(mask, self.config.border_px)
            col = np.clip(np.rint(points[:, 0]).astype(int), 0, image.shape[1] - 1)
            row = np.clip(np.rint(points[:, 1]).astype(int), 0, image.shape[0] - 1)
            keep = allowed[row, col].astype(bool)
            points, descs = points[keep], descs[torch.from_numpy(keep).to(descs.device)]
        return Features(points, descs)

    def match(self, feat_a: Features, feat_b: Features) -> PairResult:
        """Mutual-nearest-neighbour matching and kornia RANSAC (homography b to a)."""
        torch = self._torch
        if len(feat_a) < 4 or len(feat_b) < 4:
            return PairResult()
        cfg = self.config
        with torch.inference_mode():
            if cfg.ratio < 1:
                _, idx = self._kf.match_smnn(feat_b.descriptors, feat_a.descriptors, cfg.ratio)
            else:
                _, idx = self._kf.match_mnn(feat_b.descriptors, feat_a.descriptors)
            idx = idx.cpu().numpy()
            n = len(idx)
            if n < max(4, cfg.min_inliers):
                return PairResult(matches=n)
            src = torch.from_numpy(feat_b.points[idx[:, 0]]).to(self.device, torch.float32)
            dst = torch.from_numpy(feat_a.points[idx[:, 1]]).to(self.device, torch.float32)
            try:
                h, inliers = self._ransac(src, dst)
            except (RuntimeError, ValueError):  # degenerate samples
                return PairResult(matches=n)
            h = h.double().cpu().numpy()
            n_in = int(inliers.sum().item())
        if not np.all(np.isfinite(h)) or abs(h[2, 2]) < 1e-12:
            return PairResult(matches=n, inliers=n_in)
        h = h / h[2, 2]
        ok = n_in >= cfg.min_inliers and abs(np.linalg.det(h[:2, :2])) > 1e-3
        return PairResult(h, n, n_in, bool(ok))


@hookimpl
def photonpano_register_locators() -> list[type[LocatorConfig]]:
    """Register ``kornia-sift``."""
    return [KorniaSiftConfig]
