"""``photonpano score``: the Single Photon Challenge's PSNR, MS-SSIM and worst-case quantiles.

MS-SSIM and PSNR are checked against values computed with torchmetrics 1.9.0
(``MultiScaleStructuralSimilarityIndexMeasure(data_range=(0, 1))`` and
``PeakSignalNoiseRatio(data_range=(0, 1))``, what the challenge's evaluation server uses)
on the images :func:`_pair` makes, and live (torchmetrics and scikit-image are test
dependencies: PSNR against both). Known properties and a hand computation cover the rest.
"""

import json
import math

import cv2
import numpy as np
import pytest
from photonpano.cli import app
from photonpano.errors import PhotonpanoError
from photonpano.score import ImageScore, load_image, ms_ssim, psnr, score_paths, summarize
from typer.testing import CliRunner

runner = CliRunner()


def _pair(h, w, noise, seed):
    """A smooth colour reference and a dimmed, offset, noisy estimate, both quantized to 8 bits."""
    yy, xx = np.mgrid[0:h, 0:w]
    ref = np.stack([0.5 + 0.4 * np.sin(xx / 9.0 + c) * np.cos(yy / 13.0) for c in range(3)], -1)
    est = np.clip(ref * 0.9 + 0.03 + np.random.default_rng(seed).normal(0, noise, ref.shape), 0, 1)
    return np.round(est * 255) / 255, np.round(ref * 255) / 255


# (h, w, noise, seed), torchmetrics MS-SSIM, torchmetrics PSNR (dB)
TORCHMETRICS = [((192, 200, 0.05, 1), 0.9518240094184875, 24.813724517822266),
                ((240, 180, 0.2, 2), 0.7255173921585083, 14.29687786102295),
                ((256, 256, 0.02, 3), 0.9862719178199768, 29.152904510498047)]


@pytest.mark.parametrize("args,want_msssim,want_psnr", TORCHMETRICS)
def test_ms_ssim_and_psnr_match_torchmetrics(args, want_msssim, want_psnr):
    est, ref = _pair(*args)
    assert ms_ssim(est, ref) == pytest.approx(want_msssim, abs=2e-4)
    assert psnr(est, ref) == pytest.approx(want_psnr, abs=1e-4)


def test_ms_ssim_matches_torchmetrics_live():
    torch = pytest.importorskip("torch")
    tm = pytest.importorskip("torchmetrics.image")
    est, ref = _pair(200, 230, 0.1, 9)
    t = [torch.tensor(a, dtype=torch.float32).permute(2, 0, 1)[None] for a in (est, ref)]
    want = float(tm.MultiScaleStructuralSimilarityIndexMeasure(data_range=(0, 1))(*t))
    assert ms_ssim(est, ref) == pytest.approx(want, abs=2e-4)


def test_psnr_matches_scikit_image_and_torchmetrics_live():
    """PSNR against scikit-image's and torchmetrics' (both test dependencies), grey and colour."""
    from skimage.metrics import peak_signal_noise_ratio

    torch = pytest.importorskip("torch")
    tm = pytest.importorskip("torchmetrics.image")
    for args in ((120, 150, 0.05, 5), (200, 230, 0.2, 6)):
        est, ref = _pair(*args)
        for e, r in ((est, ref), (est[..., 0], ref[..., 0])):
            assert psnr(e, r) == pytest.approx(peak_signal_noise_ratio(r, e, data_range=1.0), abs=1e-9)
        t = [torch.tensor(a, dtype=torch.float64).permute(2, 0, 1)[None] for a in (est, ref)]
        assert psnr(est, ref) == pytest.approx(float(tm.PeakSignalNoiseRatio(data_range=(0, 1))(*t)), abs=1e-5)


def test_psnr_by_hand_and_ms_ssim_properties():
    ref = np.zeros((4, 4))
    est = ref.copy()
    est[0, 0] = 0.5  # MSE = 0.25 / 16
    assert psnr(est, ref) == pytest.approx(10 * math.log10(16 / 0.25))
    assert psnr(ref, ref) == math.inf
    est, ref = _pair(200, 200, 0.05, 4)
    assert ms_ssim(ref, ref) == pytest.approx(1.0, abs=1e-12)
    assert ms_ssim(est, ref) == pytest.approx(ms_ssim(ref, est), abs=1e-12)  # symmetric
    worse = _pair(200, 200, 0.15, 4)[0]
    assert ms_ssim(worse, ref) < ms_ssim(est, ref) < 1.0
    # a constant image against a textured one: the structure term is ~0 at every scale
    assert ms_ssim(np.full_like(ref, 0.5), ref) < 0.2
    # grey scores the same as its three equal channels
    grey_e, grey_r = est[..., 1], ref[..., 1]
    assert ms_ssim(grey_e, grey_r) == pytest.approx(ms_ssim(np.dstack([grey_e] * 3), np.dstack([grey_r] * 3)))
    with pytest.raises(ValueError, match="too small for 5-scale MS-SSIM; each side must exceed 160 pixels"):
        ms_ssim(np.zeros((160, 300)), np.zeros((160, 300)))


def test_quantiles_are_the_low_tail_over_images_with_linear_interpolation():
    values = np.linspace(20.0, 40.0, 21)  # 21 images: 5 % quantile at position 1.0, 1 % at 0.2
    summary = summarize([ImageScore(str(i), v, v / 40) for i, v in enumerate(values)])
    assert summary["images"] == 21
    assert summary["psnr_db"] == {"mean": pytest.approx(30.0), "low_5pct": pytest.approx(21.0),
                                  "low_1pct": pytest.approx(20.2)}
    assert summary["ms_ssim"]["low_1pct"] == pytest.approx(20.2 / 40)
    ident = summarize([ImageScore("a", math.inf, 1.0), ImageScore("b", 30.0, 0.9)])
    assert ident["psnr_db"]["mean"] == ident["psnr_db"]["low_1pct"] == math.inf  # as np.quantile([30, inf], 0.01)
    assert summarize([ImageScore(str(i), v, 1.0) for i, v in enumerate([*values[:-1], math.inf])])["psnr_db"][
        "low_5pct"] == pytest.approx(21.0)
    one = summarize([ImageScore("a", 25.0, 0.8)])
    assert one["psnr_db"]["low_5pct"] == one["psnr_db"]["low_1pct"] == 25.0


def _write(path, image01):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(image01[..., ::-1] * 255).astype(np.uint8))


def test_score_command_on_folders_table_and_json(tmp_path):
    for scene, frame, noise in (("attic", "000000", 0.02), ("attic", "000001", 0.1), ("bath", "000000", 0.05)):
        est, ref = _pair(200, 200, noise, len(frame) + int(noise * 100))
        _write(tmp_path / "ref" / scene / f"{frame}.png", ref)
        _write(tmp_path / "est" / scene / f"{frame}.png", est)
    result = runner.invoke(app, ["score", str(tmp_path / "est"), str(tmp_path / "ref")])
    assert result.exit_code == 0, result.output
    assert "PSNR (dB)" in result.output and "MS-SSIM" in result.output and "(3 images)" in result.output
    result = runner.invoke(app, ["score", str(tmp_path / "est"), str(tmp_path / "ref"), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    per = {row["name"]: row for row in data["per_image"]}
    assert sorted(per) == ["attic/000000", "attic/000001", "bath/000000"]
    values = [per[k]["psnr_db"] for k in sorted(per)]
    assert data["psnr_db"]["mean"] == pytest.approx(np.mean(values))
    assert data["psnr_db"]["low_5pct"] == pytest.approx(np.quantile(values, 0.05))
    assert min(values) <= data["psnr_db"]["low_1pct"] <= data["psnr_db"]["low_5pct"] <= data["psnr_db"]["mean"]
    est = load_image(tmp_path / "est" / "attic" / "000001.png")
    ref = load_image(tmp_path / "ref" / "attic" / "000001.png")
    assert per["attic/000001"]["ms_ssim"] == pytest.approx(ms_ssim(est, ref))
    assert per["attic/000001"]["ms_ssim"] < per["attic/000000"]["ms_ssim"]  # noisier, worse


def test_bad_inputs_are_one_line_errors(tmp_path):
    est, ref = _pair(200, 200, 0.05, 5)
    _write(tmp_path / "ref" / "a.png", ref)
    _write(tmp_path / "ref" / "b.png", ref)
    _write(tmp_path / "est" / "a.png", est)
    with pytest.raises(PhotonpanoError, match=r"has no image for 1 of the 2 references .* e\.g\. b"):
        score_paths(tmp_path / "est", tmp_path / "ref")
    np.save(tmp_path / "flux.npy", np.full((200, 200), 1234.0, np.float32))
    result = runner.invoke(app, ["score", str(tmp_path / "flux.npy"), str(tmp_path / "ref" / "a.png")])
    assert result.exit_code == 1
    assert "flux.npy holds float values outside [0, 1]" in result.output and len(result.output.splitlines()) == 1
    _write(tmp_path / "small.png", est[:190])
    result = runner.invoke(app, ["score", str(tmp_path / "small.png"), str(tmp_path / "ref" / "a.png")])
    assert result.exit_code == 1 and "the image is 200x190, the reference 200x200" in result.output
    result = runner.invoke(app, ["score", str(tmp_path / "est"), str(tmp_path / "ref" / "a.png")])
    assert result.exit_code == 1 and "must both be image files or both folders" in result.output
