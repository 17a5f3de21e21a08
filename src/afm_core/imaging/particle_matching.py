"""Particles as features of the drift methods: found by thresholding the height above the
substrate, given a region (bounding box plus margin), and matched between two images of the
same area (book 3.2.3.1).

The match starts from the integer shift that maximises the FFT cross-correlation of the two
images, pairs mutually nearest centroids, and refines an affine map fitted to the pairs (a
translation while they do not span a plane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

MIN_FEATURE_PIXELS = 9  # smaller blobs above the threshold are noise


@dataclass
class Blob:
    """A particle: its label slice, height-weighted centroid, peak and feature region."""

    label_slice: tuple
    centroid: np.ndarray  # (row, col), height-weighted over the part above half height
    peak: float
    window: tuple = ()  # (r0, r1, c0, c1), half-open, region with margin


def _background(height: np.ndarray):
    bg = float(np.median(height))
    dev = np.abs(height - bg)
    noise = 1.4826 * float(np.median(dev))
    return bg, noise


def find_blobs(height: np.ndarray, threshold: float | None = None) -> tuple[list, float]:
    """Particles: connected regions above the substrate by more than a threshold (default:
    from the image's noise and highest peak). Returns them and the threshold."""
    bg, noise = _background(height)
    rel = height - bg
    peak = float(np.max(rel))
    if threshold is None:
        threshold = max(10.0 * noise, 0.1 * peak, 1e-9)
    labels, n = ndimage.label(rel > threshold)
    blobs = []
    for index, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        mask = labels[sl] == index
        if mask.sum() < MIN_FEATURE_PIXELS:
            continue
        part = np.where(mask, rel[sl], 0.0)
        top = float(part.max())
        if top < 2.0 * threshold:
            continue
        w = np.clip(part - 0.5 * top, 0.0, None)
        rr, cc = np.mgrid[sl[0], sl[1]]
        centroid = np.array([(w * rr).sum(), (w * cc).sum()]) / w.sum()
        blobs.append(Blob(sl, centroid, top))
    return blobs, threshold


def global_shift(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Integer (row, col) shift of b against a by FFT cross-correlation: b(x + s) ~ a(x)."""
    fa = np.fft.rfft2(a - a.mean())
    fb = np.fft.rfft2(b - b.mean())
    xc = np.fft.irfft2(np.conj(fa) * fb, a.shape)
    ny, nx = a.shape
    limit_r, limit_c = ny // 4, nx // 4
    rr = np.fft.fftfreq(ny, 1.0 / ny)
    cc = np.fft.fftfreq(nx, 1.0 / nx)
    allowed = (np.abs(rr)[:, None] <= limit_r) & (np.abs(cc)[None, :] <= limit_c)
    xc = np.where(allowed, xc, -np.inf)
    i, j = np.unravel_index(int(np.argmax(xc)), xc.shape)
    return np.array([rr[i], cc[j]])


def match_blobs(src: list, dst: list, shift: np.ndarray):
    """Pairs (i, j) of blobs src[i] ~ dst[j]: translation first, then an affine fit refined twice.
    Returns the pairs and the affine (A, b) with dst ~ A src + b (in (row, col) pixels)."""
    if not src or not dst:
        return [], np.eye(2), shift
    ps = np.array([b.centroid for b in src])
    pd = np.array([b.centroid for b in dst])
    A, b = np.eye(2), shift.astype(float)
    spacing = _min_spacing(ps)
    pairs = []
    for _ in range(3):
        pred = ps @ A.T + b
        d = np.linalg.norm(pred[:, None, :] - pd[None, :, :], axis=2)
        j = np.argmin(d, axis=1)
        i_back = np.argmin(d, axis=0)
        gate = 0.4 * spacing if np.isfinite(spacing) else np.inf
        pairs = [(i, int(j[i])) for i in range(len(ps)) if i_back[j[i]] == i and d[i, j[i]] < gate]
        src_pts = np.array([ps[i] for i, _ in pairs]).reshape(-1, 2)
        if len(pairs) >= 3 and _spans_a_plane(src_pts):
            dst_pts = np.array([pd[k] for _, k in pairs])
            design = np.hstack([src_pts, np.ones((len(pairs), 1))])
            sol, *_ = np.linalg.lstsq(design, dst_pts, rcond=None)
            A, b = sol[:2].T, sol[2]
        elif pairs:
            b = np.mean([pd[k] - ps[i] for i, k in pairs], axis=0)
    return pairs, A, b


def _spans_a_plane(points: np.ndarray) -> bool:
    """Whether points fix an affine map: not (nearly) on one line, where the fit would be free
    in the direction across it."""
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(singular[0] > 0 and singular[-1] > 0.1 * singular[0])


def _min_spacing(points: np.ndarray) -> float:
    if len(points) < 2:
        return np.inf
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    d[np.diag_indices(len(points))] = np.inf
    return float(d.min())


def feature_windows(blobs: list, shape) -> list:
    """Feature regions: each blob's bounding box plus a margin, kept if inside the image."""
    ny, nx = shape
    kept = []
    for blob in blobs:
        sr, sc = blob.label_slice
        size = max(sr.stop - sr.start, sc.stop - sc.start)
        margin = max(4, int(math.ceil(0.3 * size)))
        r0, r1, c0, c1 = sr.start - margin, sr.stop + margin, sc.start - margin, sc.stop + margin
        if r0 < 2 or c0 < 2 or r1 > ny - 2 or c1 > nx - 2:
            continue  # a particle cut by the image edge is no reliable feature
        blob.window = (r0, r1, c0, c1)
        kept.append(blob)
    return kept
