"""SIFT bag of words: descriptors, k-means vocabulary, quantisation, persistence."""

from __future__ import annotations

import numpy as np
import pytest

from ptm_ros.errors import DataError, ModelError
from ptm_ros.model.vocabulary import DESCRIPTOR_SIZE, Vocabulary, sift_descriptors


def _panorama(rng: np.random.Generator, h: int = 64, w: int = 512) -> np.ndarray:
    """A textured 64×512 mono8 panorama: random rectangles of random grey on grey, plus noise."""
    img = np.full((h, w), 0.5)
    for _ in range(60):
        x0, y0 = rng.integers(0, w), rng.integers(0, h)
        img[y0 : y0 + rng.integers(4, 30), x0 : x0 + rng.integers(4, 40)] = rng.random()
    img += 0.03 * rng.standard_normal((h, w))
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


@pytest.fixture(scope="module")
def panoramas() -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [_panorama(rng) for _ in range(12)]


@pytest.fixture(scope="module")
def descriptors(panoramas) -> np.ndarray:
    return np.concatenate([sift_descriptors(im) for im in panoramas])


def test_textured_panorama_yields_sift_descriptors(panoramas):
    d = sift_descriptors(panoramas[0])
    assert d.dtype == np.float32
    assert d.shape[1] == DESCRIPTOR_SIZE
    assert d.shape[0] > 50
    assert np.all(d >= 0)  # SIFT histograms of gradient magnitudes
    # a flat image has none; RGB and float inputs go through the same grey conversion
    assert sift_descriptors(np.full((64, 512), 128, np.uint8)).shape == (0, DESCRIPTOR_SIZE)
    rgb = np.repeat(panoramas[0][:, :, None], 3, axis=2)
    np.testing.assert_array_equal(sift_descriptors(rgb), d)
    np.testing.assert_array_equal(sift_descriptors(panoramas[0] / 255.0), d)
    strongest = sift_descriptors(panoramas[0], max_features=10)
    assert strongest.shape == (10, DESCRIPTOR_SIZE)
    assert {r.tobytes() for r in strongest} <= {r.tobytes() for r in d}


def test_circular_padding_makes_words_invariant_to_heading(panoramas, descriptors):
    voc = Vocabulary.build(descriptors, 32, np.random.default_rng(0))
    img = panoramas[0]
    ref = voc.panorama_words(img)
    # a turn by a multiple of the coarsest SIFT sampling step is a circular shift of the padded image
    for shift in (64, 200, 256):
        np.testing.assert_array_equal(voc.panorama_words(np.roll(img, shift, axis=1)), ref)
    unwrapped = [
        np.abs(
            voc.panorama_words(np.roll(img, s, axis=1), wrap=False) - voc.panorama_words(img, wrap=False)
        ).sum()
        for s in (64, 200, 256)
    ]
    assert max(unwrapped) > 0  # without padding, keypoints at the seam are lost or gained


def test_words_count_every_descriptor_at_its_nearest_centre(descriptors):
    voc = Vocabulary.build(descriptors, 40, np.random.default_rng(2))
    assert voc.size == 40
    some = descriptors[:300]
    counts = voc.words(some)
    assert counts.dtype == np.int64
    assert counts.shape == (40,)
    assert counts.sum() == len(some)
    # brute force nearest centre
    dist = np.linalg.norm(some[:, None, :].astype(float) - voc.centers[None].astype(float), axis=2)
    np.testing.assert_array_equal(voc.quantize(some), dist.argmin(axis=1))
    np.testing.assert_array_equal(counts, np.bincount(dist.argmin(axis=1), minlength=40))
    assert voc.words(np.zeros((0, DESCRIPTOR_SIZE))).sum() == 0


def test_kmeans_recovers_separated_clusters():
    rng = np.random.default_rng(3)
    means = rng.uniform(0, 200, size=(3, DESCRIPTOR_SIZE))
    labels = np.repeat(np.arange(3), 100)
    data = means[labels] + rng.normal(0, 1.0, size=(300, DESCRIPTOR_SIZE))
    voc = Vocabulary.build(data, 3, np.random.default_rng(4))
    order = [int(np.argmin(np.linalg.norm(voc.centers - m, axis=1))) for m in means]
    assert sorted(order) == [0, 1, 2]
    for k in range(3):
        np.testing.assert_allclose(voc.centers[order[k]], data[labels == k].mean(axis=0), atol=1e-3)


def test_build_is_deterministic_under_a_seed(descriptors):
    a = Vocabulary.build(descriptors, 24, np.random.default_rng(5))
    b = Vocabulary.build(descriptors, 24, np.random.default_rng(5))
    c = Vocabulary.build(descriptors, 24, np.random.default_rng(6))
    np.testing.assert_array_equal(a.centers, b.centers)
    assert not np.array_equal(a.centers, c.centers)


def test_save_load_round_trip(tmp_path, descriptors):
    voc = Vocabulary.build(descriptors, 16, np.random.default_rng(7))
    path = tmp_path / "vocab.npz"
    voc.save(path)
    back = Vocabulary.load(path)
    assert back.centers.dtype == np.float32
    np.testing.assert_array_equal(back.centers, voc.centers)
    np.testing.assert_array_equal(back.words(descriptors), voc.words(descriptors))


def test_errors(tmp_path, descriptors):
    with pytest.raises(ModelError, match="needs >= 50 descriptors"):
        Vocabulary.build(descriptors[:10], 50, np.random.default_rng(0))
    with pytest.raises(ModelError, match=r"\(F, 128\)"):
        Vocabulary(np.zeros((4, 64)))
    with pytest.raises(ModelError, match="at least one word"):
        Vocabulary(np.zeros((0, DESCRIPTOR_SIZE)))
    voc = Vocabulary(descriptors[:5])
    with pytest.raises(ModelError, match="finite"):
        voc.words(np.full((2, DESCRIPTOR_SIZE), np.nan))
    with pytest.raises(DataError, match="cannot read"):
        Vocabulary.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, other=np.zeros(3))
    with pytest.raises(DataError, match="cannot read"):
        Vocabulary.load(bad)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, centers=np.zeros((3, 5)))
    with pytest.raises(DataError, match="no valid vocabulary"):
        Vocabulary.load(wrong)
    with pytest.raises(ModelError, match="shape"):
        sift_descriptors(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ModelError, match="dtype"):
        sift_descriptors(np.zeros((4, 4), np.int32))
