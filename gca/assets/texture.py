"""Solid (3D) procedural colour textures keyed by a seed: rich and non-repeating, so that SIFT finds
many distinct features on every view of a rendered object.

A texture is a callable ``colour_fn(points [N, 3] m) -> rgb [N, 3] in [0, 1]``; it composes
multi-octave value noise (one hash per channel), warped stripes and random coloured blobs, all in
object-relative coordinates ``points / size``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

_HASH_PRIMES = np.array([73856093, 19349663, 83492791], dtype=np.uint64)
_TABLE_SIZE = 1 << 16


def _smoothstep(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def value_noise(points: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Trilinearly interpolated lattice noise with smoothstep weights, in [0, 1].

    Args:
        points: [N, 3] coordinates in lattice units (one lattice cell per unit).
        table: [T] random values in [0, 1]; lattice vertices are hashed into it.

    Returns:
        [N] noise values.
    """
    assert points.ndim == 2 and points.shape[1] == 3, points.shape
    base = np.floor(points)
    w = _smoothstep(points - base)
    corners = base.astype(np.int64).astype(np.uint64)  # two's complement wrap: fine for hashing
    out = np.zeros(len(points))
    for corner in range(8):
        offset = np.array([(corner >> a) & 1 for a in range(3)], dtype=np.uint64)
        key = (corners + offset) * _HASH_PRIMES
        index = (key[:, 0] ^ key[:, 1] ^ key[:, 2]) % np.uint64(len(table))
        weight = np.prod(np.where(offset.astype(bool), w, 1.0 - w), axis=1)
        out += weight * table[index.astype(np.int64)]
    return out


@dataclasses.dataclass(frozen=True)
class SolidTexture:
    """A seeded colour field around an object of a given size (picklable, deterministic).

    Attributes:
        seed: texture seed.
        size: object size [m]; the pattern scales with it.
        base_rgb: the object's dominant colour, 3 values in [0, 1].
        octaves: value-noise octaves (frequencies 2, 4, 8, ... cycles per object size).
        n_blobs: random coloured spots.
    """

    seed: int
    size: float
    base_rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    octaves: int = 5
    n_blobs: int = 40

    def _rng(self, salt: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, salt])

    def _fbm(self, u: np.ndarray, channel: int) -> np.ndarray:
        """Fractal sum of value noise in [0, 1] for one channel; u [N, 3] object units."""
        table = self._rng(100 + channel).random(_TABLE_SIZE)
        shift = self._rng(200 + channel).uniform(-50.0, 50.0, size=3)
        total, norm = np.zeros(len(u)), 0.0
        for octave in range(self.octaves):
            amplitude = 0.6**octave
            total += amplitude * value_noise(u * 2.0 ** (octave + 1) + shift, table)
            norm += amplitude
        return total / norm

    def _blobs(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Soft coloured discs: (alpha [N], rgb [N, 3])."""
        rng = self._rng(300)
        centres = rng.uniform(-0.6, 0.6, size=(self.n_blobs, 3))
        radii = rng.uniform(0.03, 0.12, size=self.n_blobs)
        colours = rng.random((self.n_blobs, 3))
        alpha, rgb = np.zeros(len(u)), np.zeros((len(u), 3))
        for c, r, col in zip(centres, radii, colours):
            a = np.clip(2.0 - 2.0 * np.linalg.norm(u - c, axis=1) / r, 0.0, 1.0)
            rgb = rgb * (1 - a[:, None]) + col * a[:, None]
            alpha = np.maximum(alpha, a)
        return alpha, rgb

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Colours at points.

        Args:
            points: [N, 3] positions [m] in the object's frame.

        Returns:
            [N, 3] RGB in [0.02, 0.98].
        """
        points = np.asarray(points, dtype=np.float64)
        assert points.ndim == 2 and points.shape[1] == 3, points.shape
        u = points / self.size
        noise = np.stack([self._fbm(u, c) for c in range(3)], axis=1)
        rgb = np.asarray(self.base_rgb) + 1.2 * (noise - 0.5)
        direction = self._rng(400).normal(size=3)
        phase = 14.0 * u @ (direction / np.linalg.norm(direction)) + 6.0 * noise[:, 0]
        rgb *= (0.55 + 0.45 * (np.sin(phase) > 0.3))[:, None]
        alpha, blob_rgb = self._blobs(u)
        rgb = rgb * (1 - alpha[:, None]) + blob_rgb * alpha[:, None]
        return np.clip(rgb, 0.02, 0.98)
