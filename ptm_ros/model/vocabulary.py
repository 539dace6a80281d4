"""SIFT bag-of-words histograms of panoramas (thesis Ch. 4.3).

Each panorama is reduced to the SIFT descriptors of its keypoints (:func:`sift_descriptors`); a
:class:`Vocabulary` of ``V`` "appearance words" is the k-means quantisation of descriptors pooled over
many panoramas (:meth:`Vocabulary.build`); a panorama's measurement is then the ``(V,)`` histogram of the
nearest word of each descriptor (:meth:`Vocabulary.words`), modelled by the multivariate Pólya model of
:mod:`ptm_ros.model.appearance`. The thesis detected Harris-affine and MSER regions; here OpenCV's own SIFT
detector (difference of Gaussians) provides keypoints and descriptors.

Panoramas wrap around in azimuth: :func:`sift_descriptors` pads the image circularly so that a keypoint
on the seam is found once, whatever the heading. OpenCV is imported inside the functions that need it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from ptm_ros.errors import DataError, ModelError

#: Length of a SIFT descriptor.
DESCRIPTOR_SIZE = 128


def sift_descriptors(
    image: ArrayLike,
    *,
    max_features: int = 0,
    contrast_threshold: float = 0.04,
    wrap: bool = True,
) -> NDArray[np.float32]:
    """SIFT descriptors ``(F, 128)`` float32 of a panorama (``F`` may be 0).

    Args:
        image: ``(H, W)`` or ``(H, W, 3)`` RGB, uint8 or float in [0, 1] (clipped, scaled to 0–255).
        max_features: keep the ``max_features`` strongest keypoints (0 = all).
        contrast_threshold: OpenCV's DoG contrast threshold (larger = fewer, stronger keypoints).
        wrap: treat the columns as a full circle of azimuth: the image is padded circularly by
            ``min(W, H)`` columns on each side and only keypoints centred in the original columns kept.

    Raises:
        ModelError: wrong shape or dtype, non-finite values, or bad settings.
    """
    import cv2

    if max_features < 0 or not contrast_threshold > 0.0:
        msg = f"need max_features >= 0 and contrast_threshold > 0, got {max_features}, {contrast_threshold}"
        raise ModelError(msg)
    grey = _grey_uint8(np.asarray(image))
    height, width = grey.shape
    pad = min(width, height) if wrap else 0
    padded = np.concatenate([grey[:, width - pad :], grey, grey[:, :pad]], axis=1) if pad else grey
    sift = cv2.SIFT.create(nfeatures=0, contrastThreshold=contrast_threshold)
    keypoints, descriptors = sift.detectAndCompute(np.ascontiguousarray(padded), None)
    if descriptors is None or not keypoints:
        return np.zeros((0, DESCRIPTOR_SIZE), dtype=np.float32)
    xs = np.array([kp.pt[0] for kp in keypoints])
    keep = np.flatnonzero((xs >= pad) & (xs < pad + width))
    if max_features and keep.size > max_features:
        response = np.array([keypoints[int(i)].response for i in keep])
        keep = np.sort(keep[np.argsort(-response, kind="stable")[:max_features]])
    return np.ascontiguousarray(descriptors[keep], dtype=np.float32)


def _grey_uint8(img: NDArray[np.generic]) -> NDArray[np.uint8]:
    """``(H, W)`` uint8 grey image of a mono or RGB uint8/float image (BT.601 luma)."""
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)) or img.size == 0:
        msg = f"image must have shape (H, W), (H, W, 1) or (H, W, 3), got {img.shape}"
        raise ModelError(msg)
    if img.dtype == np.uint8:
        data = img.astype(np.float64)
    elif np.issubdtype(img.dtype, np.floating):
        if not np.all(np.isfinite(img)):
            msg = "image holds non-finite values"
            raise ModelError(msg)
        data = np.clip(img.astype(np.float64), 0.0, 1.0) * 255.0
    else:
        msg = f"image dtype must be uint8 or float, got {img.dtype}"
        raise ModelError(msg)
    if data.ndim == 3:
        data = data[:, :, 0] if data.shape[2] == 1 else data @ np.array([0.299, 0.587, 0.114])
    return np.clip(np.rint(data), 0, 255).astype(np.uint8)


def _descriptors(descriptors: ArrayLike, name: str = "descriptors") -> NDArray[np.float32]:
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_SIZE or not np.all(np.isfinite(d)):
        msg = f"{name} must be a finite (F, {DESCRIPTOR_SIZE}) array, got shape {d.shape}"
        raise ModelError(msg)
    return d


def _kmeans_pp(data: NDArray[np.float32], size: int, rng: np.random.Generator) -> NDArray[np.float32]:
    """k-means++ seeding (Arthur & Vassilvitskii 2007), O(size · F · 128)."""
    sq_norm = np.einsum("ij,ij->i", data, data, dtype=np.float64)
    centers = np.empty((size, data.shape[1]), dtype=np.float32)
    first = int(rng.integers(len(data)))
    centers[0] = data[first]
    best = np.maximum(sq_norm - 2.0 * (data @ data[first]) + sq_norm[first], 0.0)
    for j in range(1, size):
        total = best.sum()
        pick = int(rng.integers(len(data))) if total <= 0.0 else int(rng.choice(len(data), p=best / total))
        centers[j] = data[pick]
        dist = np.maximum(sq_norm - 2.0 * (data @ data[pick]) + sq_norm[pick], 0.0)
        np.minimum(best, dist, out=best)
    return centers


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A visual vocabulary: ``V`` word centres in SIFT descriptor space, shape ``(V, 128)`` float32."""

    centers: NDArray[np.float32]
    _tree: cKDTree = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        centers = _descriptors(self.centers, "vocabulary centers")
        if centers.shape[0] == 0:
            msg = "a vocabulary needs at least one word"
            raise ModelError(msg)
        object.__setattr__(self, "centers", centers)
        object.__setattr__(self, "_tree", cKDTree(centers.astype(np.float64)))

    @property
    def size(self) -> int:
        """Number of words V."""
        return int(self.centers.shape[0])

    @classmethod
    def build(
        cls, descriptors: ArrayLike, size: int, rng: np.random.Generator, *, iterations: int = 20
    ) -> Vocabulary:
        """k-means vocabulary of ``size`` words from pooled descriptors ``(F, 128)``, ``F >= size``.

        k-means++ seeding from ``rng``, then ``iterations`` Lloyd steps of
        :func:`scipy.cluster.vq.kmeans2`; a cluster that empties keeps its previous centre. Deterministic
        for a given ``rng`` state.
        """
        data = _descriptors(descriptors)
        if size < 1 or data.shape[0] < size:
            msg = f"a vocabulary of {size} words needs >= {max(size, 1)} descriptors, got {data.shape[0]}"
            raise ModelError(msg)
        if iterations < 1:
            msg = f"iterations must be >= 1, got {iterations}"
            raise ModelError(msg)
        seeds = _kmeans_pp(data, size, rng)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="One of the clusters is empty")
            centers, _ = kmeans2(data, seeds, iter=iterations, minit="matrix", missing="warn")
        return cls(np.asarray(centers, dtype=np.float32))

    def save(self, path: str | Path) -> None:
        """Write the centres to ``path`` (.npz, exactly that file name)."""
        with Path(path).open("wb") as fh:
            np.savez(fh, centers=self.centers)

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        """Read a vocabulary written by :meth:`save`.

        Raises:
            DataError: the file is missing, not an .npz, or holds no valid ``centers``.
        """
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                centers = np.asarray(data["centers"])
        except (OSError, ValueError, KeyError) as err:
            msg = f"cannot read a vocabulary from {path}: {err}"
            raise DataError(msg) from err
        try:
            return cls(centers)
        except ModelError as err:
            msg = f"{path} holds no valid vocabulary: {err}"
            raise DataError(msg) from err

    def quantize(self, descriptors: ArrayLike) -> NDArray[np.int64]:
        """Index of the nearest word (Euclidean) of each descriptor, shape ``(F,)``."""
        d = _descriptors(descriptors)
        if d.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        _, idx = self._tree.query(d.astype(np.float64))
        return np.asarray(idx, dtype=np.int64)

    def words(self, descriptors: ArrayLike) -> NDArray[np.int64]:
        """Bag-of-words histogram ``(V,)``: how many descriptors fall nearest to each word."""
        return np.bincount(self.quantize(descriptors), minlength=self.size).astype(np.int64)

    def panorama_words(
        self,
        image: ArrayLike,
        *,
        max_features: int = 0,
        contrast_threshold: float = 0.04,
        wrap: bool = True,
    ) -> NDArray[np.int64]:
        """:meth:`words` of the :func:`sift_descriptors` of a panorama (same options)."""
        descriptors = sift_descriptors(
            image, max_features=max_features, contrast_threshold=contrast_threshold, wrap=wrap
        )
        return self.words(descriptors)
