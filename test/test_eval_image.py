"""Image metrics: PSNR, SSIM (against scikit-image) and LPIPS (local weights only)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.eval.image import psnr, ssim, ssim_map
from vings_core.eval.lpips import LPIPS, load_lpips


@pytest.fixture(scope="module")
def photo():
    import skimage.data

    a = skimage.data.astronaut()[::4, ::4].astype(np.float64) / 255.0  # 128x128x3
    rng = np.random.default_rng(0)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    b = np.roll(b, 1, axis=1)  # a structural change too
    return a, b


def test_psnr_known_values():
    a = np.zeros((20, 30, 3))
    b = np.full((20, 30, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)  # MSE 0.01
    assert psnr(a, a) == float("inf")
    # mask: only the masked pixels count
    b2 = b.copy()
    b2[:, 15:] = 0.5
    mask = np.zeros((20, 30), bool)
    mask[:, :15] = True
    assert psnr(a, b2, mask=mask) == pytest.approx(20.0)
    assert psnr(a, b2) < 20.0
    # torch, uint8 and mono inputs
    assert psnr(torch.zeros(8, 8), torch.full((8, 8), 0.1)) == pytest.approx(20.0)
    u = np.zeros((8, 8, 3), np.uint8)
    assert psnr(u, u + 51) == pytest.approx(20 * np.log10(255 / 51))


def test_psnr_matches_skimage(photo):
    from skimage.metrics import peak_signal_noise_ratio

    a, b = photo
    assert psnr(a, b) == pytest.approx(peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-9)


def test_psnr_errors():
    a = np.zeros((8, 8, 3))
    with pytest.raises(InputError, match="differ in shape"):
        psnr(a, np.zeros((8, 9, 3)))
    with pytest.raises(InputError, match="mask shape"):
        psnr(a, a, mask=np.ones((4, 4), bool))
    with pytest.raises(InputError, match="no pixel"):
        psnr(a, a, mask=np.zeros((8, 8), bool))
    with pytest.raises(InputError, match="dtype"):
        psnr(np.zeros((8, 8), np.int32), np.zeros((8, 8), np.int32))


def test_ssim_matches_skimage(photo):
    from skimage.metrics import structural_similarity

    a, b = photo
    kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
    ref = structural_similarity(a, b, channel_axis=2, **kw)
    assert ssim(a, b) == pytest.approx(ref, abs=1e-6)
    ref_g = structural_similarity(a[..., 1], b[..., 1], **kw)
    assert ssim(a[..., 1], b[..., 1]) == pytest.approx(ref_g, abs=1e-6)
    # torch float32 input (tolerance of the brief: 1e-3)
    assert ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(ref, abs=1e-3)
    assert ssim(a, a) == pytest.approx(1.0)
    assert ssim(a, b) == pytest.approx(ssim(b, a))


def test_ssim_map_is_differentiable():
    a = torch.rand(1, 3, 32, 32, dtype=torch.float64, requires_grad=True)
    b = torch.rand(1, 3, 32, 32, dtype=torch.float64)
    m = ssim_map(a, b)
    assert m.shape == (1, 3, 22, 22)
    (1 - m.mean()).backward()
    assert a.grad is not None and torch.isfinite(a.grad).all()
    with pytest.raises(InputError, match="at least 11x11"):
        ssim(np.zeros((8, 8)), np.zeros((8, 8)))


# ----------------------------------------------------------------------------------------- LPIPS


def _random_weights(net: str, path, seed: int = 0) -> dict:
    torch.manual_seed(seed)
    m = LPIPS(net)
    sd = m.state_dict()
    for k in sd:
        if k.startswith("lin"):
            sd[k] = torch.rand_like(sd[k]) + 0.1  # trained LPIPS lin weights are non-negative
    torch.save(sd, path)
    return sd


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_random_weights_properties(tmp_path, photo, net):
    a, b = photo
    a, b = a[:64, :64], b[:64, :64]
    _random_weights(net, tmp_path / "w.pth")
    m = load_lpips(tmp_path / "w.pth")
    assert m.net_name == net
    assert m.distance(a, a) == pytest.approx(0.0, abs=1e-12)
    d_ab, d_ba = m.distance(a, b), m.distance(b, a)
    assert d_ab > 0 and d_ab == pytest.approx(d_ba, rel=1e-9)
    # more different -> larger distance
    assert m.distance(a, 1 - a) > d_ab
    # the same input checks as psnr/ssim: 0..255 floats or NaN are refused, not measured
    with pytest.raises(InputError, match=r"first image: values in .* outside \[0, 1\] \(0..255 floats"):
        m.distance(np.asarray(a, np.float64) * 255, b)
    with pytest.raises(InputError, match="second image: 1 non-finite"):
        bad = np.array(b, np.float64)
        bad.flat[0] = np.nan
        m.distance(a, bad)


def test_lpips_reference_computation(tmp_path, photo):
    """The network equals a plain functional re-statement of LPIPS v0.1 with the same weights."""
    import torch.nn.functional as F

    a, b = photo
    sd = _random_weights("alex", tmp_path / "w.pth", seed=3)
    m = load_lpips(tmp_path / "w.pth")
    x = [torch.from_numpy(im[:64, :64]).permute(2, 0, 1)[None].float() for im in (a, b)]
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feats(img):
        h = ((2 * img - 1) - shift) / scale
        out = []
        h = F.relu(F.conv2d(h, sd["net.slice1.0.weight"], sd["net.slice1.0.bias"], stride=4, padding=2))
        out.append(h)
        h = F.relu(F.conv2d(F.max_pool2d(h, 3, 2), sd["net.slice2.3.weight"], sd["net.slice2.3.bias"], padding=2))
        out.append(h)
        h = F.relu(F.conv2d(F.max_pool2d(h, 3, 2), sd["net.slice3.6.weight"], sd["net.slice3.6.bias"], padding=1))
        out.append(h)
        h = F.relu(F.conv2d(h, sd["net.slice4.8.weight"], sd["net.slice4.8.bias"], padding=1))
        out.append(h)
        h = F.relu(F.conv2d(h, sd["net.slice5.10.weight"], sd["net.slice5.10.bias"], padding=1))
        out.append(h)
        return out

    total = 0.0
    for k, (f0, f1) in enumerate(zip(feats(x[0]), feats(x[1]))):
        n0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        n1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        total += float((((n0 - n1) ** 2) * sd[f"lin{k}.model.1.weight"]).sum(1).mean())
    assert m.distance(a[:64, :64], b[:64, :64]) == pytest.approx(total, rel=1e-5)


def test_lpips_accepts_aliases(tmp_path, photo):
    a, b = photo
    a, b = a[:64, :64], b[:64, :64]
    sd = _random_weights("alex", tmp_path / "w.pth")
    ref = load_lpips(tmp_path / "w.pth").distance(a, b)
    alias = {}
    for k, v in sd.items():
        if k.startswith("net."):
            alias["features." + k.split(".", 2)[2]] = v  # torchvision naming
        elif k.startswith("lin"):
            alias["lins." + k[3:]] = v  # the official ModuleList alias
    torch.save(alias, tmp_path / "alias.pth")
    assert load_lpips(tmp_path / "alias.pth").distance(a, b) == pytest.approx(ref, rel=1e-9)


def test_lpips_bad_files(tmp_path):
    with pytest.raises(InputError, match="weights file not found"):
        load_lpips(tmp_path / "nope.pth")
    sd = _random_weights("alex", tmp_path / "w.pth")
    del sd["lin3.model.1.weight"]
    torch.save(sd, tmp_path / "inc.pth")
    with pytest.raises(InputError, match="incomplete LPIPS-alex weights.*lin3.model.1.weight"):
        load_lpips(tmp_path / "inc.pth")
    sd = _random_weights("alex", tmp_path / "w.pth")
    sd["lin0.model.1.weight"] = torch.zeros(1, 65, 1, 1)
    torch.save(sd, tmp_path / "shape.pth")
    with pytest.raises(InputError, match="lin0.model.1.weight has shape"):
        load_lpips(tmp_path / "shape.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="not a readable LPIPS weights file"):
        load_lpips(tmp_path / "junk.pth")
    torch.save({"foo": torch.zeros(3)}, tmp_path / "other.pth")
    with pytest.raises(InputError, match="no LPIPS backbone"):
        load_lpips(tmp_path / "other.pth")
    m = load_lpips(tmp_path / "w.pth")
    with pytest.raises(InputError, match="at least 32x32"):
        m.distance(np.zeros((16, 16, 3)), np.zeros((16, 16, 3)))


def test_metric_ranges_and_dtypes_are_checked():
    from vings_core.errors import InputError
    from vings_core.eval.image import psnr, ssim
    rng = np.random.default_rng(3)
    a8 = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    b8 = np.clip(a8.astype(int) + rng.integers(-9, 10, a8.shape), 0, 255).astype(np.uint8)
    # uint8 with the skimage habit data_range=255 is the same measurement as the default
    assert psnr(a8, b8, data_range=255) == pytest.approx(psnr(a8, b8))
    assert ssim(a8, b8, data_range=255) == pytest.approx(ssim(a8, b8))
    assert psnr(a8, b8) == pytest.approx(psnr(a8 / 255.0, b8 / 255.0))
    with pytest.raises(InputError, match="uint8 images are compared in"):
        psnr(a8, b8, data_range=2.0)
    # 0..255 floats without /255: refused with the hint, not a negative PSNR
    with pytest.raises(InputError, match="divide by 255"):
        psnr(a8.astype(np.float32), b8 / 255.0)
    with pytest.raises(InputError, match="divide by 255"):
        ssim(a8.astype(np.float64), b8.astype(np.float64))
    # ... unless that is the scale given
    assert psnr(a8.astype(np.float64), b8.astype(np.float64), data_range=255) == pytest.approx(psnr(a8, b8))
    bad = a8 / 255.0
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        psnr(bad, b8)
